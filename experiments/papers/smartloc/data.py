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
:mod:`experiments.papers.smartloc.wls`, the odometry + pseudorange model of the README's tightly
coupled EKF in :mod:`experiments.papers.smartloc.model`.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from difffilter import geometry as geo
from difffilter.datasets import DataSetMissingError, locate
from difffilter.models.sensors import event_times

from .librsf import Records, read_records

__all__ = ["SmartLocBatch", "SmartLocData", "default_smartloc_path", "find_drives", "load_drive", "load_smartloc"]

_INPUT = "Berlin_Potsdamer_Platz_Input.txt"
_TRUTH = "Berlin_Potsdamer_Platz_GT.txt"
#: GNSS systems as libRSF numbers them, in the order of their group index (``constellation``).
SYSTEMS = {1: "GPS", 4: "GLONASS", 8: "Galileo", 32: "BeiDou", 16: "QZSS", 2: "SBAS"}


def default_smartloc_path() -> Path:
    """``$DIFFFILTER_SMARTLOC`` if set, else the folder :func:`difffilter.datasets.locate` finds for
    ``smartloc_berlin_potsdamer`` (``$DIFFFILTER_DATA``, ``../shared/data/real`` next to the
    repository or a folder holding it, the download cache), else
    ``<repo>/../shared/data/real/smartloc_berlin_potsdamer`` (absent: callers skip or name it)."""
    env = os.environ.get("DIFFFILTER_SMARTLOC")
    if env:
        return Path(env)
    try:
        return locate("smartloc_berlin_potsdamer")
    except DataSetMissingError:
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
        name: the drive's name (its input file's stem).
        systems: the GNSS systems kept, in the order of their group index :attr:`constellation`.
        issues: counts of what the loader skipped (``{what: count}``), also given as warnings.
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
    name: str = "drive"
    systems: tuple[int, ...] = (1, 4)
    issues: dict[str, int] = field(default_factory=dict)

    @property
    def constellation(self) -> Tensor:
        """``[T, K]`` group index of each slot's system in :attr:`systems` (0 in empty slots)."""
        out = torch.zeros_like(self.system)
        for i, sys_id in enumerate(self.systems):
            out = torch.where(self.system == sys_id, i, out)
        return out

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
            "elevation": self.elevation,
            "cn0": self.cn0,
            "constellation": self.constellation.to(torch.float64),
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


def find_drives(folder: str | Path) -> list[tuple[str, str]]:
    """``[(input file, reference file)]`` of the drives in ``folder``: every ``<name>_Input.txt``
    with a ``<name>_GT.txt`` beside it (sorted by name)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder (a folder of libRSF drives <name>_Input.txt + <name>_GT.txt)")
    out = []
    for inp in sorted(folder.glob("*_Input.txt")):
        gt = inp.name[: -len("_Input.txt")] + "_GT.txt"
        if (folder / gt).is_file():
            out.append((inp.name, gt))
    if not out:
        raise FileNotFoundError(f"{folder}: no drive found (files <name>_Input.txt with <name>_GT.txt)")
    return out


def _warn(data_issues: dict[str, int], key: str, count: int, message: str) -> None:
    if count:
        data_issues[key] = int(count)
        warnings.warn(message, stacklevel=3)


def _check_unique(inp: Records, pr: np.ndarray) -> None:
    """Each (epoch, satellite) once: a repeated pair is an error naming its second line."""
    order = np.lexsort((pr[:, 6], pr[:, 0]))
    same = (np.diff(pr[order, 0]) == 0) & (np.diff(pr[order, 6]) == 0)
    if same.any():
        row = int(order[1:][same][0])
        raise ValueError(f"{inp.where('pseudorange3', row)}: satellite {int(pr[row, 6])} appears twice at time {pr[row, 0]}")


def _interp(times: np.ndarray, t: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values [N, d]`` at ``t [N]`` linearly interpolated to ``times`` (exact where they agree)."""
    return np.stack([np.interp(times, t, values[:, j]) for j in range(values.shape[1])], -1)


