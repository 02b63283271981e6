"""Small libRSF drives cut from the real smartLoc files, for loader and protocol tests."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from experiments.papers.smartloc import default_smartloc_path

SOURCE = default_smartloc_path()
INPUT, TRUTH = "Berlin_Potsdamer_Platz_Input.txt", "Berlin_Potsdamer_Platz_GT.txt"
HAVE_DATA = (SOURCE / INPUT).exists()


def write_drive(
    folder: Path,
    name: str = "Fixture",
    *,
    start: float = 0.0,
    stop: float = 30.0,
    edit: Callable[[list[str]], list[str]] | None = None,
) -> tuple[Path, Path]:
    """``folder/<name>_Input.txt`` and ``_GT.txt`` holding the real drive's lines with
    ``start <= t < stop``; ``edit`` may change the input's lines (a list of strings) first."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for src, suffix in ((INPUT, "_Input.txt"), (TRUTH, "_GT.txt")):
        lines = [ln for ln in (SOURCE / src).read_text().splitlines() if ln.split() and start <= float(ln.split()[1]) < stop]
        if edit is not None and suffix == "_Input.txt":
            lines = edit(lines)
        path = folder / f"{name}{suffix}"
        path.write_text("\n".join(lines) + "\n")
        paths.append(path)
    return paths[0], paths[1]
