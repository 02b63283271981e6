"""Ranging recordings assembled into per-step arrays - 2-D (``range2`` to fixed anchors,
``odom2``/``odom2diff`` odometry, ``point2`` ground truth) and 3-D (``range3``, ``odom3`` odometry
or none, ``point3``) - and the discovery of data sets in a folder of libRSF files.

Time base: the sorted union of the range and odometry time stamps.  An odometry record at time
``t_k`` describes the motion from ``t_{k-1}`` to ``t_k`` (body-frame velocity and turn rate; the
libRSF ranging sets move with the heading of ``t_{k-1}`` and then turn), so step ``k`` of the
filter predicts with it; a step without odometry keeps the previous record (counted).
``odom2diff`` is converted to body velocity and turn rate: ``v = (v_r + v_l) / 2``,
``w = (v_r - v_l) / b`` with the covariance propagated (including the ``v``-``w`` cross term).
``odom3`` keeps the body velocity ``v_x, v_y, v_z`` and the yaw rate ``w_z`` (a level vehicle; the
roll and pitch rates are not used) with their variances.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .librsf import LibrsfFile, detect_kinds, read_librsf

__all__ = ["RangingRecording", "find_recordings", "folder_kind", "load_ranging"]


@dataclass
class RangingRecording:
    """One ranging recording as per-step arrays (``T`` steps, ``A`` anchors, ``d`` = :attr:`dim` = 2 or 3).

    Attributes:
        name: data set name (the input file's stem without ``_Input``).
        times: ``[T]`` s.
        dt: ``[T]`` s (``dt[0] = 0``).
        odom: ``[T, 3]`` body velocity x, y (m/s) and turn rate (rad/s) of the step ending at each
            time; 3-D: ``[T, 4]`` body velocity x, y, z and yaw rate, ``[T, 0]`` without odometry.
        odom_cov: ``[T, 3, 3]`` (``[T, 4, 4]``, ``[T, 0, 0]``) their covariance (the file's
            variances: the hand-tuned values).
        ranges: ``[T, A]`` m (0 where missing); ``range_var`` ``[T, A]`` the file's variances
            (1 where missing); ``mask`` ``[T, A]`` True where a range was measured and used.
        anchors: ``[T, A, d]`` anchor positions as the file gives them per line (the last known
            position where missing); ``anchor_ids`` ``[A]``.
        truth: ``[T, d]`` reference position (NaN without a ``point2`` at that time);
            ``heading0``: the reference heading at the first step if the truth file has ``angle`` records;
            ``heading`` ``[T]`` the reference heading at every step (NaN without an ``angle`` record
            at that time; None when the recording was built without it).
        issues: counts of what was skipped or repaired.
        dim: 2 (``range2``) or 3 (``range3``).
        odometry: whether the recording has odometry (a ``range3`` file may have none).
    """

    name: str
    times: np.ndarray
    dt: np.ndarray
    odom: np.ndarray
    odom_cov: np.ndarray
    ranges: np.ndarray
    range_var: np.ndarray
    mask: np.ndarray
    anchors: np.ndarray
    anchor_ids: np.ndarray
    truth: np.ndarray
    heading0: float | None = None
    issues: dict[str, int] = field(default_factory=dict)
    heading: np.ndarray | None = None
    dim: int = 2
    odometry: bool = True

    @property
    def num_steps(self) -> int:
        return int(self.times.shape[0])

    @property
    def num_anchors(self) -> int:
        return int(self.anchor_ids.shape[0])


def _odometry(rec: LibrsfFile) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(times [N], values [N, 3], cov [N, 3, 3])`` from ``odom2`` or ``odom2diff`` records;
    ``(times, [N, 4], [N, 4, 4])`` from ``odom3`` (module docstring)."""
    if len(rec.tables.get("odom3", ())):
        tab = rec.tables["odom3"]
        cols = [1, 2, 3, 6]  # vx, vy, vz, wz
        return tab[:, 0], tab[:, cols], np.stack([np.diag(r) for r in tab[:, [c + 6 for c in cols]]])
    if len(rec.tables.get("odom2", ())):
        tab = rec.tables["odom2"]
        return tab[:, 0], tab[:, 1:4], np.stack([np.diag(r) for r in tab[:, 4:7]]) if len(tab) else np.zeros((0, 3, 3))
    tab = rec.tables["odom2diff"]
    vr, vl, vy, b = tab[:, 1], tab[:, 2], tab[:, 3], tab[:, 4]
    if np.any(b <= 0):
        row = int(np.argmax(b <= 0))
        raise ValueError(f"{rec.where('odom2diff', row)}: wheel base must be positive, got {b[row]}")
    vals = np.stack([(vr + vl) / 2, vy, (vr - vl) / b], -1)
    # d(v, vy, w)/d(vr, vl, vy): J diag(var) J^T
    jac = np.zeros((len(tab), 3, 3))
    jac[:, 0, 0], jac[:, 0, 1], jac[:, 1, 2] = 0.5, 0.5, 1.0
    jac[:, 2, 0], jac[:, 2, 1] = 1.0 / b, -1.0 / b
    cov = jac @ (tab[:, 5:8, None] * np.eye(3)) @ jac.transpose(0, 2, 1)
    return tab[:, 0], vals, cov


def load_ranging(
    input_path: str | Path, truth_path: str | Path | None = None, *, min_ranges: int = 1, on_error: str = "raise"
) -> RangingRecording:
    """Assemble a 2-D or 3-D ranging recording (module docstring).

    Args:
        input_path: libRSF file with ``range2`` and ``odom2`` or ``odom2diff`` records, or
            ``range3`` and optionally ``odom3`` records.
        truth_path: libRSF file with ``point2`` (``point3``) records (optional).
        min_ranges: steps with fewer ranges are masked (prediction only) and counted.
        on_error: passed to :func:`~difffilter.datasets.librsf.read_librsf`.

    Raises:
        FileNotFoundError: a file is missing.
        ValueError: no ranges; ``range2`` without odometry; mixed kinds (``range2`` with
            ``range3``, 2-D with 3-D odometry); an anchor twice in one step; a wheel base that is
            not positive (the message names file and line).
    """
    rec = read_librsf(input_path, ["range2", "range3", "odom2", "odom2diff", "odom3"], on_error=on_error)
    issues = dict(rec.skipped)
    dim = 3 if len(rec.tables["range3"]) and not len(rec.tables["range2"]) else 2
    kind = f"range{dim}"
    if not len(rec.tables[kind]):
        raise ValueError(f"{rec.path}: no range2 or range3 records (kinds found: {sorted(rec.kinds()) or 'none'})")
    if len(rec.tables["range2"]) and len(rec.tables["range3"]):
        raise ValueError(f"{rec.path}: both range2 and range3 records; keep one ranging kind per file")
    odom_kinds = [k for k in (("odom2", "odom2diff") if dim == 2 else ("odom3",)) if len(rec.tables[k])]
    wrong = [k for k in ("odom2", "odom2diff", "odom3") if len(rec.tables[k]) and k not in odom_kinds]
    if wrong:
        raise ValueError(f"{rec.path}: {wrong[0]} records do not go with {kind} (2-D: odom2/odom2diff; 3-D: odom3)")
    if dim == 2 and not odom_kinds:
        raise ValueError(f"{rec.path}: no odom2 or odom2diff records")
    if len(odom_kinds) > 1:
        raise ValueError(f"{rec.path}: both odom2 and odom2diff records; keep one odometry kind per file")
    has_odom = bool(odom_kinds)
    rng = rec.tables[kind]
    o_t, o_val, o_cov = _odometry(rec) if has_odom else (np.zeros(0), np.zeros((0, 0)), np.zeros((0, 0, 0)))
    times = np.unique(np.concatenate([rng[:, 0], o_t]))
    ids = np.unique(rng[:, 3 + dim])
    t_idx, a_idx = np.searchsorted(times, rng[:, 0]), np.searchsorted(ids, rng[:, 3 + dim])
    steps, num_a = len(times), len(ids)
    seen = np.full((steps, num_a), -1, dtype=np.int64)
    for row, (k, a) in enumerate(zip(t_idx, a_idx, strict=True)):
        if seen[k, a] >= 0:
            raise ValueError(
                f"{rec.where(kind, row)}: anchor {int(ids[a])} measured twice at t={times[k]} (first at line {rec.lines[kind][seen[k, a]]})"
            )
        seen[k, a] = row
    mask = seen >= 0
    ranges, var = np.zeros((steps, num_a)), np.ones((steps, num_a))
    ranges[t_idx, a_idx], var[t_idx, a_idx] = rng[:, 1], rng[:, 2]
    bad = var[mask] <= 0
    if np.any(bad):
        row = int(seen[mask][bad][0])
        raise ValueError(f"{rec.where(kind, row)}: range variance must be positive, got {rng[row, 2]}")
    anchors = np.full((steps, num_a, dim), np.nan)
    anchors[t_idx, a_idx] = rng[:, 3 : 3 + dim]
    for a in range(num_a):  # hold the last known position (first known before it)
        col = anchors[:, a]
        known = np.flatnonzero(~np.isnan(col[:, 0]))
        fill = known[np.clip(np.searchsorted(known, np.arange(steps), side="right") - 1, 0, None)]
        anchors[:, a] = col[fill]
    thin = mask.sum(1) < int(min_ranges)
    thin &= mask.sum(1) > 0
    if thin.any():
        issues[f"steps with fewer than {min_ranges} ranges"] = int(thin.sum())
        mask[thin] = False
    n_odom = o_val.shape[1] if has_odom else 0
    odom, odom_cov = np.zeros((steps, n_odom)), np.tile(np.eye(n_odom), (steps, 1, 1))
    o_idx = np.searchsorted(times, o_t)
    odom[o_idx], odom_cov[o_idx] = o_val, o_cov
    has = np.zeros(steps, dtype=bool)
    has[o_idx] = True
    held = np.flatnonzero(~has[1:]) + 1 if has_odom else np.zeros(0, dtype=np.int64)
    if len(held):
        issues["steps without odometry (previous record held)"] = int(len(held))
        src = np.flatnonzero(has)
        prev = src[np.clip(np.searchsorted(src, held) - 1, 0, None)]
        odom[held], odom_cov[held] = odom[prev], odom_cov[prev]
    truth, heading0, heading = np.full((steps, dim), np.nan), None, np.full(steps, np.nan)
    if truth_path is not None:
        gt = read_librsf(truth_path, [f"point{dim}", "angle"], on_error=on_error)
        pts = gt.tables[f"point{dim}"]
        if not len(pts):
            raise ValueError(f"{gt.path}: no point{dim} records")
        k = np.searchsorted(times, pts[:, 0])
        ok = (k < steps) & (times[np.clip(k, 0, steps - 1)] == pts[:, 0])
        truth[k[ok]] = pts[ok, 1 : 1 + dim]
        ang = gt.tables["angle"]
        if len(ang) and ang[0, 0] == times[0]:
            heading0 = float(ang[0, 1])
        k = np.searchsorted(times, ang[:, 0])
        ok = (k < steps) & (times[np.clip(k, 0, steps - 1)] == ang[:, 0])
        heading[k[ok]] = ang[ok, 1]
    if issues:
        warnings.warn(f"{rec.path}: {issues}", stacklevel=2)
    dt = np.concatenate([[0.0], np.diff(times)])
    name = re.sub(r"_Input$", "", Path(input_path).stem)
    return RangingRecording(
        name, times, dt, odom, odom_cov, ranges, var, mask, anchors, ids, truth, heading0, issues, heading, dim, has_odom
    )


def find_recordings(folder: str | Path) -> list[tuple[str, Path, Path | None]]:
    """``(name, input, truth)`` of every ``<name>_Input.txt`` in ``folder``; the truth is
    ``<name>_GT.txt`` or, for inputs sharing one truth (``W3500_skewed_Input.txt``), the
    ``<prefix>_GT.txt`` of the longest ``_``-separated prefix of ``name`` that has one."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder")
    out = []
    for inp in sorted(folder.glob("*_Input.txt")):
        name = inp.name[: -len("_Input.txt")]
        parts = name.split("_")
        truth = None
        for n in range(len(parts), 0, -1):
            cand = folder / ("_".join(parts[:n]) + "_GT.txt")
            if cand.is_file():
                truth = cand
                break
        out.append((name, inp, truth))
    if not out:
        raise FileNotFoundError(f"{folder}: no data set found (no <name>_Input.txt file)")
    return out


def folder_kind(folder: str | Path) -> str:
    """``"ranging2d"`` if the folder's inputs hold ``range2`` records, ``"ranging3d"`` if they hold
    ``range3``, ``"pseudorange"`` if they hold ``pseudorange3``; ``ValueError`` naming the file
    otherwise (or if they differ)."""
    kinds = set()
    for _name, inp, _gt in find_recordings(folder):
        found = detect_kinds(inp)
        if "range2" in found:
            kinds.add("ranging2d")
        elif "range3" in found:
            kinds.add("ranging3d")
        elif "pseudorange3" in found:
            kinds.add("pseudorange")
        else:
            raise ValueError(f"{inp}: neither range2, range3 nor pseudorange3 records (kinds: {sorted(found)})")
    if len(kinds) > 1:
        raise ValueError(f"{folder}: the inputs mix kinds {sorted(kinds)}; put each kind in its own folder")
    return kinds.pop()
