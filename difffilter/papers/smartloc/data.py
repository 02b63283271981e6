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
:meth:`SmartLocData.windows` give filter-ready tensors.  The snapshot baseline is in
:mod:`difffilter.papers.smartloc.wls`, the odometry + pseudorange model of the README's tightly
coupled EKF in :mod:`difffilter.papers.smartloc.model`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ... import geometry as geo

__all__ = ["SmartLocBatch", "SmartLocData", "default_smartloc_path", "load_smartloc"]

_INPUT = "Berlin_Potsdamer_Platz_Input.txt"
_TRUTH = "Berlin_Potsdamer_Platz_GT.txt"


def default_smartloc_path() -> Path:
    """``$DIFFFILTER_SMARTLOC`` if set, else ``<repo>/../shared/data/real/smartloc_berlin_potsdamer``."""
    env = os.environ.get("DIFFFILTER_SMARTLOC")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[4] / "shared" / "data" / "real" / "smartloc_berlin_potsdamer"


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
