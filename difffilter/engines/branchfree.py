"""Branch-free stand-ins for the linear-algebra helpers that decide on data values.

Both compiled engines run a filter's own ``predict``/``update``; neither can follow a Python
``if`` on the values of the belief (the generated engine traces with fake tensors, the inductor
engine compiles one straight-line graph per step).  :func:`branch_free` swaps the three helpers
that do branch for equivalents that do not, in every ``difffilter`` module that imported them:

* ``safe_cholesky`` retries a failed factorisation with jitter: the bare ``cholesky_ex`` is
  used instead (the engines' own Cholesky clamps non-positive pivots and reports the number of
  clamps as ``jitter``, so the step still flags itself); equal on positive-definite inputs;
* ``psd_sqrt`` tries a Cholesky factor and falls back to the semi-definite factor: the exact
  semi-definite factor (zero columns for zero pivots) is used, equal on positive semi-definite
  inputs;
* ``any_set`` guards work selected per element with ``torch.where``: taken, which gives the
  reference values.

:func:`step_flag` reads a step's own "untrusted" signal from its :class:`StepInfo`.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import torch
from torch import Tensor

from .. import linalg

__all__ = ["BRANCH_FREE", "branch_free", "step_flag"]

_LOCK = threading.RLock()


def _bare_cholesky(a: Tensor, *, max_jitter: float | None = None) -> linalg.CholeskyResult:
    """``safe_cholesky`` without its retry: the engines clamp non-positive pivots instead."""
    chol, info = torch.linalg.cholesky_ex(a)
    return linalg.CholeskyResult(chol, info.to(a.dtype))


def _semidefinite_sqrt(a: Tensor) -> linalg.CholeskyResult:
    """``psd_sqrt`` without its branches: the exact semi-definite factor (zero columns for zero
    pivots), which is also the Cholesky factor of a positive-definite matrix."""
    factor, _ = linalg._semidefinite_factor(linalg.symmetrize(a))
    return linalg.CholeskyResult(factor, torch.zeros_like(a[..., 0, 0]))


def _always(flags: Tensor) -> bool:
    return True


#: What :func:`branch_free` replaces, by name in :mod:`difffilter.linalg`.
BRANCH_FREE: dict[str, Callable[..., Any]] = {"safe_cholesky": _bare_cholesky, "psd_sqrt": _semidefinite_sqrt, "any_set": _always}


@contextmanager
def branch_free() -> Iterator[None]:
    """Inside the block, every ``difffilter`` module sees the branch-free helpers of
    :data:`BRANCH_FREE` in place of ``linalg.safe_cholesky``, ``psd_sqrt`` and ``any_set``.

    The swap is process-wide (module attributes), so the block holds a re-entrant lock: two
    engines never swap concurrently.  Code in other threads that calls the reference filters
    meanwhile sees the branch-free helpers too (same values on well-posed inputs).
    """
    with _LOCK:
        originals = {name: getattr(linalg, name) for name in BRANCH_FREE}
        patched = []
        for mod_name, mod in list(sys.modules.items()):
            if not mod_name.startswith("difffilter"):
                continue
            for name, original in originals.items():
                if getattr(mod, name, None) is original:
                    setattr(mod, name, BRANCH_FREE[name])
                    patched.append((mod, name, original))
        try:
            yield
        finally:
            for mod, name, original in patched:
                setattr(mod, name, original)


def step_flag(info: Any) -> Tensor:
    """``[B]`` 1.0 where the step flags itself untrusted (``StepInfo.flags()``, or an
    innovation covariance that needed repair, ``StepInfo.jitter``), else 0.0."""
    flag = torch.zeros_like(info.log_likelihood)
    own = info.flags() if hasattr(info, "flags") else getattr(info, "untrusted", None)
    if own is not None:
        flag = flag + own.to(flag.dtype)
    if getattr(info, "jitter", None) is not None:
        flag = flag + (info.jitter != 0).to(flag.dtype)
    return flag
