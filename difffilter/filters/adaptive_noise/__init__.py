"""Adaptive noise-estimating filters around the library's Gaussian filters (KF, EKF, UKF):
Sage–Husa, variational-Bayes (R; predicted covariance and R) and covariance matching, with
their hyperparameters learnable by back-propagation (see docs/adaptive.md)."""

from .base import AdaptiveNoiseFilter
from .covariance_matching import CovarianceMatching
from .sage_husa import SageHusa
from .vb import VBAdaptiveQR, VBAdaptiveR

__all__ = ["AdaptiveNoiseFilter", "CovarianceMatching", "SageHusa", "VBAdaptiveQR", "VBAdaptiveR"]
