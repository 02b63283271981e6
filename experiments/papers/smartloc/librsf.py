"""Reading libRSF text files (the smartLoc conversion's format) with errors that name file and line.

A libRSF text file holds one record per line, fields separated by white space, the first token
naming the record type.  The smartLoc drives use three types (upstream readme; data README in
``../shared/data/real/smartloc_berlin_potsdamer``):

* ``pseudorange3 t rho var x y z id system elevation cn0`` (11 fields): one satellite at time ``t``
  (s), pseudorange and its variance (m, m^2), satellite ECEF position (m), satellite id, system
  (1 GPS, 2 SBAS, 4 GLONASS, 8 Galileo, 16 QZSS, 32 BeiDou), elevation (deg), C/N0 (dB-Hz);
* ``odom3 t vx vy vz wx wy wz ...`` (14 fields, the first 8 used): body velocity (m/s) and turn
  rates (rad/s, ``wz`` positive = left turn);
* ``point3 t x y z ...`` (14 fields, the first 5 used): reference position, ECEF (m).

:func:`read_records` checks what a filter would otherwise silently mis-read: a missing file
(``FileNotFoundError``), a line with too few fields or a field that is not a finite number, and
time stamps that go back within one record type (``ValueError`` naming the file and line).
Record types it does not read are skipped and counted.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["FIELDS", "Records", "read_records"]

#: Fields used of each record type (including the type token).
FIELDS: dict[str, int] = {"pseudorange3": 11, "odom3": 8, "point3": 5}


@dataclass
class Records:
    """The records of one file: ``values[kind] [N, FIELDS[kind] - 1]`` (float64, the type token
    dropped), ``lines[kind] [N]`` their 1-based line numbers, ``skipped`` the counts of record
    types not read."""

    path: Path
    values: dict[str, np.ndarray]
    lines: dict[str, np.ndarray]
    skipped: dict[str, int] = field(default_factory=dict)

    def where(self, kind: str, row: int) -> str:
        """``"file:line"`` of record ``row`` of ``kind`` (for error messages)."""
        return f"{self.path}:{int(self.lines[kind][row])}"


def _number(token: str, path: Path, lineno: int, kind: str, column: int) -> float:
    try:
        value = float(token)
    except ValueError:
        raise ValueError(f"{path}:{lineno}: field {column + 1} of a {kind} line is not a number: {token!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"{path}:{lineno}: field {column + 1} of a {kind} line is not finite: {token!r}")
    return value


def read_records(path: str | Path, kinds: Mapping[str, int] | None = None, *, role: str = "libRSF") -> Records:
    """Read the records of ``kinds`` (``{type: fields used}``, default :data:`FIELDS`) from a
    libRSF text file.

    Raises:
        FileNotFoundError: the file does not exist (the message says which ``role`` it plays).
        ValueError: a line of a read type has too few fields, a field that is not a finite number,
            or a time stamp (field 2) below the previous one of the same type; the message names
            the file and the line.
    """
    kinds = dict(FIELDS if kinds is None else kinds)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file (the {role} file)")
    rows: dict[str, list[list[float]]] = {k: [] for k in kinds}
    lines: dict[str, list[int]] = {k: [] for k in kinds}
    skipped: dict[str, int] = {}
    last: dict[str, tuple[float, int]] = {}
    with open(path) as fh:
        for lineno, text in enumerate(fh, start=1):
            tokens = text.split()
            if not tokens or tokens[0].startswith("#"):
                continue
            kind = tokens[0]
            if kind not in kinds:
                skipped[kind] = skipped.get(kind, 0) + 1
                continue
            need = kinds[kind]
            if len(tokens) < need:
                raise ValueError(f"{path}:{lineno}: a {kind} line needs at least {need} fields, got {len(tokens)}")
            vals = [_number(tok, path, lineno, kind, i) for i, tok in enumerate(tokens[1:need], start=1)]
            t = vals[0]
            if kind in last and t < last[kind][0]:
                prev_t, prev_line = last[kind]
                raise ValueError(
                    f"{path}:{lineno}: {kind} time stamp {t} goes back (line {prev_line} has {prev_t}); time stamps must not decrease"
                )
            last[kind] = (t, lineno)
            rows[kind].append(vals)
            lines[kind].append(lineno)
    values = {k: np.asarray(v, dtype=np.float64).reshape(-1, kinds[k] - 1) for k, v in rows.items()}
    return Records(path=path, values=values, lines={k: np.asarray(v, dtype=np.int64) for k, v in lines.items()}, skipped=skipped)
