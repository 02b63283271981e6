"""Square-root unscented Kalman filter (p001)."""

from __future__ import annotations

import torch
from torch import Tensor

from ..linalg import chol_rank1_update, gaussian_log_density, psd_sqrt, tria
from ..models.base import Controls, StateSpaceModel
from ._common import expand_controls
from .base import Belief, StepInfo, diffuse_gaussian_update, mask_measurement_system
from .diffuse import DIFFUSE_COV, propagate_diffuse
from .jacobians import measurement_matrix
from .sigma_points import SigmaPoints
from .ukf import UKF, centred_points, deviations, linear_image, linear_space, offset_untrusted, state_add, weighted_mean
from .update import rounding_terms

__all__ = ["SquareRootUKF"]


class SquareRootUKF(UKF):
    """UKF that propagates the lower Cholesky factor ``S`` (``P = S S^T``) instead of ``P``.

    Predict: points from ``(x, S)``; ``S- = tria([sqrt(wc_i) dchi_i]_{i>=1}, sqrt(Q))`` followed
    by a rank-1 Cholesky update (``wc_0 > 0``) or downdate (``wc_0 < 0``, e.g. Julier with
    ``n + kappa < n``) with ``sqrt|wc_0| dchi_0``.  Update: ``S_zz`` likewise from the measurement
    deviations and ``sqrt(R)``; ``K = P_xz S_zz^{-T} S_zz^{-1}`` by two triangular solves; the
    posterior factor is re-triangularised in Joseph form,
    ``S+ = tria([sqrt(wc_i) (dchi_i - K dzeta_i)], K sqrt(R))`` (plus the centre point's rank-1
    update/downdate), which equals ``P- - K P_zz K^T`` exactly and never needs the ``m``
    successive downdates of the textbook form.  ``P`` is never factorised again, so it stays
    positive definite in cases where the covariance form loses definiteness.

    The belief carries ``"scale_tril"``; ``"cov"`` is recorded as ``S S^T``.  Always redraws the
    update points from ``(x-, S-)``, additive noise only.  Learnable: the model's parameters.
    """

    def __init__(self, model: StateSpaceModel, *, sigma_points: SigmaPoints | None = None) -> None:
        super().__init__(model, sigma_points=sigma_points, redraw_after_predict=True, noise="additive")

    def init_belief(self, mean: Tensor, cov: Tensor) -> Belief:
        return {"mean": mean, "cov": cov, "scale_tril": psd_sqrt(cov).factor}

    def _compound(self, dev: Tensor, wc: Tensor, extra: Tensor) -> Tensor:
        """Lower factor of ``sum_i wc_i dev_i dev_i^T + extra extra^T`` (``dev [B, S, d]``)."""
        if self.sigma_points.has_center:
            rest = dev[..., 1:, :] * wc[1:, None].sqrt()
            s = tria(torch.cat([rest.mT, extra], -1))
            w0 = wc[0]
            return chol_rank1_update(s, w0.abs().sqrt() * dev[..., 0, :], torch.sign(w0))
        return tria(torch.cat([(dev * wc[:, None].sqrt()).mT, extra], -1))

    def predict(self, belief: Belief, u: Controls) -> Belief:
        mean, s = belief["mean"], belief["scale_tril"]
        n = mean.shape[-1]
        wm, wc = self._weights(n, mean)
        dyn = self.model.dynamics
        lin = linear_space(dyn, u)
        if lin is not None:  # exact deviations, however large the mean (ukf.linear_image)
            xm, dev = linear_image(dyn, mean, centred_points(self.sigma_points, s), u, lin)
        else:
            prop = dyn(self.sigma_points.generate(mean, s), expand_controls(u))
            xm = weighted_mean(prop, wm, dyn)
            dev = deviations(prop, xm, dyn)
        q = dyn.process_noise(mean, u)
        sq = psd_sqrt(q.expand(*mean.shape[:-1], n, n)).factor
        s_new = self._compound(dev, wc, sq)
        out = {**belief, "mean": xm, "cov": s_new @ s_new.mT, "scale_tril": s_new}
        propagate_diffuse(belief, out, None, self.model, u)
        return out

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        mean, s = belief["mean"], belief["scale_tril"]
        n = mean.shape[-1]
        wm, wc = self._weights(n, mean)
        hm = self.model.measurement
        lin = linear_space(hm, u)
        exact = lin is not None
        if lin is not None:
            dx = centred_points(self.sigma_points, s)
            zhat, dz = linear_image(hm, mean, dx, u, lin)
        else:
            chi = self.sigma_points.generate(mean, s)
            zeta = hm(chi, expand_controls(u))
            zhat = weighted_mean(zeta, wm, hm)
            dz = hm.residual(zeta, zhat[..., None, :])
            dx = deviations(chi, mean, self.model.dynamics)
        add = state_add(self.model.dynamics)
        r = hm.measurement_noise(mean, u)
        r = r.expand(*mean.shape[:-1], *r.shape[-2:])
        e = hm.residual(z, zhat)
        m = e.shape[-1]
        if DIFFUSE_COV in belief:
            post, info = diffuse_gaussian_update(belief, e, (dx, dz, wc, r), mask, obs_matrix=measurement_matrix(hm, mean, u), add=add)
            rest = {k: v for k, v in belief.items() if k not in post and k != "scale_tril"}
            return {**rest, **post, "scale_tril": psd_sqrt(post["cov"]).factor}, info
        e, r, dz, num_obs = mask_measurement_system(e, r, dz, mask)
        sr = psd_sqrt(r).factor
        szz = self._compound(dz, wc, sr)
        pxz = (dx * wc[:, None]).mT @ dz
        tmp = torch.linalg.solve_triangular(szz, pxz.mT, upper=False)
        gain = torch.linalg.solve_triangular(szz.mT, tmp, upper=True).mT  # [B, n, m]
        correction = (gain @ e[..., None])[..., 0]
        new_mean = mean + correction if add is None else add(mean, correction)
        joseph_dev = dx - dz @ gain.mT
        s_new = self._compound(joseph_dev, wc, gain @ sr)
        loglik, maha = gaussian_log_density(e, szz)
        # Missing components contribute log N(0; 0, 1) each in the padded system: remove it.
        loglik = loglik + 0.5 * (m - num_obs) * torch.log(torch.tensor(2.0 * torch.pi, dtype=e.dtype))
        pzz = szz @ szz.mT
        # the gain's weak directions: P_xz and S are rounded apart, so K e keeps ~eps cond(S)
        whitened = torch.linalg.solve_triangular(szz.detach(), e.detach()[..., None], upper=False)[..., 0]
        # the rounding check deferred (StepInfo.flags), as in gaussian_update
        rounding = rounding_terms(szz, whitened, pzz, zhat, mask)
        own = None if exact else offset_untrusted(mean, s @ s.mT, zhat, pzz, maha)
        info = StepInfo(loglik, maha, num_obs, e, pzz, own, rounding=rounding)
        out = {k: v for k, v in belief.items() if k not in ("mean", "cov", "scale_tril")}
        return {**out, "mean": new_mean, "cov": s_new @ s_new.mT, "scale_tril": s_new}, info
