"""The usage examples of docs/parallel.md run as written."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_docs_examples_run():
    text = (ROOT / "docs" / "parallel.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 2
    namespace: dict = {}
    for block in blocks:  # one namespace: the second example uses the first's data
        exec(compile(block, "docs/parallel.md", "exec"), namespace)  # noqa: S102 - our own docs
    assert namespace["out"].mean.shape[0] == 3
