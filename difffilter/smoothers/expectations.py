"""Expected residual moments under the smoothed posterior: the E-step of EM for ``Q`` and ``R``.

For a model ``x_t = f(x_{t-1}, u_t) + w_t``, ``z_t = h(x_t, u_t) + v_t`` and a fixed-interval
smoother's output (:class:`~difffilter.smoothers.SmootherResult`: ``x_{t|T}``, ``P_{t|T}``, the
lag-one cross-covariance ``C_t = Cov(x_{t-1}, x_t | all)`` and the smoothed ``x_{-1}``), EM needs

.. math::
    A_t = E[(x_t - f(x_{t-1}))(x_t - f(x_{t-1}))^T],\\qquad
    M_t = E[(z_t - h(x_t))(z_t - h(x_t))^T]

under the smoothed joint Gaussian of ``(x_{t-1}, x_t)`` (mean ``[x_{t-1|T}; x_{t|T}]``,
covariance ``[[P_{t-1|T}, C_t], [C_t^T, P_{t|T}]]``) and the smoothed marginal of ``x_t``.
They are computed the way the filter approximates its model:

* Kalman filter, EKF, IteratedEKF (and SimplifiedUKF's Kalman prediction): linearised at the
  smoothed means, ``F = df/dx(x_{t-1|T})``, ``H = dh/dx(x_{t|T})``,

  .. math::
      A_t = e e^T + P_{t|T} - F C_t - C_t^T F^T + F P_{t-1|T} F^T,\\ e = x_{t|T} - f(x_{t-1|T}),
      \\qquad M_t = r r^T + H P_{t|T} H^T,\\ r = z_t - h(x_{t|T}),

  which is exact for linear models (then EM is exact and its likelihood never decreases);
* the UKF family: the filter's sigma-point rule applied to the ``2n``-dimensional joint Gaussian
  for ``A_t`` and to ``N(x_{t|T}, P_{t|T})`` for ``M_t`` (the second moment
  ``sum_i wc_i (e_i - e)(e_i - e)^T + e e^T`` of the residuals ``e_i`` of the points).

For nonlinear models both are approximations of the true expectations (the E-step itself is
approximate, since the smoother's Gaussian is).  Angular components are differenced with the
model's ``residual`` (wrapped).  Missing measurement components (``mask`` False) get zero rows
and columns in ``M_t`` (their values, NaN allowed, are never read).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor
from torch.nn.utils import parametrize

from ..filters.base import RecursiveFilter
from ..filters.ekf import EKF
from ..filters.ukf import UKF, expand_controls, weighted_mean
from ..linalg import symmetrize
from ..models.base import Controls
from .base import MAX_CHUNK_STATES, flatten_steps
from .result import SmootherResult
from .transition import is_unscented, predicting_filter

__all__ = ["measurement_residual_moments", "observed_components", "previous_smoothed", "transition_residual_moments"]


def previous_smoothed(smoothed: SmootherResult) -> tuple[Tensor, Tensor]:
    """``(x_{t-1|T}, P_{t-1|T})`` for ``t = 0..T-1`` ``[B, T, n]``, ``[B, T, n, n]``: the smoothed
    state before the first measurement, then the smoothed states shifted by one step."""
    if smoothed.initial_mean is None or smoothed.initial_cov is None or smoothed.cross_cov is None:
        raise ValueError("smoothed must come from a fixed-interval smoother (RTSSmoother): it needs initial_mean and cross_cov")
    mean = torch.cat([smoothed.initial_mean[:, None], smoothed.mean[:, :-1]], 1)
    cov = torch.cat([smoothed.initial_cov[:, None], smoothed.cov[:, :-1]], 1)
    return mean, cov


def observed_components(mask: Tensor | None, shape: tuple[int, int, int], device: torch.device) -> Tensor:
    """``mask`` (``None``, ``[B, T]`` or ``[B, T, m]``) as a bool ``[B, T, m]`` (True = observed)."""
    bsz, steps, m = shape
    if mask is None:
        return torch.ones(bsz, steps, m, dtype=torch.bool, device=device)
    if mask.dtype != torch.bool:
        raise TypeError(f"mask must be a bool tensor, got {mask.dtype}")
    if mask.shape == (bsz, steps):
        return mask[..., None].expand(bsz, steps, m)
    if mask.shape != (bsz, steps, m):
        raise ValueError(f"mask must have shape [B, T] = [{bsz}, {steps}] or [B, T, m] = [{bsz}, {steps}, {m}], got {tuple(mask.shape)}")
    return mask


def _second_moment(res: Tensor, wm: Tensor, wc: Tensor) -> Tensor:
    """``sum_i wc_i (e_i - e)(e_i - e)^T + e e^T`` of residual points ``res [N, S, d]``."""
    mean = weighted_mean(res, wm)
    dev = res - mean[..., None, :]
    return symmetrize((dev * wc[:, None]).mT @ dev + mean[..., :, None] * mean[..., None, :])


def _per_step(fn: Callable[..., Tensor], tensors: list[Tensor], controls: Controls, time_chunk: int | None) -> Tensor:
    """``fn(*flat tensors, flat controls)`` over all ``[B, T]`` steps in chunks of time steps."""
    bsz, steps = tensors[0].shape[:2]
    chunk = time_chunk or max(1, MAX_CHUNK_STATES // bsz)
    outs = []
    with parametrize.cached():
        for start in range(0, steps, chunk):
            stop = min(start + chunk, steps)
            flat = [x[:, start:stop].reshape(-1, *x.shape[2:]) for x in tensors]
            out = fn(*flat, flatten_steps(controls, start, stop))
            outs.append(out.reshape(bsz, stop - start, *out.shape[1:]))
    return torch.cat(outs, 1)


def _transition_matrix(filt: RecursiveFilter, mean: Tensor, u: Controls) -> Tensor:
    if isinstance(filt, EKF):
        return filt.transition_jacobian(mean, u)
    matrix = filt.model.dynamics.matrix(u)  # SimplifiedUKF: linear dynamics
    if matrix is None:
        raise TypeError(f"{type(filt).__name__}: the dynamics give no transition matrix to linearise with")
    return matrix


def transition_residual_moments(
    filt: RecursiveFilter, smoothed: SmootherResult, controls: Controls = None, *, time_chunk: int | None = None
) -> Tensor:
    """``A_t = E[(x_t - f(x_{t-1}, u_t))(...)^T | all]`` ``[B, T, n, n]`` (module docstring).

    Args:
        filt: the filter that was smoothed (its model and approximation are used).
        smoothed: a fixed-interval :class:`SmootherResult` of ``filt``.
        controls: the run's per-step inputs ``[B, T, ...]``.
        time_chunk: time steps per batched call (memory bound; results do not depend on it).
    """
    pf = predicting_filter(filt)
    dyn = pf.model.dynamics
    prev_mean, prev_cov = previous_smoothed(smoothed)
    n = prev_mean.shape[-1]
    assert smoothed.cross_cov is not None
    if is_unscented(pf):
        ukf: UKF = pf  # type: ignore[assignment]

        def unscented(pm: Tensor, pp: Tensor, m: Tensor, p: Tensor, c: Tensor, u: Controls) -> Tensor:
            joint_mean = torch.cat([pm, m], -1)
            joint_cov = torch.cat([torch.cat([pp, c], -1), torch.cat([c.mT, p], -1)], -2)
            pts = ukf._points(joint_mean, symmetrize(joint_cov))
            wm, wc = ukf._weights(2 * n, joint_mean)
            res = dyn.residual(pts[..., n:], dyn(pts[..., :n], expand_controls(u)))
            return _second_moment(res, wm, wc)

        return _per_step(unscented, [prev_mean, prev_cov, smoothed.mean, smoothed.cov, smoothed.cross_cov], controls, time_chunk)

    def linearised(pm: Tensor, pp: Tensor, m: Tensor, p: Tensor, c: Tensor, u: Controls) -> Tensor:
        jac = _transition_matrix(pf, pm, u).expand(pm.shape[0], n, n)
        e = dyn.residual(m, dyn(pm, u))
        fc = jac @ c
        return symmetrize(e[..., :, None] * e[..., None, :] + p - fc - fc.mT + jac @ pp @ jac.mT)

    return _per_step(linearised, [prev_mean, prev_cov, smoothed.mean, smoothed.cov, smoothed.cross_cov], controls, time_chunk)


def measurement_residual_moments(
    filt: RecursiveFilter,
    smoothed: SmootherResult,
    measurements: Tensor,
    mask: Tensor | None = None,
    controls: Controls = None,
    *,
    time_chunk: int | None = None,
) -> Tensor:
    """``M_t = E[(z_t - h(x_t, u_t))(...)^T | all]`` ``[B, T, m, m]``, zero in the rows and columns
    of missing components (``mask [B, T]`` or ``[B, T, m]``, False = missing)."""
    pf = predicting_filter(filt)
    meas = pf.model.measurement
    bsz, steps, m = measurements.shape
    obs = observed_components(mask, (bsz, steps, m), measurements.device)
    z = torch.where(obs, measurements, torch.zeros_like(measurements))
    n = smoothed.mean.shape[-1]
    if isinstance(pf, UKF):
        ukf: UKF = pf

        def unscented(mean: Tensor, cov: Tensor, zt: Tensor, u: Controls) -> Tensor:
            pts = ukf._points(mean, symmetrize(cov))
            wm, wc = ukf._weights(n, mean)
            res = meas.residual(zt[..., None, :], meas(pts, expand_controls(u)))
            return _second_moment(res, wm, wc)

        out = _per_step(unscented, [smoothed.mean, smoothed.cov, z], controls, time_chunk)
    else:
        ekf: EKF = pf  # type: ignore[assignment]

        def linearised(mean: Tensor, cov: Tensor, zt: Tensor, u: Controls) -> Tensor:
            h = ekf.measurement_jacobian(mean, u).expand(mean.shape[0], m, n)
            r = meas.residual(zt, meas(mean, u))
            return symmetrize(r[..., :, None] * r[..., None, :] + h @ cov @ h.mT)

        out = _per_step(linearised, [smoothed.mean, smoothed.cov, z], controls, time_chunk)
    both = obs[..., :, None] & obs[..., None, :]
    return torch.where(both, out, torch.zeros_like(out))
