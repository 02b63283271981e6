"""Intra-op threads while a filter runs: one by default, restored afterwards.

A filter's time loop is thousands of small tensor operations on ``[B, n, n]`` blocks.  With
torch's default thread count (one per core) several of them (batched Cholesky factors through
LAPACK, matrix products through BLAS) open a parallel region per call, and every region waits
for a second thread to be scheduled: measured on a 2-core machine, a 5-state UKF training step
(B = 64, T = 200) cost 0.7 s of CPU with one thread against 1.9 s with two on an idle machine,
and 12 s (27 s wall, 25x) with two when other processes kept the cores busy.

So every filter and smoother call (and :class:`~difffilter.filters.FusedFilter`) runs its forward
pass, and the backward pass through it, with ``torch.set_num_threads(get_filter_threads())``
(default 1), and restores the caller's setting afterwards: code outside the filter (a neural
network feeding it, the optimiser) keeps the caller's thread count.  The backward pass is scoped
by two autograd nodes: one on the outputs (first to run in the backward pass: sets the count),
one joined to the initial mean with an exact zero (runs once the gradient reached the first
step: restores it).  A backward pass that fails midway (an exception in a hook) gives it back at
the next filter call on the same Python thread.

Change it with :func:`set_filter_threads` (``None``: leave torch's setting alone, e.g. for large
batches on many cores where intra-op parallelism pays) or the environment variable
``DIFFFILTER_THREADS`` (an integer, or ``torch`` for ``None``).
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import os
import threading
import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

import torch
from torch import Tensor

__all__ = ["caller_threads", "filter_threads", "get_filter_threads", "scoped_forward", "set_filter_threads"]

_F = TypeVar("_F", bound=Callable[..., Any])


def _from_env() -> int | None:
    raw = os.environ.get("DIFFFILTER_THREADS", "1").strip().lower()
    if raw in ("torch", "none", ""):
        return None
    try:
        value = int(raw)
    except ValueError as exc:
        raise ValueError(f"DIFFFILTER_THREADS must be a positive integer or 'torch', got {raw!r}") from exc
    if value < 1:
        raise ValueError(f"DIFFFILTER_THREADS must be a positive integer or 'torch', got {raw!r}")
    return value


_setting: list[int | None] = [_from_env()]
_lock = threading.Lock()
_held = [0]  # scopes (forward calls and backward passes) now holding the setting
_saved: list[int | None] = [None]  # the caller's count while a scope holds it
_local = threading.local()
_active: weakref.WeakSet[_Hold] = weakref.WeakSet()  # backward passes that took the setting


def set_filter_threads(threads: int | None) -> None:
    """Intra-op threads for filter calls (default 1; ``None``: torch's own setting, untouched)."""
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise ValueError(f"threads must be a positive int or None, got {threads!r}")
    _setting[0] = threads


def get_filter_threads() -> int | None:
    """The setting of :func:`set_filter_threads`."""
    return _setting[0]


def caller_threads() -> int:
    """torch's thread count as the caller set it (inside a filter call: the count before it)."""
    with _lock:
        saved = _saved[0] if _held[0] else None
    return saved if saved is not None else torch.get_num_threads()


def _acquire(threads: int) -> None:
    with _lock:
        if _held[0] == 0:
            _saved[0] = torch.get_num_threads()
            if _saved[0] != threads:
                torch.set_num_threads(threads)
        _held[0] += 1


def _release() -> None:
    with _lock:
        _held[0] -= 1
        if _held[0] == 0:
            if _saved[0] is not None and torch.get_num_threads() != _saved[0]:
                torch.set_num_threads(_saved[0])
            _saved[0] = None


@contextmanager
def filter_threads(threads: int | None = None) -> Iterator[None]:
    """Run the block with ``threads`` intra-op threads (default :func:`get_filter_threads`), then
    restore the caller's count; nested blocks keep the outermost setting."""
    threads = get_filter_threads() if threads is None else threads
    if threads is None:
        yield
        return
    _acquire(threads)
    try:
        yield
    finally:
        _release()


class _Hold:
    """One backward pass's hold on the setting; released at the latest when the graph is freed or
    the next filter call starts on the thread that ran the backward pass."""

    def __init__(self, threads: int) -> None:
        self.threads = threads
        self.held = False
        self.thread = 0

    def acquire(self) -> None:
        if not self.held:
            self.held = True
            self.thread = threading.get_ident()
            _active.add(self)
            _acquire(self.threads)

    def release(self) -> None:
        if self.held:
            self.held = False
            _release()

    def __del__(self) -> None:
        self.release()


class _Enter(torch.autograd.Function):
    """Identity on the outputs; its backward (the first node of the pass) takes the setting."""

    generate_vmap_rule = True  # usable under torch.func transforms

    @staticmethod
    def forward(hold: _Hold, *xs: Tensor) -> tuple[Tensor, ...]:
        return tuple(x.view_as(x) for x in xs)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: Any) -> None:
        ctx.hold = inputs[0]
        ctx.set_materialize_grads(False)

    @staticmethod
    def backward(ctx: Any, *grads: Tensor | None) -> tuple[Tensor | None, ...]:
        ctx.hold.acquire()
        return (None, *grads)


