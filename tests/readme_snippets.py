"""The fenced code blocks of README.md and docs/*.md, for the tests that run them as written.

A ```python block runs.  Any other block (shell commands, console output, a directory map), or a
python block that needs data a fresh clone does not have, carries a marker on the line before its
fence: ``<!-- snippet: skip (reason) -->``.  ``<!-- snippet: slow -->`` runs the block in the slow
suite only.
"""

from __future__ import annotations

import functools
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
_FENCE = re.compile(r"^```([\w+-]*)[^\n]*\n(.*?)^```[ \t]*$", re.S | re.M)
_MARKER = re.compile(r"<!--\s*snippet:\s*(skip|slow)\s*(?:\((.*)\))?\s*-->\s*$")

__all__ = ["ROOT", "Block", "doc_blocks", "doc_pages", "readme_snippets", "page_namespace", "run_snippet", "section_snippets"]


@dataclass(frozen=True)
class Block:
    """One fenced block: its language, code, 1-based line and the marker before it (if any)."""

    lang: str
    code: str
    line: int
    marker: str | None
    reason: str | None


def doc_pages() -> list[Path]:
    """README.md and every Markdown page under docs/."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def doc_blocks(text: str) -> list[Block]:
    """The fenced blocks of a Markdown text, in order."""
    out = []
    for match in _FENCE.finditer(text):
        before = text[: match.start()].rstrip("\n").rsplit("\n", 1)[-1]
        marker = _MARKER.search(before)
        out.append(
            Block(
                lang=match.group(1),
                code=match.group(2),
                line=text.count("\n", 0, match.start()) + 1,
                marker=marker.group(1) if marker else None,
                reason=(marker.group(2) or "").strip() if marker else None,
            )
        )
    return out


def section_snippets(path: Path | str, heading: str) -> list[str]:
    """The ```python blocks between ``heading`` and the next heading of the page ``path``."""
    text = (ROOT / path).read_text()
    start = text.index(heading)
    end = text.find("\n#", start + len(heading))
    section = text[start : end if end >= 0 else len(text)]
    return [b.code for b in doc_blocks(section) if b.lang == "python"]


def readme_snippets(heading: str) -> list[str]:
    """The ```python blocks between ``heading`` and the next heading of README.md."""
    return section_snippets("README.md", heading)


def run_snippet(code: str, namespace: dict | None = None, filename: str = "README.md") -> dict:
    """Execute a snippet (in a fresh namespace unless one is given) and return the namespace."""
    namespace = {} if namespace is None else namespace
    exec(compile(code, filename, "exec"), namespace)  # noqa: S102 - our own documentation
    return namespace


@functools.cache
def page_namespace(relpath: str) -> dict:
    """Run every runnable block of one page in order, in one namespace, as a reader would, and
    return it (cached: the generic test and a page's own test share one run).

    The library must not warn while its documented examples run (UserWarning is an error here);
    torch's thread count and default dtype are restored afterwards (examples may set them; a
    leaked default dtype changes every later test's tensors).
    """
    path = ROOT / relpath
    namespace: dict = {}
    threads, dtype = torch.get_num_threads(), torch.get_default_dtype()
    torch.manual_seed(0)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", UserWarning)
            for b in doc_blocks(path.read_text()):
                if b.lang == "python" and b.marker != "skip":
                    run_snippet(b.code, namespace, filename=f"{relpath}:{b.line}")
    finally:
        torch.set_num_threads(threads)
        torch.set_default_dtype(dtype)
    return namespace
