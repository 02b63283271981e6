"""Which engine a plain filter call runs on: one switch, ``DIFFFILTER_ENGINE``.

``UKF(model)(z, m0, P0)`` (and every :class:`~difffilter.filters.base.RecursiveFilter` call,
so also a ``FilterLearner`` given a plain filter, evaluation, every experiment and the
smoothers' forward filters) asks :func:`run_compiled_if_chosen` first:

* ``auto`` (the default, :data:`DEFAULT_ENGINE`): the compiled engine when a C++ compiler exists
  and the work pays for a kernel build: a large call, ``B * T >= DIFFFILTER_AUTO_MIN_WORK``
  (default ``10_000``), or repeated calls of the same filter object (a training loop over small
  batches or windows) once their ``max(B, 32) * T`` add up to ``DIFFFILTER_AUTO_MIN_TOTAL``
  (default ``100_000``; the call that reaches it runs compiled; below :data:`EAGER_FLAT_BATCH`
  trajectories an eager call costs about the same, so it counts as that many).  A few small
  calls, and so the small tests, stay eager and never build a kernel.  The choice depends only
  on the sequence of calls, so a rerun switches at the same call and repeats its results bit for
  bit;
* ``compiled``: the generated C++ engine (:class:`~.filter.FusedFilter` with ``engine="generated"``)
  for every CPU call it can run;
* ``eager``: the filter's own Python loop, always.

Calls under a ``torch.func`` transform (``vmap``, ``grad``, ``jacrev``...: :mod:`difffilter.func`,
per-sample gradients) and on other devices than the CPU run eagerly, without a warning and without
counting towards the work above: the kernels read plain CPU storage, which transformed tensors do
not have.  :class:`~difffilter.filters.ParallelKalmanFilter` never asks the policy (its scan is
the point; ``last_engine`` stays ``None`` for it).

Where the compiled engine cannot run a filter (no compiler, an operation the generator lacks, an
error inside the engine on input the eager filter accepts), the call runs eagerly and one warning
per filter class and reason (one in all for a missing compiler) says why; set
``DIFFFILTER_ENGINE=eager`` to silence it.  Results are the same either way up to rounding (the
compiled engine agrees with the eager filters to ~1e-13 in float64, and each engine is
deterministic run to run); explicit ``FusedFilter(filt)`` is unaffected.  Switch in code with
:func:`set_engine`.
"""

from __future__ import annotations

import os
import threading
import warnings
import weakref
from collections import OrderedDict

import torch
from torch import Tensor

try:  # torch.func's transform stack (no public query exists); see the fallback below
    from torch._C._functorch import get_interpreter_stack as _transform_stack
except ImportError:  # pragma: no cover - a torch without it: transforms reach the engine, whose error falls back to eager

    def _transform_stack() -> list[object] | None:
        return None


from ..filters.base import Belief, FilterResult, RecursiveFilter
from ..models.base import Controls
from .build import CompileError, compiler_available
from .filter import FusedFilter
from .graph import UnsupportedOp

__all__ = ["DEFAULT_ENGINE", "POLICIES", "chosen_engine", "last_engine", "run_compiled_if_chosen", "set_engine"]

#: what a plain filter call runs on when neither ``DIFFFILTER_ENGINE`` nor :func:`set_engine` says
DEFAULT_ENGINE = "auto"
POLICIES = ("eager", "compiled", "auto")
_CACHE_SIZE = 8  # filters whose compiled runner is kept (each holds its filter alive)

_override: list[str | None] = [None]
_runners: OrderedDict[int, FusedFilter] = OrderedDict()
_work: weakref.WeakKeyDictionary[RecursiveFilter, int] = weakref.WeakKeyDictionary()  # max(B, 32) * T so far
_last: weakref.WeakKeyDictionary[RecursiveFilter, str] = weakref.WeakKeyDictionary()
_failed: weakref.WeakKeyDictionary[RecursiveFilter, str] = weakref.WeakKeyDictionary()
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


