"""Which engine a plain filter call runs on: one switch, ``DIFFFILTER_ENGINE``.

``UKF(model)(z, m0, P0)`` (and every :class:`~difffilter.filters.base.RecursiveFilter` call,
so also a ``FilterLearner`` given a plain filter and the smoothers' forward filters) asks
:func:`run_compiled_if_chosen` first:

* ``eager`` (the default, :data:`DEFAULT_ENGINE`): the filter's own Python loop, always;
* ``compiled``: the generated C++ engine (:class:`~.filter.FusedFilter` with ``engine="generated"``)
  for every CPU call it can run;
* ``auto``: the compiled engine when a C++ compiler exists and the call is large enough to pay
  for a kernel build, ``B * T >= DIFFFILTER_AUTO_MIN_WORK`` (default ``10_000``); small calls
  (and so every small test) stay eager and never build a kernel.

Where the compiled engine cannot run a filter (no compiler, an operation the generator lacks),
the call runs eagerly and one warning per filter class and reason says why (set
``DIFFFILTER_ENGINE=eager`` to silence it).  Results are the same either way (the compiled
engine agrees with the eager filters to ~1e-13 in float64); explicit ``FusedFilter(filt)`` is
unaffected.  Switch in code with :func:`set_engine`; flipping the default is the one line
:data:`DEFAULT_ENGINE`.
"""

from __future__ import annotations

import os
import threading
import warnings
from collections import OrderedDict

import torch
from torch import Tensor

from ..filters.base import Belief, FilterResult, RecursiveFilter
from ..models.base import Controls
from .build import CompileError, compiler_available
from .filter import FusedFilter
from .graph import UnsupportedOp

__all__ = ["DEFAULT_ENGINE", "POLICIES", "chosen_engine", "run_compiled_if_chosen", "set_engine"]

#: what a plain filter call runs on when neither ``DIFFFILTER_ENGINE`` nor :func:`set_engine` says
DEFAULT_ENGINE = "eager"
POLICIES = ("eager", "compiled", "auto")
_CACHE_SIZE = 8  # filters whose compiled runner is kept (each holds its filter alive)

_override: list[str | None] = [None]
_runners: OrderedDict[int, FusedFilter] = OrderedDict()
_failed: dict[int, str] = {}
_warned: set[tuple[str, str]] = set()
_lock = threading.Lock()
_local = threading.local()


def set_engine(policy: str | None) -> None:
    """``"eager"``, ``"compiled"`` or ``"auto"`` for plain filter calls (``None``: back to
    ``DIFFFILTER_ENGINE`` / :data:`DEFAULT_ENGINE`)."""
    if policy is not None and policy not in POLICIES:
        raise ValueError(f"engine must be one of {list(POLICIES)} or None, got {policy!r}")
    _override[0] = policy


def chosen_engine() -> str:
    """The policy in force: :func:`set_engine`'s, else ``DIFFFILTER_ENGINE``, else :data:`DEFAULT_ENGINE`."""
    if _override[0] is not None:
        return _override[0]
    raw = os.environ.get("DIFFFILTER_ENGINE", DEFAULT_ENGINE).strip().lower() or DEFAULT_ENGINE
    if raw not in POLICIES:
        raise ValueError(f"DIFFFILTER_ENGINE must be one of {list(POLICIES)}, got {raw!r}")
    return raw


def _min_work() -> int:
    raw = os.environ.get("DIFFFILTER_AUTO_MIN_WORK", "10000")
    try:
        return int(raw)
    except ValueError as exc:
        raise ValueError(f"DIFFFILTER_AUTO_MIN_WORK must be an integer (B * T), got {raw!r}") from exc


def _announce(filt: RecursiveFilter, reason: str) -> None:
    key = (type(filt).__name__, reason)
    with _lock:
        if key in _warned:
            return
        _warned.add(key)
    warnings.warn(
        f"difffilter: the compiled engine cannot run {type(filt).__name__} ({reason}); running it eagerly "
        "(DIFFFILTER_ENGINE=eager turns the compiled engine off)",
        stacklevel=4,
    )


def _runner(filt: RecursiveFilter) -> FusedFilter:
    with _lock:
        fused = _runners.get(id(filt))
        if fused is not None and fused.filter is filt:
            _runners.move_to_end(id(filt))
            return fused
        fused = _runners[id(filt)] = FusedFilter(filt, engine="generated")
        while len(_runners) > _CACHE_SIZE:
            _runners.popitem(last=False)
        return fused


def run_compiled_if_chosen(
    filt: RecursiveFilter,
    measurements: Tensor,
    initial_mean: Tensor | None,
    initial_cov: Tensor | None,
    mask: Tensor | None,
    controls: Controls,
    belief: Belief | None,
) -> FilterResult | None:
    """The call's result from the compiled engine, or ``None`` to run ``filt`` eagerly (see the
    module docstring)."""
    policy = chosen_engine()
    if policy == "eager" or getattr(_local, "inside", False) or not isinstance(measurements, Tensor):
        return None
    if measurements.device.type != "cpu" or measurements.dtype not in (torch.float32, torch.float64) or measurements.dim() != 3:
        return None
    if torch.compiler.is_compiling():
        return None
    if policy == "auto" and measurements.shape[0] * measurements.shape[1] < _min_work():
        return None
    reason = compiler_available()
    if reason is None:
        with _lock:
            reason = _failed.get(id(filt))
    if reason is not None:
        _announce(filt, reason)
        return None
    fused = _runner(filt)
    _local.inside = True
    try:
        return fused(measurements, initial_mean, initial_cov, mask, controls, belief=belief)
    except (UnsupportedOp, CompileError) as exc:
        with _lock:
            _failed[id(filt)] = str(exc)[:300]
        _announce(filt, str(exc)[:300])
        return None
    finally:
        _local.inside = False
