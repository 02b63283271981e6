"""Unscented Kalman filters: the general UKF and the simplified UKF of p003."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import torch
from torch import Tensor

from ..linalg import block_diag, psd_sqrt, symmetrize
from ..models.angular import check_angular_declaration
from ..models.base import Controls, DynamicsModel, MeasurementModel, StateSpaceModel, wrap_components
from ._common import expand_controls
from .base import Belief, RecursiveFilter, StepInfo, diffuse_gaussian_update, gaussian_update
from .diffuse import DIFFUSE_COV, propagate_diffuse
from .jacobians import measurement_matrix
from .sigma_points import MerweScaled, SigmaPoints
from .update import JosephForm

__all__ = [
    "UKF",
    "SimplifiedUKF",
    "centred_points",
    "deviations",
    "linear_image",
    "linear_space",
    "second_moment_exact",
    "offset_untrusted",
    "state_add",
    "weighted_mean",
    "weighted_moments",
]

#: What the unscented helpers need to know of a state or measurement space: a model part
#: (``DynamicsModel`` or ``MeasurementModel``) with ``angular`` indices and ``residual``.
Space = DynamicsModel | MeasurementModel | None


def weighted_mean(points: Tensor, wm: Tensor, space: Space = None) -> Tensor:
    """``sum_i wm_i points_i`` for weights summing to one, computed as
    ``p_0 + sum_i wm_i (p_i - p_0)``: large centre weights (scaled sets with small alpha have
    ``|W_0| ~ 1e6``) then multiply exact zeros instead of cancelling in float32.

    When ``space`` declares angular components, the differences are ``space.residual(p_i, p_0)``
    (wrapped) and the result is wrapped: a circular mean around the reference point ``p_0``,
    exact for points within ``pi`` of it, whatever the sign of the weights (a weighted sum of
    sines and cosines would be biased by a negative centre weight)."""
    ref = points[..., :1, :]
    if space is None or not space.angular:
        return ref[..., 0, :] + ((points - ref) * wm[:, None]).sum(-2)
    shift = (space.residual(points, ref) * wm[:, None]).sum(-2)
    return wrap_components(ref[..., 0, :] + shift, space.angular)


def deviations(points: Tensor, mean: Tensor, space: Space = None) -> Tensor:
    """``points [B, S, d] - mean [B, d]``, through ``space.residual`` for angular components."""
    if space is None or not space.angular:
        return points - mean[..., None, :]
    return space.residual(points, mean[..., None, :])


def weighted_moments(points: Tensor, wm: Tensor, wc: Tensor, space: Space = None) -> tuple[Tensor, Tensor, Tensor]:
    """Weighted mean ``[B, d]``, deviations ``[B, S, d]`` and covariance ``[B, d, d]`` of points ``[B, S, d]``."""
    mean = weighted_mean(points, wm, space)
    dev = deviations(points, mean, space)
    cov = (dev * wc[:, None]).mT @ dev
    return mean, dev, cov


def linear_space(space: Space, u: Controls) -> Tensor | None:
    """The matrix ``M`` of a model part that is linear at these inputs (``space.matrix(u)`` is
    not None) and has plain differences (additive noise, no angular components, no overridden
    ``residual``/``add``), else None."""
    if space is None or space.angular or not space.additive_noise:
        return None
    base = DynamicsModel if isinstance(space, DynamicsModel) else MeasurementModel
    diff = "add" if isinstance(space, DynamicsModel) else "residual"
    if type(space).matrix is base.matrix or getattr(type(space), diff) is not getattr(base, diff):
        return None
    return space.matrix(u)


def centred_points(sigma_points: SigmaPoints, sqrt_cov: Tensor) -> Tensor:
    """Deviations ``chi_i - x`` ``[..., S, n]`` of the sigma points from their centre, formed
    directly from the square root (``0, +-gamma L_i``): no digits lost to a large mean."""
    return sigma_points.generate(sqrt_cov.new_zeros(sqrt_cov.shape[:-1]), sqrt_cov)


def linear_image(space: DynamicsModel | MeasurementModel, mean: Tensor, dev: Tensor, u: Controls, matrix: Tensor) -> tuple[Tensor, Tensor]:
    """``(f(x), dev M^T)`` for a part with :func:`linear_space` matrix ``M``: the unscented
    transform of a linear map, exact (the images' weighted mean is ``f(x)`` because the
    deviations of a symmetric point set cancel exactly), whatever the size of ``x`` against the
    spread."""
    return space(mean, u), dev @ matrix.mT


def offset_untrusted(mean: Tensor, cov: Tensor, zhat: Tensor, pzz: Tensor, maha: Tensor) -> Tensor:
    """``[B]`` steps whose sigma-point deviations lost too many digits to a large mean: points
    ``x +- gamma L_i`` of a mean ``|x|`` carry absolute errors ``eps |x|``, so deviations of a
    spread ``sigma`` keep a relative accuracy ``eps |x| / sigma`` (likewise the measurement
    images), and the gain's error reaches the posterior mean multiplied by the innovation in
    standard deviations ``sqrt(NIS)``.  Flagged where that product exceeds ``1e-2``."""
    eps = torch.finfo(mean.dtype).eps
    tiny = torch.finfo(mean.dtype).tiny
    sx = torch.diagonal(cov, dim1=-2, dim2=-1).clamp_min(tiny).sqrt()
    sz = torch.diagonal(pzz, dim1=-2, dim2=-1).clamp_min(tiny).sqrt()
    loss = torch.maximum((mean.abs() / sx).amax(-1), (zhat.abs() / sz).amax(-1)) * eps
    return ~(loss * maha.clamp_min(1.0).sqrt() <= 1e-2)


def second_moment_exact(points: SigmaPoints) -> bool:
    """Whether ``points`` are the base rule's ``0, +-gamma L_i`` with covariance weights
    ``1 / (2 gamma^2)`` off the centre (every set here: Julier, MerweScaled, Cubature), whose
    weighted second moment of the deviations is ``L L^T`` exactly; a subclass with its own
    points or weights is not assumed to be."""
    cls = type(points)
    return cls.generate is SigmaPoints.generate and cls.weights is SigmaPoints.weights


def state_add(space: DynamicsModel) -> Callable[[Tensor, Tensor], Tensor] | None:
    """``space.add`` for a state with angular components, else None (plain addition)."""
    return space.add if space.angular else None


class UKF(RecursiveFilter):
    """Unscented Kalman filter with a choice of sigma points, noise handling and point reuse.

    Predict (additive noise): points ``chi_i`` of ``N(x, P)``, ``x- = sum wm_i f(chi_i)``,
    ``P- = sum wc_i (f(chi_i) - x-)(...)^T + Q``.  Update: points ``zeta_i = h(chi_i)``,
    ``P_zz = sum wc_i dzeta dzeta^T + R``, ``P_xz = sum wc_i dchi dzeta^T``, then the shared
    Gaussian update (gain by triangular solves, ``P = P- - K P_zz K^T``).

    Args:
        model: the state-space model.
        sigma_points: :class:`~difffilter.filters.sigma_points.Julier`, ``MerweScaled`` or
            ``Cubature``.  Default ``MerweScaled(alpha=1, beta=2, kappa=0)`` (points at
            ``+-sqrt(n)`` standard deviations): small ``alpha`` such as 1e-3 places the points so
            close to the mean that float32 deviations keep only ~3 digits.
        redraw_after_predict: True draws the update's points from ``N(x-, P-)``.  False reuses
            the propagated points (p000).  With additive noise the propagated points do not
            carry ``Q``, so they are extended by ``2n`` points ``x- +- gamma sqrt(Q)_i`` with
            covariance weight ``1 / (2 gamma^2)`` and mean weight 0: the measurement moments then
            see the full ``P-`` and the filter stays exact on linear-Gaussian models.
        noise: ``"additive"`` (``2n + 1`` points in ``n`` dimensions, the p003 "AUKF") or
            ``"augmented"`` (noise appended to the state: ``[x; w]`` for the prediction and
            ``[x; v]`` for a redrawn update, or ``[x; w; v]`` when reusing points, p003's
            augmented UKF).  The noise points pass through the model's ``with_noise``: ``f(x) + w``
            for additive models, ``f(x, w, u)`` / ``h(x, v, u)`` for models that declare
            non-additive noise (:class:`~difffilter.models.noise.NonAdditiveModel`), which
            need ``"augmented"``.

    Learnable: the model's parameters (Q, R, ...).
    """

    def __init__(
        self,
        model: StateSpaceModel,
        *,
        sigma_points: SigmaPoints | None = None,
        redraw_after_predict: bool = True,
        noise: str = "additive",
    ) -> None:
        super().__init__(model)
        if noise not in ("additive", "augmented"):
            raise ValueError(f"noise must be 'additive' or 'augmented', got {noise!r}")
        if noise == "additive" and not (model.dynamics.additive_noise and model.measurement.additive_noise):
            raise ValueError("the model declares non-additive noise (f(x, w, u) or h(x, v, u)): use UKF(..., noise='augmented')")
        check_angular_declaration(model.dynamics)
        check_angular_declaration(model.measurement)
        self.sigma_points = sigma_points if sigma_points is not None else MerweScaled(alpha=1.0, beta=2.0, kappa=0.0)
        self.redraw_after_predict = bool(redraw_after_predict)
        self.noise = noise

    # -- helpers -----------------------------------------------------------------------------
    def _weights(self, dim: int, like: Tensor) -> tuple[Tensor, Tensor]:
        return self.sigma_points.weights(dim, like.dtype, like.device)

    def _points(self, mean: Tensor, cov: Tensor) -> Tensor:
        return self.sigma_points.generate(mean, psd_sqrt(cov).factor)

    def _noise_matrices(self, mean: Tensor, u: Controls) -> tuple[Tensor, Tensor]:
        q = self.model.dynamics.process_noise(mean, u)
        r = self.model.measurement.measurement_noise(mean, u)
        return q.expand(*mean.shape[:-1], *q.shape[-2:]), r.expand(*mean.shape[:-1], *r.shape[-2:])

    # -- predict -----------------------------------------------------------------------------
    def predict(self, belief: Belief, u: Controls) -> Belief:
        mean, cov = belief["mean"], belief["cov"]
        n = mean.shape[-1]
        u1 = expand_controls(u)
        f = self.model.dynamics
        q, r = self._noise_matrices(mean, u)
        out: Belief = dict(belief)
        lin = linear_space(f, u) if self.noise == "additive" and self.redraw_after_predict else None
        if lin is not None and second_moment_exact(self.sigma_points):
            # the points' weighted second moment is P itself (weights 1 / (2 gamma^2) on 0, +-gamma L_i),
            # so the transform of a linear map is F P F^T: no square root, no points
            xm, new_cov = f(mean, u), symmetrize(lin @ cov @ lin.mT + q)
        elif lin is not None:
            wm, wc = self._weights(n, mean)
            xm, dev = linear_image(f, mean, centred_points(self.sigma_points, psd_sqrt(cov).factor), u, lin)
            new_cov = symmetrize((dev * wc[:, None]).mT @ dev + q)
        elif self.noise == "additive":
            chi = self._points(mean, cov)
            wm, wc = self._weights(n, mean)
            prop = f(chi, u1)
            xm, dev, pf = weighted_moments(prop, wm, wc, f)
            new_cov = symmetrize(pf + q)
            if not self.redraw_after_predict:
                sq = psd_sqrt(q).factor.mT * self.sigma_points.gamma(n)  # rows = scaled columns
                ext = torch.cat([prop, xm[..., None, :] + sq, xm[..., None, :] - sq], -2)
                wq = torch.full((2 * n,), 0.5 / self.sigma_points.gamma(n) ** 2, dtype=wm.dtype, device=wm.device)
                out["sigma_points"] = ext
                out["sigma_wm"] = torch.cat([wm, torch.zeros_like(wq)])
                out["sigma_wc"] = torch.cat([wc, wq])
        else:
            # noise dimensions q, r: those of Q and R (non-additive models may differ from n, m)
            qd, m = q.shape[-1], r.shape[-1]
            reuse = not self.redraw_after_predict
            blocks = [cov, q, r] if reuse else [cov, q]
            aug_mean = torch.cat([mean, mean.new_zeros(*mean.shape[:-1], qd + (m if reuse else 0))], -1)
            chi = self._points(aug_mean, block_diag(*blocks))
            dim = aug_mean.shape[-1]
            wm, wc = self._weights(dim, mean)
            prop = f.with_noise(chi[..., :n], chi[..., n : n + qd], u1)
            xm, dev, pf = weighted_moments(prop, wm, wc, f)
            new_cov = symmetrize(pf)
            if reuse:
                out["sigma_points"] = prop
                out["sigma_noise"] = chi[..., n + qd :]
                out["sigma_wm"], out["sigma_wc"] = wm, wc
        out["mean"], out["cov"] = xm, new_cov
        propagate_diffuse(belief, out, None, self.model, u)
        return out

    # -- update ------------------------------------------------------------------------------
    def _update_points(self, belief: Belief, u: Controls) -> tuple[Tensor, Tensor | None, Tensor, Tensor, bool]:
        """Points ``[B, S, n]``, measurement-noise samples (or None), weights, and whether R is
        still to be added to ``P_zz``."""
        mean, cov = belief["mean"], belief["cov"]
        n = mean.shape[-1]
        if "sigma_points" in belief:
            return belief["sigma_points"], belief.get("sigma_noise"), belief["sigma_wm"], belief["sigma_wc"], "sigma_noise" not in belief
        if self.noise == "augmented":
            _, r = self._noise_matrices(mean, u)
            m = r.shape[-1]
            aug_mean = torch.cat([mean, mean.new_zeros(*mean.shape[:-1], m)], -1)
            chi = self._points(aug_mean, block_diag(cov, r))
            wm, wc = self._weights(n + m, mean)
            return chi[..., :n], chi[..., n:], wm, wc, False
        wm, wc = self._weights(n, mean)
        return self._points(mean, cov), None, wm, wc, True

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        mean, cov = belief["mean"], belief["cov"]
        hm = self.model.measurement
        dyn = self.model.dynamics
        lin = linear_space(hm, u) if "sigma_points" not in belief and self.noise == "additive" else None
        exact = lin is not None
        if lin is not None:  # a linear measurement of redrawn points: deviations without a large mean
            wm, wc = self._weights(mean.shape[-1], mean)
            dx = centred_points(self.sigma_points, psd_sqrt(cov).factor)
            zhat, dz = linear_image(hm, mean, dx, u, lin)
            add_r = True
        else:
            chi, vnoise, wm, wc, add_r = self._update_points(belief, u)
            zeta = hm(chi, expand_controls(u)) if vnoise is None else hm.with_noise(chi, vnoise, expand_controls(u))
            zhat = weighted_mean(zeta, wm, hm)
            dz = hm.residual(zeta, zhat[..., None, :])
            dx = deviations(chi, mean, dyn)
        pzz = (dz * wc[:, None]).mT @ dz
        r = hm.measurement_noise(mean, u) if add_r else None
        if r is not None:
            pzz = pzz + r
        pxz = (dx * wc[:, None]).mT @ dz
        e = hm.residual(z, zhat)
        if DIFFUSE_COV in belief:
            h = measurement_matrix(hm, mean, u)
            post, info = diffuse_gaussian_update(belief, e, (dx, dz, wc, r), mask, obs_matrix=h, add=state_add(dyn))
            return {**self._carry(belief), **post}, info
        joseph = JosephForm.sigma_points(dx, dz, wc, r)
        new_mean, new_cov, info = gaussian_update(mean, cov, e, pzz, pxz, mask, joseph=joseph, add=state_add(dyn), prediction=zhat)
        if not exact:
            lossy = offset_untrusted(mean, cov, zhat, pzz, info.nis)
            info = replace(info, untrusted=lossy if info.untrusted is None else info.untrusted | lossy)
        return {"mean": new_mean, "cov": new_cov, **self._carry(belief)}, info

    @staticmethod
    def _carry(belief: Belief) -> Belief:
        """Belief entries that survive the update (everything but the predict-only points)."""
        return {k: v for k, v in belief.items() if k not in ("mean", "cov") and not k.startswith("sigma_")}


class SimplifiedUKF(UKF):
    """Simplified UKF (p003's UTCUKF): Kalman prediction, unscented update.

    For models with linear dynamics (``dynamics.matrix(u)`` returns ``F``): ``x- = f(x, u)``,
    ``P- = F P F^T + Q`` exactly as a Kalman filter, then ``2n + 1`` points drawn once from
    ``N(x-, P-)`` for the measurement update with additive ``R``.  Learnable: the model's
    parameters.

    When the dynamics offer ``linear_prediction(x, u) -> (f(x, u), F, Q)`` (e.g.
    :class:`~experiments.papers.p003.sins.SinsErrorDynamics`), the prediction takes all three from that
    one call, so a model whose ``F`` is expensive (matrix exponential) builds it once per step
    instead of once each in ``matrix``, ``process_noise`` and ``f``.
    """

    def __init__(self, model: StateSpaceModel, *, sigma_points: SigmaPoints | None = None) -> None:
        super().__init__(model, sigma_points=sigma_points, redraw_after_predict=True, noise="additive")
        if type(model.dynamics).matrix is DynamicsModel.matrix:
            raise TypeError("SimplifiedUKF needs linear dynamics: model.dynamics must implement matrix()")

    def predict(self, belief: Belief, u: Controls) -> Belief:
        mean, cov = belief["mean"], belief["cov"]
        dyn = self.model.dynamics
        joint = getattr(dyn, "linear_prediction", None)
        if callable(joint):
            xm, f, q = joint(mean, u)
        else:
            f = dyn.matrix(u)
            q = dyn.process_noise(mean, u)
            xm = dyn(mean, u)
        out = {**belief, "mean": xm, "cov": symmetrize(f @ cov @ f.mT + q)}
        propagate_diffuse(belief, out, f, self.model, u)
        return out