def load_drive(
    folder: str | Path,
    *,
    input_file: str = _INPUT,
    truth_file: str = _TRUTH,
    slots: str = "epoch",
    systems: Sequence[int] = (1, 4),
    min_satellites: int = 4,
) -> SmartLocData:
    """Load one drive in the libRSF text format: ``folder/input_file`` (``pseudorange3`` and
    ``odom3`` lines) and ``folder/truth_file`` (``point3`` reference positions).

    The filter's steps are the times at which any sensor reports (the union of the pseudorange
    epochs and the odometry times): a step without pseudoranges only predicts (its mask is
    False), odometry and reference are interpolated linearly to the steps (exact where their
    time stamps are the steps', as in the smartLoc drives); nothing shifts a time stamp.

    Args:
        folder: the drive's folder.
        input_file, truth_file: file names in it.
        slots: ``"epoch"`` (K = most satellites in an epoch, slots filled in satellite-id order) or
            ``"satellite"`` (one fixed slot per satellite id for the whole drive).
        systems: the GNSS systems used (libRSF numbers, default GPS and GLONASS, the systems the
            model's single inter-system bias covers); the group index ``constellation`` follows
            this order.  Pseudoranges of other systems are skipped with a counted warning.
        min_satellites: epochs with fewer usable pseudoranges are not used for updates (their
            slots are masked) and counted in a warning; odometry still predicts through them.

    Raises:
        FileNotFoundError: a missing folder or file.
        ValueError: malformed lines, time stamps that go back, a satellite twice in one epoch, a
            reference track that does not cover the drive's time span (messages name file and line).
    """
    folder = Path(folder)
    if slots not in ("epoch", "satellite"):
        raise ValueError(f"slots must be 'epoch' or 'satellite', got {slots!r}")
    unknown = sorted(set(int(s) for s in systems) - set(SYSTEMS))
    if unknown or not systems:
        raise ValueError(f"systems must be libRSF system numbers {sorted(SYSTEMS)}, got {list(systems)}")
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder")
    inp = read_records(folder / input_file, {"pseudorange3": 11, "odom3": 8}, role="input (pseudorange3 + odom3)")
    ref = read_records(folder / truth_file, {"point3": 5}, role="reference (point3)")
    pr, odom, gt = inp.values["pseudorange3"], inp.values["odom3"], ref.values["point3"]
    for rec, kind, arr in ((inp, "pseudorange3", pr), (inp, "odom3", odom), (ref, "point3", gt)):
        if len(arr) == 0:
            raise ValueError(f"{rec.path}: no {kind} line")
    issues: dict[str, int] = {}
    for kind, count in {**inp.skipped, **ref.skipped}.items():
        _warn(issues, f"skipped {kind} lines", count, f"{folder}: {count} {kind} lines skipped (record type not read)")
    _check_unique(inp, pr)
    systems = tuple(int(s) for s in systems)
    keep = np.isin(pr[:, 7].astype(np.int64), systems)
    _warn(
        issues,
        "pseudoranges of other systems",
        int((~keep).sum()),
        f"{inp.path}: {int((~keep).sum())} pseudoranges of systems other than {systems} skipped",
    )
    pr = pr[keep]
    # the filter's steps: every time a sensor reports (odometry at its own rate only predicts)
    streams = {
        "gnss": (torch.from_numpy(pr[:, 0]), torch.empty(len(pr), 0)),
        "odometry": (torch.from_numpy(odom[:, 0]), torch.empty(len(odom), 0)),
    }
    times = event_times(streams).numpy()
    for rec, kind, t in ((ref, "point3", gt[:, 0]), (inp, "odom3", odom[:, 0])):
        if t[0] > times[0] or t[-1] < times[-1]:
            raise ValueError(f"{rec.path}: the {kind} time stamps [{t[0]}, {t[-1]}] do not cover the drive's [{times[0]}, {times[-1]}]")
    epoch_of = np.searchsorted(times, pr[:, 0])
    sat_ids = pr[:, 6].astype(np.int64)
    order = np.lexsort((sat_ids, epoch_of))
    pr, epoch_of, sat_ids = pr[order], epoch_of[order], sat_ids[order]
    counts = np.bincount(epoch_of, minlength=len(times))
    few = (counts > 0) & (counts < int(min_satellites))
    first_few = times[few][0] if few.any() else 0.0
    _warn(
        issues,
        f"epochs with fewer than {min_satellites} satellites",
        int(few.sum()),
        f"{inp.path}: {int(few.sum())} epochs with fewer than {min_satellites} satellites (first at t = {first_few}): "
        "their pseudoranges are not used",
    )
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

    mask = grid(np.ones(len(pr), dtype=bool), False) & ~few[:, None]
    truth_ecef = torch.from_numpy(_interp(times, gt[:, 0], gt[:, 1:4]))
    odo = _interp(times, odom[:, 0], odom[:, 1:7])
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
        speed=torch.from_numpy(odo[:, 0].copy()),
        yaw_rate=torch.from_numpy(odo[:, 5].copy()),
        origin_ecef=origin,
        origin_llh=llh0,
        rotation=rot,
        name=input_file[: -len("_Input.txt")] if input_file.endswith("_Input.txt") else Path(input_file).stem,
        systems=systems,
        issues=issues,
    )


def load_smartloc(path: str | Path | None = None, *, slots: str = "epoch") -> SmartLocData:
    """Load the Berlin Potsdamer Platz drive (:func:`load_drive` on ``Berlin_Potsdamer_Platz_Input.txt``
    and ``..._GT.txt`` in ``path``, default :func:`default_smartloc_path`)."""
    folder = Path(path) if path is not None else default_smartloc_path()
    if not (folder / _INPUT).exists():
        raise FileNotFoundError(f"smartLoc data not found in {folder} (set DIFFFILTER_SMARTLOC)")
    return load_drive(folder, input_file=_INPUT, truth_file=_TRUTH, slots=slots)
