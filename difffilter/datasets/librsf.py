"""A reader for the libRSF text format: one record per line, fields separated by white space,
the first token naming the record kind, the second its time stamp (s).

Columns of the kinds read (after the kind token; from the libRSF data-type table and the data
sets' readme files, checked against the files):

* ``pseudorange3``: t, range (m), variance (m^2), satellite x, y, z (m), id, system, elevation (deg), C/N0 (dB-Hz)
* ``range3``: t, range, variance, anchor x, y, z, id [, snr]
* ``range2``: t, range, variance, anchor x, y, id [, snr]
* ``odom3``: t, vx, vy, vz (m/s), wx, wy, wz (rad/s), then their six variances
* ``odom2``: t, vx, vy (m/s, body frame), turn rate (rad/s), then their three variances
* ``odom2diff``: t, right wheel speed, left wheel speed, vy (m/s), wheel base (m), then the
  variances of the three speeds
* ``point2``: t, x, y [, 2x2 covariance];  ``point3``: t, x, y, z [, 3x3 covariance]
* ``angle``: t, angle (rad) [, variance]

Bad input is reported, never mis-read: a missing file raises ``FileNotFoundError``; a line of a
read kind with too few fields or a field that is not a finite number, and a time stamp that goes
back within one kind, raise ``ValueError`` naming the file and the line (``on_error="skip"``
skips the malformed line instead and counts it); a kind not in the table is skipped and counted
(``strict=True`` raises), known kinds not asked for are skipped and counted too, and the counts
are issued as one warning per file.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["COLUMNS", "LibrsfFile", "OPTIONAL", "detect_kinds", "read_librsf"]

#: Column names of every record kind (after the kind token).
COLUMNS: dict[str, tuple[str, ...]] = {
    "pseudorange3": ("t", "range", "var", "sx", "sy", "sz", "id", "system", "elevation", "cn0"),
    "range3": ("t", "range", "var", "ax", "ay", "az", "id", "snr"),
    "range2": ("t", "range", "var", "ax", "ay", "id", "snr"),
    "odom3": ("t", "vx", "vy", "vz", "wx", "wy", "wz", "var_vx", "var_vy", "var_vz", "var_wx", "var_wy", "var_wz"),
    "odom2": ("t", "vx", "vy", "wz", "var_vx", "var_vy", "var_wz"),
    "odom2diff": ("t", "v_right", "v_left", "vy", "wheel_base", "var_right", "var_left", "var_vy"),
    "point2": ("t", "x", "y"),
    "point3": ("t", "x", "y", "z"),
    "angle": ("t", "angle"),
}
#: How many trailing columns of a kind may be absent (filled with 0).
OPTIONAL: dict[str, int] = {"range2": 1, "range3": 1}


@dataclass
class LibrsfFile:
    """The records of one file.

    Attributes:
        path: the file.
        tables: ``{kind: [N, len(COLUMNS[kind])]}`` float64 arrays, rows in file order.
        lines: ``{kind: [N]}`` 1-based line numbers of the rows.
        skipped: counts of what was skipped (``"unknown kind imu3"``, ``"malformed range2"``).
    """

    path: Path
    tables: dict[str, np.ndarray]
    lines: dict[str, np.ndarray]
    skipped: dict[str, int] = field(default_factory=dict)

    def kinds(self) -> set[str]:
        """The record kinds with at least one row."""
        return {k for k, v in self.tables.items() if len(v)}

    def column(self, kind: str, name: str) -> np.ndarray:
        """Column ``name`` of ``kind``'s table ``[N]``."""
        return self.tables[kind][:, COLUMNS[kind].index(name)]

    def where(self, kind: str, row: int) -> str:
        """``"file:line"`` of row ``row`` of ``kind`` (for error messages)."""
        return f"{self.path}:{int(self.lines[kind][row])}"


def _parse(tokens: list[str], kind: str, path: Path, lineno: int, ncols: int | None = None) -> list[float]:
    cols = COLUMNS[kind][:ncols] if ncols is not None else COLUMNS[kind]
    need = len(cols) - (OPTIONAL.get(kind, 0) if ncols is None else 0)
    if len(tokens) - 1 < need:
        raise ValueError(f"{path}:{lineno}: a {kind} line needs at least {need + 1} fields, got {len(tokens)}")
    out = []
    for i, tok in enumerate(tokens[1 : len(cols) + 1], start=2):
        try:
            v = float(tok)
        except ValueError:
            raise ValueError(f"{path}:{lineno}: field {i} of a {kind} line is not a number: {tok!r}") from None
        if not math.isfinite(v):
            raise ValueError(f"{path}:{lineno}: field {i} of a {kind} line is not finite: {tok!r}")
        out.append(v)
    return out + [0.0] * (len(cols) - len(out))


