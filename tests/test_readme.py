"""The README's usage example runs as written, and its test command is the one CI runs."""

from __future__ import annotations

import re
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def test_readme_python_example_runs():
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert blocks
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)  # noqa: S102 - our own README
    res = namespace["res"]
    assert res.mean.shape == (32, 100, 4)
    assert torch.isfinite(res.mean).all()
    assert namespace["model"].measurement.angular == (1,)  # the example's bearing is declared an angle (wrapped)
    raw = namespace["model"].measurement.parametrizations.R.original
    assert raw.grad is not None and torch.isfinite(raw.grad).all()


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    command = "python -m pytest -q"
    assert f"&& {command}\n" in readme
    assert f"\n{command}\n" in ci
    # the slow suite runs as its own step, after the default suite
    slow = f"\n{command} -m slow\n"
    assert slow in ci and ci.index(slow) > ci.index(f"\n{command}\n")
