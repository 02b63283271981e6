"""Cross-covariance of a filter's prediction, computed the way the filter predicts.

A Rauch-Tung-Striebel backward step needs, besides the filter's posterior and prior, the
cross-covariance ``C = Cov(x_{t-1}, x_t | z_{0:t-1})`` between the posterior at ``t - 1`` and
the prediction to ``t``.  :func:`transition_cross_covariance` computes it with the same
approximation the filter's prediction uses:

* :class:`~difffilter.filters.EKF` / :class:`~difffilter.filters.KalmanFilter` (and
  :class:`~difffilter.filters.SimplifiedUKF`, whose prediction is the Kalman one): ``C = P F^T``
  with the filter's transition Jacobian (or ``F``) at the posterior mean;
* :class:`~difffilter.filters.UKF` and its subclasses (``SquareRootUKF``, ``RCUKF``): the
  unscented transform of the prediction, ``C = sum_i wc_i (chi_i - x)(f(chi_i) - x-)^T`` over
  the same sigma points (Sarkka's unscented RTS smoother), with the augmented points
  ``[x; w(; v)]`` when the filter uses ``noise="augmented"``; for a linear ``f`` with additive
  noise (:func:`~difffilter.filters.ukf.linear_space`) the transform is exact and, as in the
  filter's prediction, computed without points: ``C = P F^T`` for the base rule's points;
* :class:`~difffilter.filters.SequentialUpdate`: the wrapped filter's.

Everything is batched over the leading dimension, so a smoother evaluates all ``B * T`` steps
of a window in one call.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..filters.base import RecursiveFilter
from ..filters.colored import ColoredNoiseUKF
from ..filters.ekf import EKF
from ..filters.sequential import SequentialUpdate
from ..filters.ukf import UKF, SimplifiedUKF, centred_points, deviations, expand_controls, linear_space, second_moment_exact, weighted_mean
from ..linalg import block_diag, psd_sqrt
from ..models.base import Controls
from .base import flatten_steps

__all__ = ["check_smoothable", "is_unscented", "needs_points", "predicting_filter", "transition_cross_covariance"]


def predicting_filter(filt: RecursiveFilter) -> RecursiveFilter:
    """The filter whose prediction ``filt`` runs (a :class:`SequentialUpdate`'s wrapped filter)."""
    while isinstance(filt, SequentialUpdate):
        filt = filt.filter
    return filt


def check_smoothable(filt: RecursiveFilter) -> None:
    """Raise ``TypeError`` unless :func:`transition_cross_covariance` supports ``filt``."""
    filt = predicting_filter(filt)
    if isinstance(filt, ColoredNoiseUKF):
        raise TypeError(
            "ColoredNoiseUKF cannot be smoothed: its prediction couples the state with the previous step's "
            "coloured measurement noise, which the RTS backward step over the state alone does not model"
        )
    if not isinstance(filt, EKF | UKF):
        raise TypeError(
            f"RTS smoothing needs a KalmanFilter, EKF, IteratedEKF, UKF, SimplifiedUKF, SquareRootUKF or RCUKF; got {type(filt).__name__} "
            "(IMM: use IMMSmoother)"
        )


def is_unscented(filt: RecursiveFilter) -> bool:
    """Whether the filter's prediction is an unscented transform (not SimplifiedUKF's Kalman one)."""
    filt = predicting_filter(filt)
    return isinstance(filt, UKF) and not isinstance(filt, SimplifiedUKF)


def needs_points(filt: RecursiveFilter, controls: Controls) -> bool:
    """Whether the cross-covariance of ``filt`` may need more memory than its inputs (sigma points,
    or an EKF's Jacobians by automatic differentiation), so that a smoother computes it in time
    chunks; False for the product ``P F^T`` of a linear prediction (a KalmanFilter or
    SimplifiedUKF, or a UKF whose ``f`` is linear with additive noise)."""
    filt = predicting_filter(filt)
    if not is_unscented(filt):
        return isinstance(filt, EKF)
    return filt.noise != "additive" or linear_space(filt.model.dynamics, flatten_steps(controls, 0, 1)) is None  # type: ignore[union-attr]


def _linear_transition(filt: RecursiveFilter, mean: Tensor, u: Controls) -> Tensor:
    if isinstance(filt, EKF):
        return filt.transition_jacobian(mean, u)
    dyn = filt.model.dynamics
    joint = getattr(dyn, "linear_prediction", None)
    return joint(mean, u)[1] if callable(joint) else dyn.matrix(u)


def _unscented_cross(filt: UKF, mean: Tensor, cov: Tensor, u: Controls) -> Tensor:
    n = mean.shape[-1]
    dyn = filt.model.dynamics
    u1 = expand_controls(u)
    lin = linear_space(dyn, u) if filt.noise == "additive" else None
    if lin is not None:
        # a linear f: the transform is exact, as in the filter's own prediction; with the base
        # rule's points the weighted second moment of the deviations is P itself, so C = P F^T
        # (no square root, no points: the smoother's gains over B * T steps cost one product)
        if second_moment_exact(filt.sigma_points):
            return cov @ lin.mT
        wc = filt._weights(n, mean)[1]
        dev = centred_points(filt.sigma_points, psd_sqrt(cov).factor)
        return (dev * wc[:, None]).mT @ (dev @ lin.mT)
    if filt.noise == "additive":
        chi = filt._points(mean, cov)
        wm, wc = filt._weights(n, mean)
        prop = dyn(chi, u1)
    else:
        # the filter's augmented prediction points: [x; w] (and v when it reuses them)
        q = dyn.process_noise(mean, u)
        q = q.expand(*mean.shape[:-1], *q.shape[-2:])
        blocks = [cov, q]
        if not filt.redraw_after_predict:
            r = filt.model.measurement.measurement_noise(mean, u)
            blocks.append(r.expand(*mean.shape[:-1], *r.shape[-2:]))
        aug_cov = block_diag(*blocks)
        aug_mean = torch.cat([mean, mean.new_zeros(*mean.shape[:-1], aug_cov.shape[-1] - n)], -1)
        full = filt._points(aug_mean, aug_cov)
        wm, wc = filt._weights(aug_cov.shape[-1], mean)
        chi = full[..., :n]
        prop = dyn.with_noise(chi, full[..., n : n + q.shape[-1]], u1)
    # angular states: circular mean and wrapped deviations, as in the filter's prediction
    pred = weighted_mean(prop, wm, dyn)
    dx = deviations(chi, mean, dyn) * wc[:, None]
    return dx.mT @ deviations(prop, pred, dyn)


def transition_cross_covariance(filt: RecursiveFilter, mean: Tensor, cov: Tensor, u: Controls) -> Tensor:
    """``Cov(x_{t-1}, x_t) [N, n, n]`` of the filter's prediction from ``N(mean [N, n], cov)``.

    ``u`` are the controls of the predicted step (leading dimension ``N``, as in a filter
    step).  See the module docstring for the approximation used per filter family.
    """
    check_smoothable(filt)
    filt = predicting_filter(filt)
    if is_unscented(filt):
        return _unscented_cross(filt, mean, cov, u)  # type: ignore[arg-type]
    return cov @ _linear_transition(filt, mean, u).mT
