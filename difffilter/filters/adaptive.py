"""Residual-constrained fading-memory UKF (p002's RC-UKF)."""

from __future__ import annotations

import torch
from torch import Tensor

from ..linalg import symmetrize
from ..models.base import Controls, StateSpaceModel
from ..params import Bounded, Positive, register_constrained
from ._common import expand_controls
from .base import Belief, StepInfo
from .diffuse import DIFFUSE_COV, DIFFUSE_SCALE
from .jacobians import measurement_matrix
from .sigma_points import SigmaPoints
from .ukf import UKF, deviations, weighted_mean

__all__ = ["RCUKF"]


class RCUKF(UKF):
    """Unscented Kalman filter with a residual-driven fading factor (p002).

    The belief carries the residual covariance estimate ``C0 [B, m, m]`` (zero before the
    first measurement, so the first steps are not faded).  At step ``k``, with the ordinary
    UKF prediction ``x-``, ``P- = S + Q`` (``S`` the propagated sigma-point spread):

    1. points of ``N(x-, P-)`` give ``z^``, the spread ``Pzz - R = sum wc dz dz^T`` and the
       residual ``eps = z - z^`` of the *un-faded* prediction;
    2. ``C0_k = (rho C0_{k-1} + eps eps^T) / (1 + rho)`` on the observed components (a
       component pair not observed at ``k`` keeps its previous value, so ``C0`` is unchanged
       when nothing is observed);
    3. the fading factor
       ``eta_k = min(cap, max(1, tr_o(C0_k - R_k) / tr_o(Pzz_k - R_k)))``, traces ``tr_o`` over
       the observed components (``eta = 1`` when nothing is observed);
    4. the prediction is inflated as in p002, ``P-_faded = Lambda S Lambda + Q`` (Q is not
       inflated): scalar (``per_state=False``) ``P-_faded = P- + (eta - 1) S``; per state,
       ``Lambda = diag(sqrt(eta_i))`` so that the variance of state ``i`` is scaled by
       ``eta_i``;
    5. the standard UKF update is recomputed from ``(x-, P-_faded)`` (points redrawn).

    ``eta = 1`` leaves ``P-`` bit-for-bit unchanged, so the filter then *is* the UKF.  The max
    and min are hard (differentiable almost everywhere: gradient 1 or 0).

    Per-state factors (the paper's diagonal ``Lambda``; its formula was lost): each measurement
    component ``j`` gives ``eta^z_j = max(1, (C0_jj - R_jj) / (Pzz_jj - R_jj))`` and state ``i``
    takes ``eta_i = 1 + max_j r_ij^2 (eta^z_j - 1)`` with ``r_ij^2 = Pxz_ij^2 / (P_ii Pzz_jj)``
    the squared correlation between state ``i`` and component ``j`` (so states the measurements
    do not see are not faded), then the cap.  The factor per step is recorded as
    ``result.fading_factor`` (``[B, T]``, or ``[B, T, n]`` per state).

    Args:
        model: the state-space model (additive noise).
        sigma_points: sigma-point set (default of :class:`UKF`).
        rho: forgetting factor, learnable ``Bounded(0, 1)`` (p002's ``(0, 1]``).
        fading_cap: ``None`` (no cap) or an upper bound ``> 1`` on ``eta``, learnable
            ``Positive(floor=1)``.
        per_state: diagonal fading matrix instead of a scalar factor.

    Learnable: the model's parameters, ``rho``, ``fading_cap``.
    """

    memory_keys = ("residual_cov",)
    record_keys = ("fading_factor",)

    def __init__(
        self,
        model: StateSpaceModel,
        *,
        sigma_points: SigmaPoints | None = None,
        rho: float = 0.95,
        fading_cap: float | None = None,
        per_state: bool = False,
    ) -> None:
        super().__init__(model, sigma_points=sigma_points, redraw_after_predict=True, noise="additive")
        dtype = self._param_dtype() or torch.get_default_dtype()
        if not 0.0 < rho <= 1.0:
            raise ValueError(f"rho must lie in (0, 1], got {rho}")
        register_constrained(self, "rho", torch.tensor(float(rho), dtype=dtype), Bounded(0.0, 1.0))
        if fading_cap is not None:
            if not fading_cap > 1.0:
                raise ValueError(f"fading_cap must exceed 1 (or be None), got {fading_cap}")
            register_constrained(self, "fading_cap", torch.tensor(float(fading_cap), dtype=dtype), Positive(floor=1.0))
        self.has_cap = fading_cap is not None
        self.per_state = bool(per_state)

    def init_belief(self, mean: Tensor, cov: Tensor) -> Belief:
        m = self.measurement_dim
        return {"mean": mean, "cov": cov, "residual_cov": mean.new_zeros(mean.shape[0], m, m)}

    def predict(self, belief: Belief, u: Controls) -> Belief:
        out = super().predict(belief, u)
        q = self.model.dynamics.process_noise(belief["mean"], u)
        out["process_noise"] = q.expand_as(out["cov"])
        return out

    def fading_factor(self, residual_cov: Tensor, spread_zz: Tensor, r: Tensor, pxz: Tensor, cov: Tensor, mask: Tensor | None) -> Tensor:
        """``eta [B]`` (or ``[B, n]`` per state) from ``C0_k``, ``Pzz - R``, ``R``, ``Pxz``,
        the prior ``P-`` and the mask ``[B, m]`` (see the class docstring)."""
        obs = torch.ones_like(r[..., 0]) if mask is None else mask.to(r.dtype)
        excess = (torch.diagonal(residual_cov, dim1=-2, dim2=-1) - torch.diagonal(r, dim1=-2, dim2=-1)) * obs
        sdiag = torch.diagonal(spread_zz, dim1=-2, dim2=-1) * obs
        tiny = torch.finfo(r.dtype).tiny
        if not self.per_state:
            eta = torch.clamp(excess.sum(-1) / sdiag.sum(-1).clamp_min(tiny), min=1.0)
        else:
            eta_z = torch.clamp(excess / sdiag.clamp_min(tiny), min=1.0)  # [B, m]
            pzz_diag = torch.diagonal(spread_zz + r, dim1=-2, dim2=-1)
            corr2 = pxz**2 / (torch.diagonal(cov, dim1=-2, dim2=-1)[..., :, None] * pzz_diag[..., None, :]).clamp_min(tiny)
            eta = 1.0 + (corr2 * (eta_z - 1.0)[..., None, :]).amax(-1)
        if self.has_cap:
            eta = torch.minimum(eta, self.fading_cap)
        return eta

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        belief = dict(belief)
        mean, cov = belief["mean"], belief["cov"]
        q = belief.pop("process_noise", None)
        spread = cov - q if q is not None else cov
        hm = self.model.measurement
        n = mean.shape[-1]
        wm, wc = self._weights(n, mean)
        chi = self._points(mean, cov)
        zeta = hm(chi, expand_controls(u))
        zhat = weighted_mean(zeta, wm, hm)
        dz = hm.residual(zeta, zhat[..., None, :])
        spread_zz = (dz * wc[:, None]).mT @ dz
        pxz = (wc[:, None] * deviations(chi, mean, self.model.dynamics)).mT @ dz
        r = hm.measurement_noise(mean, u)
        r = r.expand(*mean.shape[:-1], *r.shape[-2:])
        eps = hm.residual(z, zhat)
        c_prev = belief["residual_cov"]
        rho = self.rho
        c_new = (rho * c_prev + eps[..., :, None] * eps[..., None, :]) / (1.0 + rho)
        if mask is not None:
            c_new = torch.where(mask[..., :, None] & mask[..., None, :], c_new, c_prev)
        if DIFFUSE_COV in belief:
            # the diffuse part is all spread: it enters the ratios at its full size and is faded too
            p_inf, kappa = belief[DIFFUSE_COV], belief[DIFFUSE_SCALE][..., None, None]
            h = measurement_matrix(hm, mean, u)
            eta = self.fading_factor(c_new, spread_zz + kappa * h @ p_inf @ h.mT, r, pxz + kappa * p_inf @ h.mT, cov + kappa * p_inf, mask)
        else:
            eta = self.fading_factor(c_new, spread_zz, r, pxz, cov, mask)
        scale = (eta.sqrt()[..., :, None] * eta.sqrt()[..., None, :]) if self.per_state else eta[..., None, None]
        faded = cov + (scale - 1.0) * spread
        if DIFFUSE_COV in belief:
            belief[DIFFUSE_COV] = symmetrize(scale * belief[DIFFUSE_COV])
        post, info = super().update({**belief, "cov": symmetrize(faded)}, z, mask, u)
        post["residual_cov"] = c_new
        post["fading_factor"] = eta
        return post, info
