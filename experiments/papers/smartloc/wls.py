"""Single-epoch (snapshot) robust weighted least squares on the smartLoc pseudoranges: the classic
baseline and the source of the filters' initial beliefs."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from difffilter.models.navigation.pseudorange import GnssStateLayout, PseudorangeMeasurement

from .data import SmartLocData

__all__ = ["WlsSolution", "single_epoch_wls"]


@dataclass
class WlsSolution:
    """Single-epoch fixes: ``enu [T, 3]``, ``clock [T]``, ``isb [T]`` (m), post-fit ``residuals
    [T, K]`` (m), the satellites ``used [T, K]`` and whether each epoch was solvable ``valid [T]``."""

    enu: Tensor
    clock: Tensor
    isb: Tensor
    residuals: Tensor
    used: Tensor
    valid: Tensor


def _snapshot_measurement(num_slots: int, origin: Tensor, sagnac: bool) -> torch.nn.Module:
    layout = GnssStateLayout(state_dim=5, velocity=None, clock_bias=3, clock_drift=None, isb=4)
    return PseudorangeMeasurement(num_satellites=num_slots, layout=layout, sagnac=sagnac, frame_origin=origin, frame="enu", reduced=True)


def single_epoch_wls(
    data: SmartLocData,
    *,
    elevation_mask_deg: float = 15.0,
    robust: str | None = "huber",
    threshold: float = 1.5,
    iterations: int = 15,
    isb_prior_sigma: float = 100.0,
    sagnac: bool = True,
) -> WlsSolution:
    """Snapshot weighted least squares per epoch (Gauss-Newton, float64) for ``[E, N, U, b, beta]``.

    Model: Sagnac-corrected pseudoranges, GLONASS inter-system bias ``beta`` (weak zero-mean prior
    ``isb_prior_sigma`` so GPS-only epochs stay solvable), weights ``1/pr_var``.  ``robust``:
    ``"huber"`` (iteratively reweighted, ``w = min(1, c/|r_n|)``) or ``"cauchy"``
    (``w = 1/(1 + (r_n/c)^2)``) on residuals normalised by ``sigma_j`` and the epoch's MAD scale,
    with ``c = threshold``; ``None`` for plain WLS.  ``sagnac=False`` drops the Earth-rotation term
    (for comparison: the README's mean east error grows from 10.8 m to 32 m).
    """
    h = _snapshot_measurement(data.num_slots, data.origin_ecef, sagnac)
    z = data.reduced_pseudorange()
    used = data.mask & (data.elevation >= elevation_mask_deg)
    u = {"sat_pos": data.sat_enu, "glonass": data.glonass.to(torch.float64)}
    x = z.new_zeros(data.num_epochs, 5)
    base_w = torch.where(used, 1.0 / data.pr_var, 0.0)
    w = base_w
    prior = torch.zeros(5, 5, dtype=z.dtype)
    prior[4, 4] = 1.0 / isb_prior_sigma**2
    for it in range(iterations):
        r = torch.where(used, z - h(x, u), 0.0)
        if robust is not None and it >= 3:
            rn = r * torch.sqrt(base_w)
            absn = torch.where(used, rn.abs(), torch.nan)
            scale = (1.4826 * torch.nanmedian(absn, dim=1).values).clamp_min(1.0)
            rs = rn.abs() / scale[:, None]
            if robust == "huber":
                rw = torch.where(rs > threshold, threshold / rs.clamp_min(1e-12), 1.0)
            elif robust == "cauchy":
                rw = 1.0 / (1.0 + (rs / threshold) ** 2)
            else:
                raise ValueError(f"robust must be 'huber', 'cauchy' or None, got {robust!r}")
            w = base_w * rw
        jac = h.jacobian(x, u)
        normal = jac.mT @ (w[..., None] * jac) + prior
        rhs = jac.mT @ (w * r)[..., None] - (prior @ x[..., None])
        x = x + torch.linalg.solve(normal, rhs)[..., 0]
    r = torch.where(used, z - h(x, u), 0.0)
    valid = used.sum(1) >= 5
    nan = torch.full_like(x, torch.nan)
    x = torch.where(valid[:, None], x, nan)
    return WlsSolution(enu=x[:, :3], clock=x[:, 3], isb=x[:, 4], residuals=r, used=used, valid=valid)