def _env_int(name: str, default: int) -> int:
    raw = os.environ.get(name, str(default))
    try:
        return int(raw)
    except ValueError as exc:
        raise ValueError(f"{name} must be an integer (B * T), got {raw!r}") from exc


#: below this batch size an eager step costs about the same whatever the batch (Python and
#: dispatch overhead per step; the benchmark's UKF training step, process CPU per step on the
#: loaded 2-core machine: 2.0 ms at B = 1, 2.6 ms at B = 32, 7.5 ms at B = 256), so a
#: small-batch call counts as this many trajectories towards ``DIFFFILTER_AUTO_MIN_TOTAL``
EAGER_FLAT_BATCH = 32


def _pays_for_a_build(filt: RecursiveFilter, batch: int, steps: int) -> bool:
    """``auto``'s rule: this call is large, or this filter's calls add up to a lot of work."""
    min_work, min_total = _env_int("DIFFFILTER_AUTO_MIN_WORK", 10_000), _env_int("DIFFFILTER_AUTO_MIN_TOTAL", 100_000)
    with _lock:
        total = _work[filt] = _work.get(filt, 0) + max(batch, EAGER_FLAT_BATCH) * steps
    return batch * steps >= min_work or total >= min_total


def _announce(filt: RecursiveFilter, reason: str) -> None:
    # a missing compiler concerns every filter: said once, not once per filter class
    key = ("" if reason == compiler_available() else type(filt).__name__, reason)
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
    if getattr(_local, "inside", False):  # the compiled engine's own (or its fallback's) call of filt
        return None
    out, engine = _compiled_result(filt, measurements, initial_mean, initial_cov, mask, controls, belief)
    with _lock:
        _last[filt] = engine
    return out


def last_engine(filt: RecursiveFilter) -> str | None:
    """The engine that ran ``filt``'s last plain call: ``"generated"`` (compiled), ``"eager"``, or
    ``None`` before its first call."""
    with _lock:
        return _last.get(filt)


def _compiled_result(
    filt: RecursiveFilter,
    measurements: Tensor,
    initial_mean: Tensor | None,
    initial_cov: Tensor | None,
    mask: Tensor | None,
    controls: Controls,
    belief: Belief | None,
) -> tuple[FilterResult | None, str]:
    policy = chosen_engine()
    if policy == "eager" or not isinstance(measurements, Tensor):
        return None, "eager"
    if measurements.device.type != "cpu" or measurements.dtype not in (torch.float32, torch.float64) or measurements.dim() != 3:
        return None, "eager"
    if torch.compiler.is_compiling() or _transform_stack():
        # a transform's wrapped tensors have no storage for the kernels to read: eager, and the
        # filter is not marked as one the engine failed on (its plain calls still compile)
        return None, "eager"
    if policy == "auto" and not _pays_for_a_build(filt, measurements.shape[0], measurements.shape[1]):
        return None, "eager"
    reason = compiler_available()
    if reason is None:
        with _lock:
            reason = _failed.get(filt)
    if reason is not None:
        _announce(filt, reason)
        return None, "eager"
    fused = _runner(filt)
    _local.inside = True
    try:
        # FusedFilter's own run, without its forward's thread scope and isolation of non-finite
        # trajectories: the filter's forward, which asked this hook, already provides both
        return fused._run(measurements, initial_mean, initial_cov, mask, controls, belief=belief), "generated"
    except (UnsupportedOp, CompileError) as exc:
        _give_up(filt, str(exc)[:300])
        return None, "eager"
    except Exception as exc:  # noqa: BLE001 - bad input, or a defect of the engine: the eager filter tells which
        # bad input raises here again, as the eager filter raises it; input the eager filter accepts
        # means the engine failed on it: the eager result, flagged
        result = filt._run(measurements, initial_mean, initial_cov, mask, controls, belief=belief)
        _give_up(filt, f"{type(exc).__name__}: {exc}"[:300])
        return result, "eager"
    finally:
        _local.inside = False


def _give_up(filt: RecursiveFilter, reason: str) -> None:
    with _lock:
        _failed[filt] = reason
    _announce(filt, reason)
