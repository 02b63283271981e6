"""Iterated extended and sigma-point (posterior-linearisation) smoothers, parallel in time:
:class:`IteratedSmoother` (Yaghoobi, Corenflos, Hassan & Särkkä 2021, "Parallel iterated
extended and sigma-point Kalman smoothers")."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from ..filters.base import Belief, RecursiveFilter
from ..filters.diffuse import total_cov
from ..filters.ekf import EKF
from ..filters.kalman import KalmanFilter
from ..filters.parallel import ParallelKalmanFilter
from ..filters.sigma_points import SigmaPoints
from ..filters.ukf import UKF, expand_controls
from ..linalg import psd_solve, symmetrize
from ..models.affine import TimeVaryingLinearModel
from ..models.base import Controls, StateSpaceModel
from ..threads import scoped_forward
from .base import Smoother, flatten_steps
from .parallel import ParallelRTSSmoother
from .result import SmootherResult
from .rts import RTSSmoother

__all__ = ["IteratedSmoother", "statistical_linearisation"]

_METHODS = ("extended", "sigma")


def _mv(a: Tensor, x: Tensor) -> Tensor:
    return (a @ x[..., None])[..., 0]


def statistical_linearisation(
    fn: Callable[[Tensor], Tensor], points: Tensor, wm: Tensor, wc: Tensor, mean: Tensor, cov: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Statistical linear regression of ``y = fn(x)`` under ``x ~ N(mean [N, n], cov)`` from
    sigma ``points [N, S, n]`` with weights ``wm, wc [S]``: ``(A [N, k, n], b [N, k],
    Omega [N, k, k])`` with ``A = Psi^T P^{-1}``, ``b = E[y] - A mean``,
    ``Omega = Cov(y) - A P A^T`` (``Psi = Cov(x, y)``)."""
    y = fn(points)
    ybar = (wm[:, None] * y).sum(-2)
    dx = (points - mean[..., None, :]) * wc[:, None]
    dy = y - ybar[..., None, :]
    psi = dx.mT @ dy  # [N, n, k]
    a = psd_solve(symmetrize(cov), psi).mT
    omega = symmetrize((dy * wc[:, None]).mT @ dy - a @ cov @ a.mT)
    return a, ybar - _mv(a, mean), omega


