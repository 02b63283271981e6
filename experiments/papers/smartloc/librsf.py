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

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from difffilter.datasets.librsf import read_librsf

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


def read_records(path: str | Path, kinds: Mapping[str, int] | None = None, *, role: str = "libRSF") -> Records:
    """Read the records of ``kinds`` (``{type: fields used}``, default :data:`FIELDS`) from a
    libRSF text file (the generic reader :func:`difffilter.datasets.read_librsf` does the work;
    this keeps the smartLoc loader's ``{type: fields}`` interface and its messages).

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
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the loader reports the counts itself (SmartLocData.issues)
        rec = read_librsf(path, list(kinds), columns={k: n - 1 for k, n in kinds.items()})
    skipped = {k.removeprefix("unknown kind ").removeprefix("unread kind "): v for k, v in rec.skipped.items()}
    return Records(path=path, values=rec.tables, lines=rec.lines, skipped=skipped)
