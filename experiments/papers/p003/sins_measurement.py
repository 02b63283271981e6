"""The measurement half of p003's GPS/SINS ultra-tight model: pseudorange and pseudorange-rate
differences INS - GPS (state layout and inputs: :mod:`experiments.papers.p003.sins`)."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor

from difffilter import geometry as geo
from difffilter.models.base import Controls, MeasurementModel
from difffilter.params import register_covariance

from .sins import _get, _position_scale

__all__ = ["SinsPseudorangeMeasurement"]


class SinsPseudorangeMeasurement(MeasurementModel):
    """Pseudorange and pseudorange-rate differences INS - GPS for ``K`` satellites (p003).

    Nonlinear form (default): with ``p_I = ecef(llh_I)``, ``d = ecef(llh_I) - ecef(llh_I - dllh)``
    (exact, :func:`~difffilter.geometry.ecef_displacement`), ``a_j = p_I - s_j``,
    ``b_j = a_j - d = p_true - s_j``, ``w_I = C_n^e(llh_I) v_I - sdot_j``,
    ``w_G = C_n^e(llh_I - dllh) (v_I - dv) - sdot_j``:

    .. math::
        \\delta\\rho_j = \\|a_j\\| - \\|b_j\\| - dt_u, \\qquad
        \\delta\\dot\\rho_j = \\frac{a_j^T w_I}{\\|a_j\\|} - \\frac{b_j^T w_G}{\\|b_j\\|} - dt_{ru}

    (``||a|| - ||b||`` is evaluated as ``(2 a.d - |d|^2) / (||a|| + ||b||)``: no cancellation).
    ``linearized=True`` gives the paper's ``e_j^T J_geo dllh - dt_u`` and ``e_j^T C_n^e dv - dt_ru``
    with ``e_j = a_j/||a_j||`` (then :meth:`matrix` returns ``H``).  Output
    ``[drho_1..K, drhodot_1..K]`` (or only ranges with ``rates=False``).  Analytic Jacobian.

    Learnable: ``R`` (default ``"scalar"`` structure on ``diag(sigma_range^2, sigma_rate^2)``).
    """

    def __init__(
        self,
        *,
        num_satellites: int,
        rates: bool = True,
        linearized: bool = False,
        sigma_range: float = 3.0,
        sigma_rate: float = 0.05,
        R: Tensor | None = None,
        R_structure: str = "scalar",
        position_in_metres: bool = False,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        self.num_satellites, self.rates, self.linearized = int(num_satellites), rates, linearized
        self.position_in_metres = position_in_metres
        self.measurement_dim = self.num_satellites * (2 if rates else 1)
        if R is None:
            var = [sigma_range**2] * self.num_satellites + ([sigma_rate**2] * self.num_satellites if rates else [])
            R = torch.diag(torch.tensor(var, dtype=dtype))
        register_covariance(self, "R", R, R_structure)

    def precompute_controls(self, controls: Controls) -> Controls:
        """Add the INS-only geometry of the nonlinear form for every step at once: ``a_j``
        (``"sins.los" [B, T, K, 3]``), ``||a_j||`` (``"sins.range" [B, T, K]``), the metre scale of
        the position states (``"sins.scale" [B, T, 3]``) and, with rates, ``w_I``
        (``"sins.ins_rate" [B, T, K, 3]``).  They depend on the inputs only (not on the state, the
        parameters or this model's settings), so :meth:`forward` of every sigma point, step and
        IMM mode reads them instead of recomputing them.  Inputs without ``llh``/``sat_pos``
        (or a linearized model) are returned unchanged."""
        if self.linearized or not isinstance(controls, Mapping) or "llh" not in controls or "sat_pos" not in controls:
            return controls
        out = dict(controls)
        llh = controls["llh"]
        if "sins.los" not in out:
            out["sins.los"], out["sins.range"] = self._line_of_sight(llh, controls["sat_pos"])
        if "sins.scale" not in out:
            out["sins.scale"] = _position_scale(llh)
        if self.rates and "sins.ins_rate" not in out and "vel" in controls and "sat_vel" in controls:
            out["sins.ins_rate"] = self._ins_rate(controls)
        return out

    @staticmethod
    def _line_of_sight(llh: Tensor, sat_pos: Tensor) -> tuple[Tensor, Tensor]:
        """``a_j`` = INS position (ECEF) - satellite ``[..., K, 3]`` and its length ``[..., K]``."""
        a = geo.geodetic_to_ecef(llh)[..., None, :] - sat_pos
        return a, torch.linalg.vector_norm(a, dim=-1)

    @staticmethod
    def _ins_rate(u: Controls) -> Tensor:
        """``w_I = C_n^e(llh_I) v_I - sdot_j`` ``[..., K, 3]``."""
        llh = _get(u, "llh")
        c_i = geo.enu_rotation(llh[..., 0], llh[..., 1])
        return (_get(u, "vel")[..., None, :] @ c_i)[..., 0, None, :] - _get(u, "sat_vel")

    @staticmethod
    def _derived(u: Controls, key: str) -> Tensor | None:
        return u.get(key) if isinstance(u, Mapping) else None

    def _errors(self, x: Tensor, u: Controls) -> tuple[Tensor, Tensor, Tensor]:
        llh = _get(u, "llh")
        pos = x[..., 0:3]
        if self.position_in_metres:
            scale = self._derived(u, "sins.scale")
            pos = pos / (_position_scale(llh) if scale is None else scale)
        return llh, pos, x[..., 3:6]

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        llh, dllh, dv = self._errors(x, u)
        a, na = self._derived(u, "sins.los"), self._derived(u, "sins.range")
        if a is None or na is None:
            a, na = self._line_of_sight(llh, _get(u, "sat_pos"))
        ea = a / na[..., None]
        if self.linearized:
            d = (geo.geodetic_jacobian(llh) @ dllh[..., None])[..., 0]
            rho = (ea * d[..., None, :]).sum(-1)
        else:
            d = geo.ecef_displacement(llh, dllh)[..., None, :]
            b = a - d
            nb = torch.linalg.vector_norm(b, dim=-1)
            rho = (2.0 * (a * d).sum(-1) - (d * d).sum(-1)) / (na + nb)
        rho = rho - x[..., 18, None]
        if not self.rates:
            return rho
        if self.linearized:
            dve = (dv[..., None, :] @ geo.enu_rotation(llh[..., 0], llh[..., 1]))[..., 0, :]
            rate = (ea * dve[..., None, :]).sum(-1)
        else:
            vel = _get(u, "vel")
            sv = _get(u, "sat_vel")
            w_i = self._derived(u, "sins.ins_rate")
            if w_i is None:
                w_i = self._ins_rate(u)
            true_llh = llh - dllh
            c_t = geo.enu_rotation(true_llh[..., 0], true_llh[..., 1])
            w_g = ((vel - dv)[..., None, :] @ c_t)[..., 0, None, :] - sv
            rate = (ea * w_i).sum(-1) - (b * w_g).sum(-1) / nb
        return torch.cat([rho, rate - x[..., 19, None]], -1)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        llh, dllh, dv = self._errors(x, u)
        s = _get(u, "sat_pos")
        k = self.num_satellites
        a = geo.geodetic_to_ecef(llh)[..., None, :] - s
        ea = a / torch.linalg.vector_norm(a, dim=-1, keepdim=True)
        true_llh = llh if self.linearized else llh - dllh
        jgeo = geo.geodetic_jacobian(true_llh)  # [..., 3, 3]
        if self.linearized:
            e = ea
        else:
            b = a - geo.ecef_displacement(llh, dllh)[..., None, :]
            nb = torch.linalg.vector_norm(b, dim=-1, keepdim=True)
            e = b / nb
        batch = torch.broadcast_shapes(e.shape[:-2], x.shape[:-1])
        jac = x.new_zeros(*batch, self.measurement_dim, 20)
        jac[..., :k, 0:3] = e @ jgeo
        jac[..., :k, 18] = -1.0
        if self.rates:
            c_t = geo.enu_rotation(true_llh[..., 0], true_llh[..., 1])  # rows E, N, U in ECEF
            jac[..., k:, 3:6] = e @ c_t.mT
            jac[..., k:, 19] = -1.0
            if not self.linearized:
                vt = _get(u, "vel") - dv
                w_g = (vt[..., None, :] @ c_t)[..., 0, None, :] - _get(u, "sat_vel")
                proj = (w_g - e * (e * w_g).sum(-1, keepdim=True)) / nb
                east, north, up = c_t.unbind(-2)
                lat = true_llh[..., 0]
                sl, cl = torch.sin(lat)[..., None], torch.cos(lat)[..., None]
                ve, vn, vu = (vt[..., i, None] for i in range(3))
                dvec_dlat = -vn * up + vu * north
                dvec_dlon = ve * (sl * north - cl * up) - vn * sl * east + vu * cl * east
                rot_part = torch.stack(
                    [(e * dvec_dlat[..., None, :]).sum(-1), (e * dvec_dlon[..., None, :]).sum(-1), torch.zeros_like(e[..., 0])], -1
                )
                jac[..., k:, 0:3] = proj @ jgeo + rot_part
        if self.position_in_metres:
            jac[..., 0:3] = jac[..., 0:3] / _position_scale(llh)[..., None, :]
        return jac

    def matrix(self, u: Controls = None) -> Tensor | None:
        if not self.linearized:
            return None
        x = _get(u, "llh").new_zeros(*_get(u, "llh").shape[:-1], 20)
        return self.jacobian(x, u)
