"""The shared filter battery (tests/filter_contract.py) on the adaptive noise-estimating filters
with their estimation switched off: the wrappers' own prediction, moments, update, masks, belief
carry-over and step must then reproduce the closed-form Kalman filter exactly, around each inner
filter.  (With estimation on they are checked against numpy references in
tests/test_adaptive_noise_reference.py.)"""

from __future__ import annotations

from difffilter.filters import EKF, UKF, CovarianceMatching, KalmanFilter, MerweScaled, SageHusa

from .filter_contract import FilterContract


class TestSageHusaFrozenKF(FilterContract):
    def make_filter(self, model):
        return SageHusa(KalmanFilter(model), b=0.9, adapt_r=False, adapt_q=False)


class TestSageHusaFrozenEKF(FilterContract):
    def make_filter(self, model):
        return SageHusa(EKF(model, joseph=False), b=0.9, adapt_r=False)


class TestCovarianceMatchingFrozenUKF(FilterContract):
    def make_filter(self, model):
        return CovarianceMatching(UKF(model, sigma_points=MerweScaled(alpha=0.5, beta=2.0, kappa=0.0)), window=5.0, adapt_r=False)
