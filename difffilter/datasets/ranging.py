"""2-D ranging recordings (``range2`` to fixed anchors, ``odom2``/``odom2diff`` odometry,
``point2`` ground truth) assembled into per-step arrays, and the discovery of data sets in a
folder of libRSF files.

Time base: the sorted union of the range and odometry time stamps.  An odometry record at time
``t_k`` describes the motion from ``t_{k-1}`` to ``t_k`` (body-frame velocity and turn rate; the
libRSF ranging sets move with the heading of ``t_{k-1}`` and then turn), so step ``k`` of the
filter predicts with it; a step without odometry keeps the previous record (counted).
``odom2diff`` is converted to body velocity and turn rate: ``v = (v_r + v_l) / 2``,
``w = (v_r - v_l) / b`` with the covariance propagated (including the ``v``-``w`` cross term).
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
    """One 2-D ranging recording as per-step arrays (``T`` steps, ``A`` anchors).

    Attributes:
        name: data set name (the input file's stem without ``_Input``).
        times: ``[T]`` s.
        dt: ``[T]`` s (``dt[0] = 0``).
        odom: ``[T, 3]`` body velocity x, y (m/s) and turn rate (rad/s) of the step ending at each time.
        odom_cov: ``[T, 3, 3]`` their covariance (the file's variances: the hand-tuned values).
        ranges: ``[T, A]`` m (0 where missing); ``range_var`` ``[T, A]`` the file's variances
            (1 where missing); ``mask`` ``[T, A]`` True where a range was measured and used.
        anchors: ``[T, A, 2]`` anchor positions as the file gives them per line (the last known
            position where missing); ``anchor_ids`` ``[A]``.
        truth: ``[T, 2]`` reference position (NaN without a ``point2`` at that time);
            ``heading0``: the reference heading at the first step if the truth file has ``angle`` records;
            ``heading`` ``[T]`` the reference heading at every step (NaN without an ``angle`` record
            at that time; None when the recording was built without it).
        issues: counts of what was skipped or repaired.
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

    @property
    def num_steps(self) -> int:
        return int(self.times.shape[0])

    @property
    def num_anchors(self) -> int:
        return int(self.anchor_ids.shape[0])


def _odometry(rec: LibrsfFile) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(times [N], values [N, 3], cov [N, 3, 3])`` from ``odom2`` or ``odom2diff`` records."""
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
    """Assemble a 2-D ranging recording (module docstring).

    Args:
        input_path: libRSF file with ``range2`` and ``odom2`` or ``odom2diff`` records.
        truth_path: libRSF file with ``point2`` records (optional).
        min_ranges: steps with fewer ranges are masked (prediction only) and counted.
        on_error: passed to :func:`~difffilter.datasets.librsf.read_librsf`.

    Raises:
        FileNotFoundError: a file is missing.
        ValueError: no ``range2`` or no odometry records; an anchor twice in one step; a wheel
            base that is not positive (the message names file and line).
    """
    rec = read_librsf(input_path, ["range2", "odom2", "odom2diff"], on_error=on_error)
    issues = dict(rec.skipped)
    if not len(rec.tables["range2"]):
        raise ValueError(f"{rec.path}: no range2 records (kinds found: {sorted(rec.kinds()) or 'none'})")
    if not (len(rec.tables["odom2"]) or len(rec.tables["odom2diff"])):
        raise ValueError(f"{rec.path}: no odom2 or odom2diff records")
    if len(rec.tables["odom2"]) and len(rec.tables["odom2diff"]):
        raise ValueError(f"{rec.path}: both odom2 and odom2diff records; keep one odometry kind per file")
    rng = rec.tables["range2"]
    o_t, o_val, o_cov = _odometry(rec)
    times = np.unique(np.concatenate([rng[:, 0], o_t]))
    ids = np.unique(rng[:, 5])
    t_idx, a_idx = np.searchsorted(times, rng[:, 0]), np.searchsorted(ids, rng[:, 5])
    steps, num_a = len(times), len(ids)
    seen = np.full((steps, num_a), -1, dtype=np.int64)
    for row, (k, a) in enumerate(zip(t_idx, a_idx, strict=True)):
        if seen[k, a] >= 0:
            raise ValueError(
                f"{rec.where('range2', row)}: anchor {int(ids[a])} measured twice at t={times[k]} "
                f"(first at line {rec.lines['range2'][seen[k, a]]})"
            )
        seen[k, a] = row
    mask = seen >= 0
    ranges, var = np.zeros((steps, num_a)), np.ones((steps, num_a))
    ranges[t_idx, a_idx], var[t_idx, a_idx] = rng[:, 1], rng[:, 2]
    bad = var[mask] <= 0
    if np.any(bad):
        row = int(seen[mask][bad][0])
        raise ValueError(f"{rec.where('range2', row)}: range variance must be positive, got {rng[row, 2]}")
    anchors = np.full((steps, num_a, 2), np.nan)
    anchors[t_idx, a_idx] = rng[:, 3:5]
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
    odom, odom_cov = np.zeros((steps, 3)), np.tile(np.eye(3), (steps, 1, 1))
    o_idx = np.searchsorted(times, o_t)
    odom[o_idx], odom_cov[o_idx] = o_val, o_cov
    has = np.zeros(steps, dtype=bool)
    has[o_idx] = True
    held = np.flatnonzero(~has[1:]) + 1
    if len(held):
        issues["steps without odometry (previous record held)"] = int(len(held))
        src = np.flatnonzero(has)
        prev = src[np.clip(np.searchsorted(src, held) - 1, 0, None)]
        odom[held], odom_cov[held] = odom[prev], odom_cov[prev]
    truth, heading0, heading = np.full((steps, 2), np.nan), None, np.full(steps, np.nan)
    if truth_path is not None:
        gt = read_librsf(truth_path, ["point2", "angle"], on_error=on_error)
        pts = gt.tables["point2"]
        if not len(pts):
            raise ValueError(f"{gt.path}: no point2 records")
        k = np.searchsorted(times, pts[:, 0])
        ok = (k < steps) & (times[np.clip(k, 0, steps - 1)] == pts[:, 0])
        truth[k[ok]] = pts[ok, 1:3]
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
    return RangingRecording(name, times, dt, odom, odom_cov, ranges, var, mask, anchors, ids, truth, heading0, issues, heading)


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
    """``"ranging2d"`` if the folder's inputs hold ``range2`` records, ``"pseudorange"`` if they
    hold ``pseudorange3``; ``ValueError`` naming the file otherwise (or if they differ)."""
    kinds = set()
    for _name, inp, _gt in find_recordings(folder):
        found = detect_kinds(inp)
        if "range2" in found:
            kinds.add("ranging2d")
        elif "pseudorange3" in found:
            kinds.add("pseudorange")
        else:
            raise ValueError(f"{inp}: neither range2 nor pseudorange3 records (kinds: {sorted(found)})")
    if len(kinds) > 1:
        raise ValueError(f"{folder}: the inputs mix kinds {sorted(kinds)}; put each kind in its own folder")
    return kinds.pop()