class _Exit(torch.autograd.Function):
    """A zero joined to the initial belief; its backward (after the first step's) gives the setting back."""

    generate_vmap_rule = True

    @staticmethod
    def forward(hold: _Hold, link: Tensor, like: Tensor) -> Tensor:
        return like.new_zeros(())

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: Any) -> None:
        ctx.hold = inputs[0]

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        ctx.hold.release()
        # zeros, not ``grad * 0``: a non-finite gradient must not reach what the link came from
        return None, torch.zeros((), dtype=grad.dtype, device=grad.device), None


# Function.apply binds every call's arguments to ``forward``'s signature when ``setup_context`` is
# defined; a signature stored on the function is read instead of rebuilt (~60 us per filter call)
_Enter.forward.__signature__ = inspect.signature(_Enter.forward)  # type: ignore[attr-defined]
_Exit.forward.__signature__ = inspect.signature(_Exit.forward)  # type: ignore[attr-defined]


def _tensors(value: Any) -> Iterator[Tensor]:
    if isinstance(value, Tensor):
        yield value
    elif isinstance(value, dict):
        for v in value.values():
            yield from _tensors(v)


def _anchor(value: Any, zero: Tensor) -> Any:
    """``value`` (a tensor or a dict of them) plus an exact zero in every floating tensor."""
    if isinstance(value, Tensor):
        return value + zero.to(value.dtype) if value.is_floating_point() else value
    if isinstance(value, dict):
        return {k: _anchor(v, zero) for k, v in value.items()}
    return value


def _replace_outputs(result: Any, new: dict[int, Tensor]) -> None:
    """Put the tensors ``new`` (by ``id`` of the tensor they replace) back into ``result``'s fields."""
    if dataclasses.is_dataclass(result):
        for f in dataclasses.fields(result):
            value = getattr(result, f.name)
            if isinstance(value, Tensor):
                setattr(result, f.name, new.get(id(value), value))
            elif isinstance(value, dict):
                for k, v in list(value.items()):
                    if isinstance(v, Tensor):
                        value[k] = new.get(id(v), v)
            else:
                _replace_outputs(value, new)


def _outputs(result: Any) -> list[Tensor]:
    out: list[Tensor] = []
    if dataclasses.is_dataclass(result):
        for f in dataclasses.fields(result):
            value = getattr(result, f.name)
            if isinstance(value, (Tensor, dict)):
                out += [t for t in _tensors(value) if t.requires_grad]
            else:
                out += _outputs(value)
    return out


def scoped_forward(forward: _F) -> _F:
    """Decorate a filter's ``forward(measurements, initial_mean, initial_cov, mask, controls, *,
    belief)`` so that it, and the backward pass through its result, run under
    :func:`filter_threads` (see the module docstring); calls nested in one (a smoother's filter)
    run under the outer one."""

    @functools.wraps(forward)
    def wrapper(self: Any, measurements: Tensor, initial_mean: Any = None, initial_cov: Any = None, *args: Any, **kwargs: Any) -> Any:
        threads = get_filter_threads()
        if threads is None or getattr(_local, "inside", False):
            return forward(self, measurements, initial_mean, initial_cov, *args, **kwargs)
        # a backward pass on this thread that never reached its end (it raised) is over by now
        for stale in [h for h in list(_active) if h.held and h.thread == threading.get_ident()]:
            stale.release()
        hold = None
        if torch.is_grad_enabled():
            belief = kwargs.get("belief")
            links = [p for p in self.parameters() if p.requires_grad and p.numel()]
            links += [t for t in _tensors(measurements) if t.requires_grad and t.numel()]
            for v in (initial_mean, initial_cov, belief, *args, *kwargs.values()):
                links += [t for t in _tensors(v) if t.requires_grad and t.numel() and t.is_floating_point()]
            start = belief if belief is not None else initial_mean
            like = next(_tensors(start), None)
            if links and like is not None and like.is_floating_point():
                hold = _Hold(threads)
                link = torch.stack([t.reshape(-1)[0].to(like.dtype) for t in links]).sum()
                zero = _Exit.apply(hold, link, like)
                # the mean only: a covariance that needs no gradient stays one (a batch sharing
                # one covariance keeps its shared-covariance path in the compiled engine)
                if belief is not None:
                    if isinstance(belief, dict) and "mean" in belief:
                        kwargs["belief"] = {**belief, "mean": _anchor(belief["mean"], zero)}
                    else:
                        kwargs["belief"] = _anchor(belief, zero)
                else:
                    initial_mean = _anchor(initial_mean, zero)
        _local.inside = True
        try:
            with filter_threads(threads):
                result = forward(self, measurements, initial_mean, initial_cov, *args, **kwargs)
        finally:
            _local.inside = False
        if hold is not None:
            outs = _outputs(result)
            if outs:
                # one tensor may sit in several fields (a final belief that is the last mean)
                unique = list({id(t): t for t in outs}.values())
                new = _Enter.apply(hold, *unique)
                _replace_outputs(result, {id(t): n for t, n in zip(unique, new, strict=True)})
        return result

    return wrapper  # type: ignore[return-value]
