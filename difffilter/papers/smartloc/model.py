"""The smartLoc drive's filter model: odometry + clock dynamics and Sagnac-corrected reduced
pseudoranges in the drive's ENU frame, with the outlier gate (:func:`make_smartloc_model`), and the
initial beliefs of windows of the drive (:func:`smartloc_initial_belief`)."""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from ...models.base import StateSpaceModel
from ...models.navigation.clock import OdometryClockDynamics
from ...models.navigation.pseudorange import GnssStateLayout, PseudorangeMeasurement
from .data import SmartLocData
from .wls import WlsSolution, single_epoch_wls

__all__ = ["make_smartloc_model", "smartloc_initial_belief"]

_NO_SOFT_CONSTANT_GATE = "gate_gradient=False detaches the hard gate's rejected ranges; it cannot be combined with gate_softness > 0"


def make_smartloc_model(
    data: SmartLocData,
    *,
    dtype: torch.dtype = torch.float64,
    noise_from_data: bool = True,
    robust: str | None = "reject",
    gate: float = 2.5,
    gate_floor: float = 8.0,
    gate_gradient: bool = True,
    gate_softness: float | None = None,
    **dynamics_kwargs: float,
) -> torch.nn.Module:
    """Odometry + pseudorange model of the README's tightly coupled filter.

    State ``[E, N, U, yaw, b, d, beta]``: :class:`~difffilter.models.navigation.clock.OdometryClockDynamics`
    driven by ``speed``/``yaw_rate`` and :class:`~difffilter.models.navigation.pseudorange.PseudorangeMeasurement`
    in the ENU frame of ``data`` with the Sagnac term, reduced pseudoranges (float32-safe) and
    ``R = noise_scale * diag(pr_var)``.  ``robust`` is the outlier gate (see
    ``PseudorangeMeasurement.robust_inflation``): the urban-canyon multipath/NLOS errors make an
    ungated filter about three times worse (README).  ``dynamics_kwargs`` go to
    ``OdometryClockDynamics``; the default ``vertical_psd`` is 0.01 m^2/s (a car's height changes
    slowly; a free height drifts with the multipath and drags the horizontal solution along).

    ``gate_gradient=False`` (``robust="reject"`` only) detaches the variance of a rejected range
    (``1e6 R_jj``): the estimates are the same, but a rejected range's innovation-likelihood term
    ``log(1e6 R_jj) / 2`` becomes a constant, so it no longer pulls ``R`` (``noise_scale``)
    down during maximum-likelihood learning (with gradients, every rejected range adds
    ``1 / (2 noise_scale)`` to the gradient towards a smaller scale, unopposed by a residual).

    ``gate_softness`` (``robust="reject"``; ``None`` or ``0``: the hard gate, the default) makes
    the gate smooth, ``R_jj x 1e6 ** sigmoid((n_j - gate) / gate_softness)`` with ``n_j`` the
    normalised prior residual, and registers the temperature as the learnable-by-name parameter
    ``gate_softness`` (see ``PseudorangeMeasurement.set_gate_softness``).
    """
    if not isinstance(gate_gradient, bool):
        raise TypeError(f"gate_gradient must be a bool, got {type(gate_gradient).__name__}")
    if not gate_gradient and robust != "reject":
        raise ValueError(f"gate_gradient=False needs robust='reject', got robust={robust!r}")
    if not gate_gradient and gate_softness:
        raise ValueError(_NO_SOFT_CONSTANT_GATE)
    dynamics_kwargs = {"vertical_psd": 1e-2, **dynamics_kwargs}

    dyn = OdometryClockDynamics(dtype=dtype, **dynamics_kwargs)
    cls = PseudorangeMeasurement if gate_gradient else _constant_gate_measurement_class()
    meas = cls(
        num_satellites=data.num_slots,
        layout=GnssStateLayout.odometry(isb=True),
        sagnac=True,
        frame_origin=data.origin_ecef,
        frame="enu",
        reduced=True,
        noise_from_data=noise_from_data,
        robust=robust,
        gate=gate,
        gate_floor=gate_floor,
        gate_softness=gate_softness,
        dtype=dtype,
    )
    return StateSpaceModel(dyn, meas)


@functools.lru_cache(maxsize=1)
def _constant_gate_measurement_class() -> type:
    """:class:`~difffilter.models.navigation.pseudorange.PseudorangeMeasurement` whose rejected ranges have
    a parameter-free (detached) inflated variance (see ``make_smartloc_model(gate_gradient=False)``)."""
    class ConstantGatePseudorange(PseudorangeMeasurement):
        def set_gate_softness(self, value: float | None) -> None:
            if value:
                raise ValueError(_NO_SOFT_CONSTANT_GATE)
            super().set_gate_softness(value)

        def robust_inflation(self, x: Tensor, u: object, r: Tensor) -> Tensor:
            out = super().robust_inflation(x, u, r)
            eye = torch.eye(out.shape[-1], dtype=torch.bool, device=out.device)
            rejected = (torch.diagonal(out, dim1=-2, dim2=-1) > torch.diagonal(r, dim1=-2, dim2=-1))[..., None] & eye
            return torch.where(rejected, out.detach(), out)

    return ConstantGatePseudorange


def smartloc_initial_belief(
    data: SmartLocData,
    start: Tensor,
    *,
    wls: WlsSolution | None = None,
    height_sigma: float = 2.0,
    dtype: torch.dtype = torch.float64,
) -> tuple[Tensor, Tensor]:
    """Initial beliefs ``[B, 7]``, ``[B, 7, 7]`` for windows starting at epochs ``start [B]``.

    E, N, clock bias and ISB from the robust snapshot fix at the epoch before the window (std
    30 m, 30 m, 10 m), clock drift from the snapshot clocks over the next 5 s (std 2 m/s).  From
    the reference track, as a map and a known start would give them: yaw (std 10 deg; the
    README's dead reckoning was started the same way) and height U (std ``height_sigma``): the
    snapshot heights at the start are ~90 m off in this canyon.
    """
    sol = wls if wls is not None else single_epoch_wls(data)
    idx = (start - 1).clamp_min(0)
    means = []
    for i in idx.tolist():
        j = i
        while not bool(sol.valid[j]):
            j += 1
        k = min(j + 25, data.num_epochs - 1)
        drift = (sol.clock[k] - sol.clock[j]) / (data.times[k] - data.times[j])
        d = data.truth_enu[min(i + 5, data.num_epochs - 1)] - data.truth_enu[i]
        yaw = torch.atan2(d[1], d[0])
        means.append(torch.stack([sol.enu[j, 0], sol.enu[j, 1], data.truth_enu[i, 2], yaw, sol.clock[j], drift, sol.isb[j]]))
    sd = torch.tensor([30.0, 30.0, height_sigma, np.radians(10.0), 30.0, 2.0, 10.0], dtype=torch.float64)
    mean = torch.stack(means).to(dtype)
    return mean, torch.diag(sd * sd).to(dtype).expand(mean.shape[0], 7, 7).clone()