class IteratedSmoother(Smoother):
    """Iterated extended (IEKS) or sigma-point / posterior-linearisation (IPLS) RTS smoother.

    Starting from the sequential filter's trajectory (:class:`~difffilter.filters.EKF` for
    ``method="extended"``, :class:`~difffilter.filters.UKF` for ``"sigma"``), each of
    ``iterations`` passes linearises the model around the previous pass's smoothed trajectory
    ``(x̄_k, P̄_k)``, ``k = -1 .. T-1``, and smooths the resulting affine-Gaussian model exactly:

    * ``"extended"``: ``f(x) ~ f(x̄) + F (x - x̄)`` with ``F = df/dx(x̄_{t-1})``, noise ``Q``;
      ``h`` likewise at ``x̄_t`` (Gauss-Newton on the trajectory's MAP: the fixed point is the
      MAP trajectory);
    * ``"sigma"``: statistical linear regression of ``f`` under ``N(x̄_{t-1}, P̄_{t-1})`` with
      the filter's sigma points, ``f(x) ~ A x + b`` with the regression error ``Omega`` added to
      ``Q`` (:func:`statistical_linearisation`); ``h`` likewise under ``N(x̄_t, P̄_t)``.

    With ``parallel=True`` each pass is :class:`~difffilter.filters.ParallelKalmanFilter` and
    :class:`~difffilter.smoothers.ParallelRTSSmoother` (two scans, ``O(log T)`` depth); with
    ``parallel=False`` the sequential :class:`~difffilter.filters.KalmanFilter` and
    :class:`~difffilter.smoothers.RTSSmoother` on the same linearised model (the reference).
    The number of passes is fixed (no data-dependent stopping), so the smoother is batched and
    differentiable: gradients flow through every linearisation to the model's parameters.
    The result's ``filtered`` (and its ``log_likelihood``) is the last pass's filter on the
    linearised model.  Additive noise only; angular components are refused.

    The starting filter and, with ``parallel=False``, each pass's sequential filter are plain
    filter calls: the engine policy applies to them (:mod:`difffilter.engines.policy`; on the
    CPU a large or repeated call runs the compiled engine, same values to ~1e-13,
    ``DIFFFILTER_ENGINE=eager`` turns it off).  The scans never run compiled, and neither does
    anything under ``torch.func`` transforms (:mod:`difffilter.func`).

    Args:
        model: the nonlinear state-space model.
        method: ``"extended"`` or ``"sigma"``.
        iterations: relinearisation passes ``>= 1``.
        sigma_points: for ``"sigma"`` (default: the UKF's).
        parallel: scan each pass (True) or run it sequentially (False).

    Learnable: the model's parameters.
    """

    def __init__(
        self,
        model: StateSpaceModel,
        *,
        method: str = "extended",
        iterations: int = 10,
        sigma_points: SigmaPoints | None = None,
        parallel: bool = True,
    ) -> None:
        if method not in _METHODS:
            raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
            raise ValueError(f"iterations must be an int >= 1, got {iterations!r}")
        if not (model.dynamics.additive_noise and model.measurement.additive_noise):
            raise ValueError("IteratedSmoother needs additive process and measurement noise")
        if model.dynamics.angular or model.measurement.angular:
            raise ValueError("IteratedSmoother cannot wrap angular components")
        filt: RecursiveFilter = EKF(model) if method == "extended" else UKF(model, sigma_points=sigma_points)
        super().__init__(filt)
        self.method, self.iterations, self.parallel = method, iterations, bool(parallel)
        affine = TimeVaryingLinearModel(state_dim=model.state_dim, measurement_dim=model.measurement_dim)
        self.linear: Smoother = ParallelRTSSmoother(ParallelKalmanFilter(affine)) if parallel else RTSSmoother(KalmanFilter(affine))

    def linearise(self, mean: Tensor, cov: Tensor, controls: Controls) -> dict[str, Tensor]:
        """The affine model around the trajectory ``mean [B, T+1, n]``, ``cov`` (``x_{-1}`` first):
        ``{"F", "c", "Q", "H", "d", "R"}`` ``[B, T, ...]`` for
        :class:`~difffilter.models.TimeVaryingLinearModel`."""
        bsz, t1, n = mean.shape
        steps = t1 - 1
        filt = self.filter
        model = filt.model
        u = flatten_steps(controls, 0, steps)
        prev, cur = mean[:, :-1].reshape(-1, n), mean[:, 1:].reshape(-1, n)
        if self.method == "extended":
            f = filt.transition_jacobian(prev, u).expand(bsz * steps, n, n)  # type: ignore[operator]
            c = model.dynamics(prev, u) - _mv(f, prev)
            q = filt.process_noise_cov(prev, u)  # type: ignore[operator]
            h = filt.measurement_jacobian(cur, u)  # type: ignore[operator]
            h = h.expand(bsz * steps, *h.shape[-2:])
            d = model.measurement(cur, u) - _mv(h, cur)
            r = filt.measurement_noise_cov(cur, u)  # type: ignore[operator]
        else:
            ukf: UKF = filt  # type: ignore[assignment]
            wm, wc = ukf._weights(n, mean)
            u1 = expand_controls(u)
            pcov, ccov = cov[:, :-1].reshape(-1, n, n), cov[:, 1:].reshape(-1, n, n)
            f, c, omega_f = statistical_linearisation(lambda x: model.dynamics(x, u1), ukf._points(prev, pcov), wm, wc, prev, pcov)
            h, d, omega_h = statistical_linearisation(lambda x: model.measurement(x, u1), ukf._points(cur, ccov), wm, wc, cur, ccov)
            q0, r0 = ukf._noise_matrices(prev, u)
            q, r = symmetrize(q0 + omega_f), symmetrize(r0.expand_as(omega_h) + omega_h)
        m = h.shape[-2]
        shape = lambda x, *tail: x.expand(bsz * steps, *tail).reshape(bsz, steps, *tail)  # noqa: E731
        return {"F": shape(f, n, n), "c": shape(c, n), "Q": shape(q, n, n), "H": shape(h, m, n), "d": shape(d, m), "R": shape(r, m, m)}

    @scoped_forward
    def forward(
        self,
        measurements: Tensor,
        initial_mean: Tensor | None = None,
        initial_cov: Tensor | None = None,
        mask: Tensor | None = None,
        controls: Controls = None,
        *,
        belief: Belief | None = None,
    ) -> SmootherResult:
        """Smooth ``measurements [B, T, m]`` (arguments as the filters')."""
        filt = self.filter
        z, mask3, m0, p0 = filt.check_inputs(measurements, initial_mean, initial_cov, mask, controls)
        if belief is not None:
            m0, p0 = belief["mean"], total_cov(belief)
        if m0 is None or p0 is None:
            raise ValueError("initial_mean and initial_cov are required unless belief= is given")
        first = filt(z, m0, p0, mask=mask3, controls=controls)
        mean = torch.cat([m0[:, None], first.mean], 1)
        cov = torch.cat([p0[:, None], first.cov], 1)
        derived = filt.precompute_controls(controls)
        out: SmootherResult | None = None
        for _ in range(self.iterations):
            system = self.linearise(mean, cov, derived)
            out = self.linear(z, m0, p0, mask=mask3, controls=system)
            mean = torch.cat([out.initial_mean[:, None], out.mean], 1)  # type: ignore[index]
            cov = torch.cat([out.initial_cov[:, None], out.cov], 1)  # type: ignore[index]
        assert out is not None
        return out
