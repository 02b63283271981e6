"""UKF for first-order autoregressive (coloured) measurement noise by measurement differencing (p001)."""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from ..linalg import psd_sqrt, symmetrize
from ..models.base import Controls, StateSpaceModel
from ..params import Bounded, register_constrained
from ._common import expand_controls
from .base import Belief, StepInfo, diffuse_gaussian_update, gaussian_update
from .diffuse import DIFFUSE_COV, propagate_diffuse
from .jacobians import measurement_matrix, transition_matrix
from .sigma_points import SigmaPoints
from .ukf import UKF, centred_points, deviations, linear_image, linear_space, offset_untrusted, state_add, weighted_mean, weighted_moments
from .update import JosephForm

__all__ = ["ColoredNoiseUKF"]

_PREV_U = "prev_controls"


class ColoredNoiseUKF(UKF):
    """UKF for ``z_k = h(x_k) + v_k`` with AR(1) noise ``v_k = Psi v_{k-1} + eta_k`` (p001).

    ``Psi = diag(psi)`` acts per measurement component, ``eta ~ N(0, R)`` is white (``R`` is
    the model's measurement noise).  The differenced measurement
    ``z*_{k-1} = z_k - Psi z_{k-1} = h(x_k) - Psi h(x_{k-1}) + eta_k`` has white noise.

    Timing convention (no delay): the belief at step ``k`` is the posterior of ``x_k`` given
    ``z_1..z_k`` and carries the previous measurement ``z_k``, its mask and the controls of its
    step.  Step ``k + 1`` predicts ``x_{k+1}`` with the standard unscented prediction and also
    the cross-covariance ``C = Cov(x_{k+1}, x_k) = sum wc (f(chi_i) - x-)(chi_i - x_k)^T``; the
    update runs an unscented transform of the joint ``[x_{k+1}; x_k] ~ N([x-; x_k],
    [[P-, C], [C^T, P_k]])`` through ``g(a, b) = h(a, u_{k+1}) - Psi h(b, u_k)`` and conditions
    ``x_{k+1}`` on ``z*_k`` (gain from ``Cov(a, g)``, ``Pzz = Cov(g) + R``).  For linear
    models this is the exact posterior (tested against the dense joint Gaussian).

    The joint transform uses ``4n + 1`` symmetric points along the ``2n`` columns of the
    joint's Cholesky factor (``x_{k+1}`` first), with the spread ``gamma(n)`` and non-centre
    weights of the ``n``-dimensional set and the centre weights taking the remainder
    (``wm_0 = 1 - 2n / gamma^2``, ``wc_0 = wm_0 + wc_0(n) - wm_0(n)``): a valid set for the
    ``2n``-dimensional Gaussian (mean and covariance exact) that makes ``Psi = 0`` reproduce
    the plain UKF (rounding-level).

    First step and missing previous measurements: a component whose previous value was not
    observed is updated undifferenced, ``g_j = h_j(a)``, with the stationary AR(1) noise.  The
    effective noise covariance is ``R_ij / (1 - Psi_i Psi_j)`` between two undifferenced
    components and ``R_ij`` otherwise (``Cov(eta_i, v_j) = R_ij``).  This is exact for the first
    step when ``v_1`` is stationary; after a gap it ignores the correlation with older
    measurements (documented approximation).

    Per-step coefficients: with ``psi=None`` the filter registers no ``psi`` and asks the
    measurement model for ``Psi`` at every update, ``model.measurement.ar_coefficient(u) [..., m]``
    (e.g. an elevation-dependent correlation time); the differenced measurement then uses the
    coefficient of the newer step, ``z_k - Psi_k z_{k-1}`` (``v_k = Psi_k v_{k-1} + eta_k``).

    Args:
        model: the state-space model; ``R`` is the covariance of the driving noise ``eta``.
        psi: AR coefficient(s), a float or ``[m]``, learnable ``Bounded(-1, 1)``; ``None``: from
            the measurement model per step (see above).
        sigma_points: the (``n``-dimensional) sigma-point set.

    Learnable: ``psi`` and the model's parameters.
    """

    memory_keys = ("prev_measurement", "prev_observed")

    def __init__(self, model: StateSpaceModel, *, psi: float | Tensor | None = 0.0, sigma_points: SigmaPoints | None = None) -> None:
        super().__init__(model, sigma_points=sigma_points, redraw_after_predict=True, noise="additive")
        self.psi_from_model = psi is None
        if self.psi_from_model:
            if not callable(getattr(model.measurement, "ar_coefficient", None)):
                raise TypeError("psi=None needs a measurement model with an ar_coefficient(u) method")
            return
        m = self.measurement_dim
        dtype = self._param_dtype() or torch.get_default_dtype()
        psi_t = torch.as_tensor(psi, dtype=dtype).detach().clone()
        if psi_t.ndim == 0:
            psi_t = psi_t.expand(m).clone()
        if psi_t.shape != (m,):
            raise ValueError(f"psi must be a float or a tensor of shape [{m}], got {tuple(psi_t.shape)}")
        if not bool(((psi_t > -1) & (psi_t < 1)).all()):
            raise ValueError(f"psi must lie in (-1, 1), got {psi_t.tolist()}")
        register_constrained(self, "psi", psi_t, Bounded(-1.0, 1.0))

    def ar_coefficients(self, u: Controls) -> Tensor:
        """``Psi`` of the step whose controls are ``u``: ``[m]``, or ``[..., m]`` from the
        measurement model when the filter was built with ``psi=None``."""
        if self.psi_from_model:
            return self.model.measurement.ar_coefficient(u)  # type: ignore[operator]
        return self.psi

    def init_belief(self, mean: Tensor, cov: Tensor) -> Belief:
        m = self.measurement_dim
        return {
            "mean": mean,
            "cov": cov,
            "prev_measurement": mean.new_zeros(mean.shape[0], m),
            "prev_observed": torch.zeros(mean.shape[0], m, dtype=torch.bool, device=mean.device),
        }

    def predict(self, belief: Belief, u: Controls) -> Belief:
        mean, cov = belief["mean"], belief["cov"]
        n = mean.shape[-1]
        wm, wc = self._weights(n, mean)
        dyn = self.model.dynamics
        # chi_i - x straight from the square root: subtracting a mean of size |x| from points
        # spread by sigma keeps only eps |x| / sigma of the deviations, and the cross-covariance
        # built from them is then inconsistent with P- and P_k (the joint of the update turned
        # indefinite at P0 = Q = 1e-30 and its factor fell back to the identity)
        dchi = centred_points(self.sigma_points, psd_sqrt(cov).factor)
        lin = linear_space(dyn, u)
        if lin is not None:
            xm, dev = linear_image(dyn, mean, dchi, u, lin)
            pf = (dev * wc[:, None]).mT @ dev
        else:
            chi = mean[..., None, :] + dchi
            xm, dev, pf = weighted_moments(dyn(chi, expand_controls(u)), wm, wc, dyn)
            if dyn.angular:
                dchi = deviations(chi, mean, dyn)
        q, _ = self._noise_matrices(mean, u)
        cross = (dev * wc[:, None]).mT @ dchi
        out = {**belief, "mean": xm, "cov": symmetrize(pf + q), "cross_cov": cross, "prev_mean": mean, "prev_cov": cov}
        if DIFFUSE_COV in belief:
            jac = transition_matrix(self.model.dynamics, mean, u)
            out["prev_diffuse_cov"] = belief[DIFFUSE_COV]
            out["diffuse_cross"] = jac @ belief[DIFFUSE_COV]  # Cov_inf(x_{k+1}, x_k)
            propagate_diffuse(belief, out, jac, self.model, u)
        return out

    @staticmethod
    def _previous_controls(belief: Belief, u: Controls) -> Controls:
        if u is None:
            return None
        if isinstance(u, Tensor):
            return belief.get(_PREV_U, u)
        return {k: belief.get(f"{_PREV_U}.{k}", v) for k, v in u.items()}

    @staticmethod
    def _store_controls(u: Controls) -> Belief:
        if u is None:
            return {}
        if isinstance(u, Tensor):
            return {_PREV_U: u}
        return {f"{_PREV_U}.{k}": v for k, v in u.items()}

    def _joint_points(
        self, mean_a: Tensor, mean_b: Tensor, cov_a: Tensor, cross: Tensor, cov_b: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Points ``[B, 4n+1, 2n]`` of the joint ``[a; b]``, their deviations from the centre
        (formed directly, no digits lost to a large mean), their weights (see class doc), and
        ``[B]`` whether the joint needed more than its exact semi-definite factor."""
        n = mean_a.shape[-1]
        joint = symmetrize(torch.cat([torch.cat([cov_a, cross], -1), torch.cat([cross.mT, cov_b], -1)], -2))
        root = psd_sqrt(joint)
        offsets = self.sigma_points.gamma(n) * root.factor.mT
        dev = torch.cat([torch.zeros_like(offsets[..., :1, :]), offsets, -offsets], -2)
        points = torch.cat([mean_a, mean_b], -1)[..., None, :] + dev
        wm_n, wc_n = self._weights(n, mean_a)
        wi = wm_n[-1]
        wm0 = 1.0 - 4 * n * wi
        wc0 = wm0 + (wc_n[0] - wm_n[0] if self.sigma_points.has_center else 0.0)
        rest = wi.expand(4 * n)
        return points, dev, torch.cat([wm0[None], rest]), torch.cat([wc0[None], rest]), root.jitter != 0

    def _differenced_moments(
        self, belief: Belief, points: Tensor, dev: Tensor, wm: Tensor, coef: Tensor, u: Controls
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, bool]:
        """``(za_hat, zb_hat, dg [B, S, m], dx [B, S, n], exact)`` of ``g(a, b) = h(a, u) -
        coef h(b, u_prev)`` over the joint points; a measurement linear at both steps' controls
        maps the deviations (``exact`` when the dynamics are linear too: no digits lost to the
        size of ``f``'s or ``h``'s values)."""
        hm, dyn = self.model.measurement, self.model.dynamics
        mean, n = belief["mean"], belief["mean"].shape[-1]
        u_prev = self._previous_controls(belief, u)
        h_a = linear_space(hm, u)
        h_b = linear_space(hm, u_prev) if h_a is not None else None
        dx = deviations(points[..., :n], mean, dyn) if dyn.angular else dev[..., :n]
        if h_a is not None and h_b is not None:
            # exact only where the prediction's deviations were too (linear dynamics)
            exact = linear_space(dyn, u) is not None
            za_hat, dza = linear_image(hm, mean, dev[..., :n], u, h_a)
            zb_hat, dzb = linear_image(hm, belief["prev_mean"], dev[..., n:], u_prev, h_b)
            return za_hat, zb_hat, dza - coef[..., None, :] * dzb, dx, exact
        za = hm(points[..., :n], expand_controls(u))
        zb = hm(points[..., n:], expand_controls(u_prev))
        za_hat, zb_hat = weighted_mean(za, wm, hm), weighted_mean(zb, wm, hm)
        dg = hm.residual(za, za_hat[..., None, :]) - coef[..., None, :] * hm.residual(zb, zb_hat[..., None, :])
        return za_hat, zb_hat, dg, dx, False

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        mean, cov = belief["mean"], belief["cov"]
        hm = self.model.measurement
        points, dev, wm, wc, repaired = self._joint_points(mean, belief["prev_mean"], cov, belief["cross_cov"], belief["prev_cov"])
        diff = belief["prev_observed"].to(mean.dtype)
        psi = self.ar_coefficients(u)
        coef = diff * psi  # [B, m], zero for undifferenced components
        za_hat, zb_hat, dg, dx, exact = self._differenced_moments(belief, points, dev, wm, coef, u)
        innovation = hm.residual(z, za_hat) - coef * hm.residual(belief["prev_measurement"], zb_hat)
        r = hm.measurement_noise(mean, u)
        undiff = 1.0 - diff
        pp = psi[..., :, None] * psi[..., None, :]
        r_eff = r / (1.0 - undiff[..., :, None] * undiff[..., None, :] * pp)
        pzz = (dg * wc[:, None]).mT @ dg + r_eff
        dyn = self.model.dynamics
        pxz = (wc[:, None] * dx).mT @ dg
        r_full = r_eff.expand(*mean.shape[:-1], *r_eff.shape[-2:])
        if DIFFUSE_COV in belief:
            post, info = self._diffuse_update(belief, innovation, (dx, dg, wc, r_full), coef, mask, u)
        else:
            new_mean, new_cov, info = gaussian_update(
                mean,
                cov,
                innovation,
                pzz,
                pxz,
                mask,
                joseph=JosephForm.sigma_points(dx, dg, wc, r_full),
                add=state_add(dyn),
                prediction=za_hat.abs() + (coef * zb_hat).abs(),
            )
            post = {"mean": new_mean, "cov": new_cov}
        # a joint that needed jitter (its points no longer have the belief's moments), or a
        # nonlinear measurement of points whose deviations lost digits to a large mean
        flag = repaired
        if not exact:
            flag = flag | offset_untrusted(mean, cov, za_hat, pzz, info.nis)
            flag = flag | offset_untrusted(belief["prev_mean"], belief["prev_cov"], coef * zb_hat, pzz, info.nis)
        info = replace(info, untrusted=flag if info.untrusted is None else info.untrusted | flag)
        drop = ("cross_cov", "prev_mean", "prev_cov", "prev_measurement", "prev_observed", "prev_diffuse_cov", "diffuse_cross")
        out = {k: v for k, v in belief.items() if k not in drop and not k.startswith(_PREV_U) and not k.startswith("sigma_")}
        observed = torch.ones_like(z, dtype=torch.bool) if mask is None else mask
        out.update(self._store_controls(u))
        out.update(post)
        out.update({"prev_measurement": torch.where(observed, z, torch.zeros_like(z)), "prev_observed": observed})
        return out, info

    def _diffuse_update(
        self,
        belief: Belief,
        innovation: Tensor,
        devs: tuple[Tensor, Tensor, Tensor, Tensor | None],
        coef: Tensor,
        mask: Tensor | None,
        u: Controls,
    ) -> tuple[Belief, StepInfo]:
        """Exact update of a two-part belief: the diffuse part of the differenced measurement
        ``g = h(a) - coef h(b)`` through the Jacobians of ``h`` at ``x-`` and ``x_k``."""
        hm = self.model.measurement
        mean = belief["mean"]
        h_a = measurement_matrix(hm, mean, u)
        h_b = measurement_matrix(hm, belief["prev_mean"], self._previous_controls(belief, u)) * coef[..., :, None]
        p_a, cross, p_b = belief[DIFFUSE_COV], belief["diffuse_cross"], belief["prev_diffuse_cov"]
        m_inf = p_a @ h_a.mT - cross @ h_b.mT  # Cov_inf(a, g) [B, n, m]
        f_inf = h_a @ m_inf - h_b @ (cross.mT @ h_a.mT - p_b @ h_b.mT)
        return diffuse_gaussian_update(
            belief, innovation, devs, mask, diffuse_cross=m_inf, diffuse_innovation=symmetrize(f_inf), add=state_add(self.model.dynamics)
        )
