"""The smartLoc Berlin Potsdamer Platz drive: real u-blox pseudoranges, odometry and reference.

Data (CC BY-SA 4.0, TU Chemnitz smartLoc, converted by libRSF): P. Reisdorf, T. Pfeifer, J. Bressler,
S. Bauer, P. Weissig, S. Lange, G. Wanielik, P. Protzel, "The Problem of Comparable GNSS Results - An
Approach for a Uniform Dataset with Low-Cost and Reference Data", VEHICULAR 2016.  The files live
outside the repository, in ``../shared/data/real/smartloc_berlin_potsdamer/`` (or the folder named by
the environment variable ``DIFFFILTER_SMARTLOC``); see the README there for the format.

:func:`load_smartloc` groups the ``odom3``/``pseudorange3``/``point3`` lines by time stamp into
1,372 epochs with a fixed number of satellite slots ``K`` (17 = most satellites in one epoch, or one
slot per satellite with ``slots="satellite"``, which coloured-noise models need) and a mask.
Positions are ENU around the first reference point.  :meth:`SmartLocData.batch` and
:meth:`SmartLocData.windows` give filter-ready tensors; :func:`single_epoch_wls` is the classic
snapshot baseline and :func:`make_smartloc_model` the odometry + pseudorange model of the README's
tightly coupled EKF (with :func:`smartloc_initial_belief`).
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from . import geometry as geo

__all__ = [
    "SmartLocBatch",
    "SmartLocData",
    "WlsSolution",
    "default_smartloc_path",
    "load_smartloc",
    "make_smartloc_model",
    "single_epoch_wls",
    "smartloc_initial_belief",
]

_INPUT = "Berlin_Potsdamer_Platz_Input.txt"
_TRUTH = "Berlin_Potsdamer_Platz_GT.txt"


def default_smartloc_path() -> Path:
    """``$DIFFFILTER_SMARTLOC`` if set, else ``<repo>/../shared/data/real/smartloc_berlin_potsdamer``."""
    env = os.environ.get("DIFFFILTER_SMARTLOC")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "smartloc_berlin_potsdamer"


@dataclass
class SmartLocBatch:
    """Filter-ready tensors (batch-first).

    ``measurements [B, T, K]`` (pseudoranges, reduced by ``|s_enu|`` if ``reduced``), ``mask [B, T, K]``,
    ``controls``: ``sat_pos [B, T, K, 3]`` (ENU), ``glonass [B, T, K]`` (0/1), ``pr_var [B, T, K]``,
    ``pr_obs [B, T, K]`` (= measurements, for the robust noise option), ``speed``, ``yaw_rate``,
    ``dt`` ``[B, T, 1]`` (odometry averaged over the step ending at each epoch); ``truth [B, T, 3]``
    ENU reference, ``times [B, T]``, ``start [B]`` epoch index of each window's first step.
    """

    measurements: Tensor
    mask: Tensor
    controls: dict[str, Tensor]
    truth: Tensor
    times: Tensor
    start: Tensor
    reduced: bool


@dataclass
class SmartLocData:
    """One drive, ``T`` epochs and ``K`` satellite slots (float64 / long / bool tensors).

    Attributes:
        times, dt: ``[T]`` epoch time stamps (s) and steps (``dt[0] = 0``).
        truth_ecef, truth_enu: ``[T, 3]`` reference trajectory (ENU origin: first point).
        pseudorange, pr_var: ``[T, K]`` pseudoranges (m) and their variances (m^2).
        sat_ecef, sat_enu: ``[T, K, 3]`` satellite positions (not Earth-rotation corrected).
        sat_id, system: ``[T, K]`` satellite id (GLONASS = 300 + slot) and system (1 GPS, 4 GLONASS).
        glonass, mask: ``[T, K]`` bool; ``mask`` False marks empty slots (their positions are a
        finite dummy 20,000 km above the origin, pseudorange 0, variance 1).
        elevation, cn0: ``[T, K]`` degrees and dB-Hz.
        speed, yaw_rate: ``[T]`` odometry (m/s, rad/s, positive = left turn).
        origin_ecef, origin_llh: ``[3]`` ENU origin; rotation ``[3, 3]`` (``enu = C (ecef - o)``).
    """

    times: Tensor
    dt: Tensor
    truth_ecef: Tensor
    truth_enu: Tensor
    pseudorange: Tensor
    pr_var: Tensor
    sat_ecef: Tensor
    sat_enu: Tensor
    sat_id: Tensor
    system: Tensor
    glonass: Tensor
    mask: Tensor
    elevation: Tensor
    cn0: Tensor
    speed: Tensor
    yaw_rate: Tensor
    origin_ecef: Tensor
    origin_llh: Tensor
    rotation: Tensor

    @property
    def num_epochs(self) -> int:
        return int(self.times.shape[0])

    @property
    def num_slots(self) -> int:
        return int(self.mask.shape[1])

    def ecef_to_enu(self, xyz: Tensor) -> Tensor:
        """ECEF ``[..., 3]`` -> ENU around :attr:`origin_ecef`."""
        o = self.origin_ecef.to(xyz.dtype)
        return ((xyz - o)[..., None, :] @ self.rotation.to(xyz.dtype).mT)[..., 0, :]

    def enu_to_ecef(self, enu: Tensor) -> Tensor:
        """ENU ``[..., 3]`` -> ECEF."""
        return self.origin_ecef.to(enu.dtype) + (enu[..., None, :] @ self.rotation.to(enu.dtype))[..., 0, :]

    def reduced_pseudorange(self) -> Tensor:
        """``rho - |s_enu|`` ``[T, K]`` in float64 (0 in empty slots)."""
        return torch.where(self.mask, self.pseudorange - torch.linalg.vector_norm(self.sat_enu, dim=-1), 0.0)

    def batch(
        self,
        dtype: torch.dtype = torch.float64,
        *,
        elevation_mask_deg: float = 0.0,
        reduced: bool = True,
        exclude: Tensor | None = None,
    ) -> SmartLocBatch:
        """The whole drive as a ``B = 1`` batch; slots below ``elevation_mask_deg`` or flagged in
        ``exclude [T, K]`` are masked out."""
        mask = self.mask & (self.elevation >= elevation_mask_deg)
        if exclude is not None:
            mask = mask & ~exclude
        z = self.reduced_pseudorange() if reduced else torch.where(self.mask, self.pseudorange, 0.0)
        prev = torch.cat([self.speed[:1], self.speed[:-1]])
        prev_w = torch.cat([self.yaw_rate[:1], self.yaw_rate[:-1]])
        controls = {
            "sat_pos": self.sat_enu,
            "glonass": self.glonass.to(torch.float64),
            "pr_var": self.pr_var,
            "pr_obs": z,
            "speed": (0.5 * (self.speed + prev))[:, None],
            "yaw_rate": (0.5 * (self.yaw_rate + prev_w))[:, None],
            "dt": self.dt[:, None],
        }
        return SmartLocBatch(
            measurements=z[None].to(dtype),
            mask=mask[None],
            controls={k: v[None].to(dtype) for k, v in controls.items()},
            truth=self.truth_enu[None].to(dtype),
            times=self.times[None].to(dtype),
            start=torch.zeros(1, dtype=torch.long),
            reduced=reduced,
        )

    def windows(self, length: int, stride: int | None = None, dtype: torch.dtype = torch.float64, **batch_kwargs: object) -> SmartLocBatch:
        """Split the drive into windows of ``length`` epochs every ``stride`` (default ``length``):
        ``B = number of windows``.  Use ``start`` to build each window's initial belief."""
        full = self.batch(dtype, **batch_kwargs)  # type: ignore[arg-type]
        stride = length if stride is None else stride
        starts = list(range(0, self.num_epochs - length + 1, stride))
        if not starts:
            raise ValueError(f"window length {length} exceeds the {self.num_epochs} epochs")

        def cut(t: Tensor) -> Tensor:
            return torch.cat([t[:, s : s + length] for s in starts], 0)

        return SmartLocBatch(
            measurements=cut(full.measurements),
            mask=cut(full.mask),
            controls={k: cut(v) for k, v in full.controls.items()},
            truth=cut(full.truth),
            times=cut(full.times),
            start=torch.tensor(starts, dtype=torch.long),
            reduced=full.reduced,
        )


