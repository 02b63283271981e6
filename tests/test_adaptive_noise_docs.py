"""The usage example of docs/adaptive.md runs as written and does what it says."""

from __future__ import annotations

import re
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def test_docs_example_runs_and_learns_b():
    text = (ROOT / "docs" / "adaptive.md").read_text()
    block = re.findall(r"```python\n(.*?)```", text, re.S)[0]
    assert len(block.strip().splitlines()) <= 25
    namespace: dict = {}
    default = torch.get_default_dtype()
    try:
        exec(compile(block, "docs/adaptive.md", "exec"), namespace)  # noqa: S102 - our own docs
    finally:
        torch.set_default_dtype(default)
    flt, res = namespace["flt"], namespace["res"]
    assert abs(float(flt.b.detach()) - 0.7) > 0.05
    # the noise variance after the jump is 25 (the model says 1): the estimates follow it
    assert float(res.noise_R[:, -1, 0, 0].detach().mean()) > 5.0