def read_librsf(
    path: str | Path,
    kinds: Iterable[str] | None = None,
    *,
    strict: bool = False,
    on_error: str = "raise",
    columns: Mapping[str, int] | None = None,
) -> LibrsfFile:
    """Read the records of ``kinds`` (default: every kind of :data:`COLUMNS`) from a libRSF file.

    Args:
        path: the file.
        kinds: the kinds to read; other known kinds are skipped silently.
        strict: raise on a kind not in :data:`COLUMNS` instead of skipping and counting it.
        on_error: ``"raise"`` (default) or ``"skip"`` (count malformed lines instead).
        columns: ``{kind: n}`` reads only the first ``n`` columns of ``kind`` (and needs only
            those); default: every column of :data:`COLUMNS`.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: a malformed line, an unknown kind with ``strict``, or a time stamp that goes
            back within one kind (always an error: sorting would hide a broken file); the message
            names the file and the line.
    """
    if on_error not in ("raise", "skip"):
        raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such libRSF file")
    wanted = set(COLUMNS if kinds is None else kinds)
    unknown = wanted - set(COLUMNS)
    if unknown:
        raise ValueError(f"kinds {sorted(unknown)} are not libRSF kinds this reader knows: {sorted(COLUMNS)}")
    ncols = dict(columns or {})
    bad = {k: n for k, n in ncols.items() if k not in COLUMNS or not 1 <= int(n) <= len(COLUMNS[k])}
    if bad:
        raise ValueError(f"columns {bad} out of range (per kind: 1 .. number of COLUMNS)")
    rows: dict[str, list[list[float]]] = {k: [] for k in wanted}
    lines: dict[str, list[int]] = {k: [] for k in wanted}
    skipped: dict[str, int] = {}
    last: dict[str, tuple[float, int]] = {}
    with open(path) as fh:
        for lineno, text in enumerate(fh, start=1):
            tokens = text.split()
            if not tokens or tokens[0].startswith("#"):
                continue
            kind = tokens[0]
            if kind not in COLUMNS:
                if strict:
                    raise ValueError(f"{path}:{lineno}: unknown record kind {kind!r} (known: {sorted(COLUMNS)})")
                skipped[f"unknown kind {kind}"] = skipped.get(f"unknown kind {kind}", 0) + 1
                continue
            if kind not in wanted:
                skipped[f"unread kind {kind}"] = skipped.get(f"unread kind {kind}", 0) + 1
                continue
            try:
                vals = _parse(tokens, kind, path, lineno, ncols.get(kind))
            except ValueError:
                if on_error == "raise":
                    raise
                skipped[f"malformed {kind}"] = skipped.get(f"malformed {kind}", 0) + 1
                continue
            if kind in last and vals[0] < last[kind][0]:
                prev_t, prev_line = last[kind]
                raise ValueError(f"{path}:{lineno}: {kind} time stamp {vals[0]} goes back (line {prev_line} has {prev_t})")
            last[kind] = (vals[0], lineno)
            rows[kind].append(vals)
            lines[kind].append(lineno)
    if skipped:
        warnings.warn(f"{path}: skipped {dict(sorted(skipped.items()))}", stacklevel=2)
    tables = {k: np.asarray(v, dtype=np.float64).reshape(-1, ncols.get(k, len(COLUMNS[k]))) for k, v in rows.items()}
    return LibrsfFile(path, tables, {k: np.asarray(v, dtype=np.int64) for k, v in lines.items()}, skipped)


def detect_kinds(path: str | Path, *, max_lines: int | None = None) -> dict[str, int]:
    """``{kind: line count}`` of the first tokens of a file (every line, or the first ``max_lines``)."""
    counts: dict[str, int] = {}
    with open(path) as fh:
        for i, text in enumerate(fh):
            if max_lines is not None and i >= max_lines:
                break
            tokens = text.split(maxsplit=1)
            if tokens and not tokens[0].startswith("#"):
                counts[tokens[0]] = counts.get(tokens[0], 0) + 1
    return counts