def _read(path: Path) -> list[list[str]]:
    with open(path) as fh:
        return [line.split() for line in fh if line.strip()]


def load_smartloc(path: str | Path | None = None, *, slots: str = "epoch") -> SmartLocData:
    """Load the Berlin Potsdamer Platz drive.

    Args:
        path: folder with ``Berlin_Potsdamer_Platz_Input.txt`` and ``..._GT.txt`` (default
            :func:`default_smartloc_path`).
        slots: ``"epoch"`` (K = most satellites in an epoch, 17, slots filled in satellite-id
            order) or ``"satellite"`` (one fixed slot per satellite id for the whole drive).
    """
    folder = Path(path) if path is not None else default_smartloc_path()
    if not (folder / _INPUT).exists():
        raise FileNotFoundError(f"smartLoc data not found in {folder} (set DIFFFILTER_SMARTLOC)")
    if slots not in ("epoch", "satellite"):
        raise ValueError(f"slots must be 'epoch' or 'satellite', got {slots!r}")
    rows = _read(folder / _INPUT)
    odom = np.array([[float(v) for v in r[1:8]] for r in rows if r[0] == "odom3"])
    pr = np.array([[float(v) for v in r[1:11]] for r in rows if r[0] == "pseudorange3"])
    gt = np.array([[float(v) for v in r[1:5]] for r in _read(folder / _TRUTH) if r[0] == "point3"])
    times = np.unique(pr[:, 0])
    epoch_of = np.searchsorted(times, pr[:, 0])
    odom = odom[np.argsort(odom[:, 0], kind="stable")]
    gt = gt[np.argsort(gt[:, 0], kind="stable")]
    if not (np.array_equal(odom[:, 0], times) and np.array_equal(gt[:, 0], times)):
        raise ValueError("odometry, pseudorange and reference time stamps differ")
    sat_ids = pr[:, 6].astype(np.int64)
    order = np.lexsort((sat_ids, epoch_of))
    pr, epoch_of, sat_ids = pr[order], epoch_of[order], sat_ids[order]
    if slots == "epoch":
        first = np.searchsorted(epoch_of, epoch_of, side="left")
        slot = np.arange(len(pr)) - first
    else:
        _, slot = np.unique(sat_ids, return_inverse=True)
    n_t, n_k = len(times), int(slot.max()) + 1

    def grid(col: np.ndarray, fill: float) -> np.ndarray:
        out = np.full((n_t, n_k), fill, dtype=col.dtype)
        out[epoch_of, slot] = col
        return out

    mask = grid(np.ones(len(pr), dtype=bool), False)
    truth_ecef = torch.from_numpy(gt[:, 1:4].copy())
    origin = truth_ecef[0].clone()
    llh0 = geo.ecef_to_geodetic(origin)
    rot = geo.enu_rotation(llh0[0], llh0[1])
    dummy = (origin + 2.0e7 * rot[2]).numpy()
    sat = np.stack([grid(pr[:, 3 + i], float(dummy[i])) for i in range(3)], -1)
    sat_ecef = torch.from_numpy(sat)
    sat_enu = ((sat_ecef - origin)[..., None, :] @ rot.mT)[..., 0, :]
    system = torch.from_numpy(grid(pr[:, 7].astype(np.int64), 0))
    t = torch.from_numpy(times)
    return SmartLocData(
        times=t,
        dt=torch.cat([t.new_zeros(1), t[1:] - t[:-1]]),
        truth_ecef=truth_ecef,
        truth_enu=((truth_ecef - origin) @ rot.mT),
        pseudorange=torch.from_numpy(grid(pr[:, 1], 0.0)),
        pr_var=torch.from_numpy(grid(pr[:, 2], 1.0)),
        sat_ecef=sat_ecef,
        sat_enu=sat_enu,
        sat_id=torch.from_numpy(grid(sat_ids, 0)),
        system=system,
        glonass=system == 4,
        mask=torch.from_numpy(mask),
        elevation=torch.from_numpy(grid(pr[:, 8], 0.0)),
        cn0=torch.from_numpy(grid(pr[:, 9], 0.0)),
        speed=torch.from_numpy(odom[:, 1].copy()),
        yaw_rate=torch.from_numpy(odom[:, 6].copy()),
        origin_ecef=origin,
        origin_llh=llh0,
        rotation=rot,
    )


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
    from ..models.pseudorange import GnssStateLayout, PseudorangeMeasurement  # lazy: models may import sim

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

    State ``[E, N, U, yaw, b, d, beta]``: :class:`~difffilter.models.pseudorange.OdometryClockDynamics`
    driven by ``speed``/``yaw_rate`` and :class:`~difffilter.models.pseudorange.PseudorangeMeasurement`
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
    from ..models.base import StateSpaceModel
    from ..models.pseudorange import GnssStateLayout, OdometryClockDynamics, PseudorangeMeasurement

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
    """:class:`~difffilter.models.pseudorange.PseudorangeMeasurement` whose rejected ranges have
    a parameter-free (detached) inflated variance (see ``make_smartloc_model(gate_gradient=False)``)."""
    from ..models.pseudorange import PseudorangeMeasurement

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
