"""Importing difffilter before torch asks OpenMP's idle workers to sleep (difffilter/_openmp.py)."""

from __future__ import annotations

import os
import subprocess
import sys

_PROBE = "import os, sys; {imports}; print(os.environ.get('OMP_WAIT_POLICY'), 'torch' in sys.modules)"


def _policy(imports: str, **env: str) -> str:
    base = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run(
        [sys.executable, "-c", _PROBE.format(imports=imports)], env={**base, **env}, capture_output=True, text=True, check=True
    )
    return out.stdout.strip()


def test_wait_policy_is_passive_only_when_difffilter_comes_first_and_the_user_set_none():
    assert _policy("import difffilter") == "PASSIVE True"
    assert _policy("import torch; import difffilter") == "None True"  # too late for the OpenMP runtime: left alone
    assert _policy("import difffilter", OMP_WAIT_POLICY="ACTIVE") == "ACTIVE True"
