"""The python snippets of one README section, for the tests that run them as written."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def readme_snippets(heading: str) -> list[str]:
    """The ```python blocks between ``heading`` and the next heading of README.md."""
    text = (ROOT / "README.md").read_text()
    start = text.index(heading)
    end = text.index("\n#", start + len(heading))
    return re.findall(r"```python\n(.*?)```", text[start:end], re.S)


def run_snippet(code: str) -> dict:
    """Execute a snippet in a fresh namespace and return the namespace."""
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)  # noqa: S102 - our own README
    return namespace
