"""Every core filter runs the shared battery of tests/filter_contract.py."""

from __future__ import annotations

import torch

from difffilter.filters import EKF, UKF, Cubature, Julier, KalmanFilter, MerweScaled, SimplifiedUKF, SquareRootUKF

from .filter_contract import FilterContract, make_data


class TestKalmanFilter(FilterContract):
    def make_filter(self, model):
        return KalmanFilter(model)


class TestEKF(FilterContract):
    def make_filter(self, model):
        return EKF(model)


class TestEKFReverseMode(FilterContract):
    def make_filter(self, model):
        # FunctionalModel-like autodiff path: hide the analytic Jacobians of the linear model
        flt = EKF(model, jacobian_mode="rev")
        flt.transition_jacobian = lambda x, u: _autodiff(flt, model.dynamics, x, u)
        flt.measurement_jacobian = lambda x, u: _autodiff(flt, model.measurement, x, u)
        return flt


def _autodiff(flt, fn, x, u):
    from difffilter.filters.ekf import autodiff_jacobian

    return autodiff_jacobian(fn, x, u, mode=flt.jacobian_mode)


class TestUKFMerweRedraw(FilterContract):
    def make_filter(self, model):
        return UKF(model, sigma_points=MerweScaled(alpha=0.5, beta=2.0, kappa=0.0))


class TestUKFMerweSmallAlphaReuse(FilterContract):
    # |W0| ~ 1e6: the log-likelihood carries ~1e-9 rounding noise, which central differences
    # with eps = 1e-6 turn into ~1e-3 noise (measured analytic/numeric gap 2e-4).
    gradcheck_atol = 2e-3

    def make_filter(self, model):
        return UKF(model, sigma_points=MerweScaled(alpha=1e-3, beta=2.0, kappa=1.0), redraw_after_predict=False)

    def test_float32_matches_float64(self):
        # alpha = 1e-3 puts the points 1e-3 standard deviations from the mean: in float32 the
        # deviations keep ~3 significant digits (measured: 7e-2 relative error in the mean), so
        # this is not a well-conditioned float32 case.  Require a finite, sane float32 run only;
        # float64 agreement with the closed-form KF is checked by the rest of the battery.
        model32 = self.linear_model(dtype=torch.float32)
        z = make_data(2, 20, 2, seed=7).float()
        res = self.make_filter(model32)(z, torch.zeros(4), torch.eye(4) * 2)
        assert torch.isfinite(res.mean).all() and torch.isfinite(res.log_likelihood).all()
        assert (res.mean[..., [0, 2]] - z).abs().max() < 10.0


class TestUKFJulierReuse(FilterContract):
    def make_filter(self, model):
        return UKF(model, sigma_points=Julier(kappa=-1.0), redraw_after_predict=False)


class TestUKFCubatureAugmented(FilterContract):
    def make_filter(self, model):
        return UKF(model, sigma_points=Cubature(), noise="augmented")


class TestUKFJulierAugmentedReuse(FilterContract):
    def make_filter(self, model):
        return UKF(model, sigma_points=Julier(kappa=1.0), noise="augmented", redraw_after_predict=False)


class TestSimplifiedUKF(FilterContract):
    def make_filter(self, model):
        return SimplifiedUKF(model, sigma_points=MerweScaled(alpha=1.0, beta=0.0, kappa=0.0))


class TestSquareRootUKF(FilterContract):
    def make_filter(self, model):
        return SquareRootUKF(model, sigma_points=MerweScaled(alpha=0.5))


class TestSquareRootUKFNegativeCenter(FilterContract):
    def make_filter(self, model):
        return SquareRootUKF(model, sigma_points=Julier(kappa=-1.0))
