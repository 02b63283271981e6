"""The smartLoc drive's filter model: odometry + clock dynamics and Sagnac-corrected reduced
pseudoranges in the drive's ENU frame, with the outlier gate (:func:`make_smartloc_model`), and the
initial beliefs of windows of the drive (:func:`smartloc_initial_belief`)."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from difffilter.models.base import StateSpaceModel
from difffilter.models.layout import StateLayout, describe
from difffilter.models.navigation.clock import OdometryClockDynamics
from difffilter.models.navigation.pseudorange import GnssStateLayout, PseudorangeMeasurement

from .data import SmartLocData
from .wls import WlsSolution, single_epoch_wls

__all__ = ["SMARTLOC_LAYOUT", "DriveWindows", "make_smartloc_model", "smartloc_initial_belief"]

#: State of the odometry + pseudorange model: ENU position (origin: the first reference point),
#: yaw (from east, counter-clockwise), clock bias and drift, GLONASS inter-system bias.
SMARTLOC_LAYOUT = StateLayout(
    names=("E", "N", "U", "yaw", "clock_bias", "clock_drift", "isb"),
    units=("m", "m", "m", "rad", "m", "m/s", "m"),
    position=(0, 1, 2),
    angles=(3,),
)
_LEARN = ("noise_scale", "speed_sigma", "yaw_rate_sigma", "horizontal_psd", "vertical_psd", "yaw_psd")
_LEARN += ("clock_bias_psd", "clock_drift_psd", "isb_psd")

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
    gate_learnable: bool = False,
    noise_model: torch.nn.Module | None = None,
    lever_arm: Sequence[float] | None = None,
    latency: float | None = None,
    elevation_bias: Sequence[float] | None = None,
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
    ``gate_softness`` (see ``PseudorangeMeasurement.set_gate_softness``); ``gate_learnable`` also
    makes the threshold and floor learnable (``gate_threshold``, ``gate_floor``).

    ``noise_model`` (a variance module, :mod:`difffilter.models.heteroscedastic`, reading
    ``elevation``, ``cn0``, ``constellation``, ``pr_var`` from the batch controls) replaces
    ``noise_scale * pr_var`` (``noise_from_data`` is then ignored).

    Extras (:mod:`experiments.papers.smartloc.extras`; ``None``: not modelled): ``lever_arm``
    (m; forward, left, up), ``latency`` (s) and ``elevation_bias`` (m per constellation group)
    of :class:`~difffilter.models.navigation.pseudorange.PseudorangeMeasurement`, learnable by
    those names (the odometry gives the heading and speed they need).
    """
    if not isinstance(gate_gradient, bool):
        raise TypeError(f"gate_gradient must be a bool, got {type(gate_gradient).__name__}")
    if not gate_gradient and robust != "reject":
        raise ValueError(f"gate_gradient=False needs robust='reject', got robust={robust!r}")
    if not gate_gradient and gate_softness:
        raise ValueError(_NO_SOFT_CONSTANT_GATE)
    dynamics_kwargs = {"vertical_psd": 1e-2, **dynamics_kwargs}

    if noise_model is not None:
        noise_from_data = False
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
        gate_learnable=gate_learnable,
        noise_model=noise_model,
        lever_arm=lever_arm,
        latency=latency,
        elevation_bias=elevation_bias,
        dtype=dtype,
    )
    extras = [n for n, v in (("lever_arm", lever_arm), ("latency", latency), ("elevation_bias", elevation_bias)) if v is not None]
    sd = [30.0, 30.0, 2.0, float(np.radians(10.0)), 30.0, 2.0, 10.0]  # smartloc_initial_belief's spreads
    return describe(
        StateSpaceModel(dyn, meas),
        layout=SMARTLOC_LAYOUT,
        learn=[n for n in _LEARN if n != "noise_scale" or noise_from_data]
        + (["*noise_model.*"] if noise_model is not None else [])
        + extras,
        initial_mean=[0.0] * 7,
        initial_var=[s * s for s in sd],
        controls=DriveWindows(data=data),
    )  # type: ignore[return-value]


class DriveWindows:
    """In-family inputs of the smartLoc model: ``(batch_size, num_steps, generator, dtype) ->`` the
    real drive's controls (satellite positions, receiver variances, odometry) over windows of
    ``num_steps`` epochs starting at random epochs."""

    def __init__(self, *, data: SmartLocData, elevation_mask_deg: float = 15.0) -> None:
        self.data, self.elevation_mask_deg = data, float(elevation_mask_deg)

    def __call__(self, batch_size: int, num_steps: int, gen: torch.Generator, dtype: torch.dtype) -> dict[str, Tensor]:
        total = self.data.num_epochs
        if not 1 <= num_steps <= total:
            raise ValueError(f"num_steps must lie in [1, {total}] (the drive's epochs), got {num_steps}")
        full = self.data.batch(dtype, elevation_mask_deg=self.elevation_mask_deg)
        starts = torch.randint(0, total - num_steps + 1, (batch_size,), generator=gen).tolist()
        return {k: torch.cat([v[:, s : s + num_steps] for s in starts], 0) for k, v in full.controls.items()}


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
