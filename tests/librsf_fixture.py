"""Small libRSF drives cut from the real smartLoc files, for loader and protocol tests.

The lines come from the excerpt shipped in ``tests/assets/librsf/smartlocx_{Input,GT}.txt.gz``
(the drive's lines with ``0 <= t < 30`` or ``100 <= t < 140`` s, unchanged; CC BY-SA 4.0,
attribution in that folder's README), so these tests run in a fresh clone without the full data
set; ``HAVE_FULL`` says whether the whole drive is on disk too (for comparisons against it)."""

from __future__ import annotations

import gzip
from collections.abc import Callable
from functools import cache
from pathlib import Path

from experiments.papers.smartloc import default_smartloc_path

SOURCE = default_smartloc_path()
INPUT, TRUTH = "Berlin_Potsdamer_Platz_Input.txt", "Berlin_Potsdamer_Platz_GT.txt"
HAVE_FULL = (SOURCE / INPUT).exists()
EXCERPT = Path(__file__).resolve().parent / "assets" / "librsf"
#: Time spans (s) of the drive the excerpt holds.
SPANS = ((0.0, 30.0), (100.0, 140.0))
HAVE_DATA = (EXCERPT / "smartlocx_Input.txt.gz").exists()


@cache
def _excerpt(suffix: str) -> tuple[str, ...]:
    with gzip.open(EXCERPT / f"smartlocx{suffix}.gz", "rt") as fh:
        return tuple(fh.read().splitlines())


def write_drive(
    folder: Path,
    name: str = "Fixture",
    *,
    start: float = 0.0,
    stop: float = 30.0,
    edit: Callable[[list[str]], list[str]] | None = None,
) -> tuple[Path, Path]:
    """``folder/<name>_Input.txt`` and ``_GT.txt`` holding the real drive's lines with
    ``start <= t < stop`` (inside one span of :data:`SPANS`); ``edit`` may change the input's
    lines (a list of strings) first."""
    if not any(a <= start < stop <= b for a, b in SPANS):
        raise ValueError(f"[{start}, {stop}) is not inside one span of the shipped excerpt {SPANS}")
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for suffix in ("_Input.txt", "_GT.txt"):
        lines = [ln for ln in _excerpt(suffix) if ln.split() and start <= float(ln.split()[1]) < stop]
        if edit is not None and suffix == "_Input.txt":
            lines = edit(lines)
        path = folder / f"{name}{suffix}"
        path.write_text("\n".join(lines) + "\n")
        paths.append(path)
    return paths[0], paths[1]
