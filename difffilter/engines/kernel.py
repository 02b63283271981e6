"""Run a traced step as compiled sequence kernels, with autograd.

:class:`SequenceProgram` owns the forward kernel of one traced step and builds reverse kernels
on demand (one per set of outputs that receive a gradient).  :func:`run_sequence` is the
differentiable call: its backward runs the reverse kernel, which recomputes every step from the
stored beliefs instead of keeping the step's intermediates.
"""

from __future__ import annotations

import ctypes
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from .build import compile_library
from .codegen import BackwardSpec, backward_source, forward_source
from .emit import VECTOR_BYTES
from .trace import TracedStep

__all__ = ["ReusableBuffers", "SequenceProgram", "lanes", "run_sequence", "unreferenced"]

_P = ctypes.c_void_p
_I64 = ctypes.c_int64
_pools: dict[tuple[int, str], ThreadPoolExecutor] = {}
_pool_lock = threading.Lock()


def lanes(dtype: torch.dtype) -> int:
    """Trajectories per SIMD vector (the batch is padded to a multiple of this)."""
    return VECTOR_BYTES // torch.finfo(dtype).bits * 8


def _pool(threads: int, purpose: str = "run") -> ThreadPoolExecutor:
    with _pool_lock:
        pool = _pools.get((threads, purpose))
        if pool is None:
            pool = _pools[(threads, purpose)] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix=f"difffilter-{purpose}")
        return pool


def unreferenced(buf: Tensor) -> bool:
    """True if no tensor other than ``buf`` itself (no view, no returned result, no NumPy
    array, no autograd graph) shares ``buf``'s memory; False when that cannot be told."""
    try:
        return torch._C._storage_Use_Count(buf.untyped_storage()._cdata) <= 2  # buf + the storage object asked
    except Exception:  # noqa: BLE001 - a private helper; without it, never reuse
        return False


class ReusableBuffers:
    """Output buffers of the previous call, handed out again once nothing references them (no
    result, view, NumPy array or autograd graph), else fresh ones; ``enabled=False`` always
    allocates."""

    def __init__(self, *, enabled: bool = True) -> None:
        self.enabled = enabled
        self.kept: list[Tensor] = []
        self._lock = threading.Lock()

    def get(self, shapes: list[tuple[int, ...]], like: Tensor) -> list[Tensor]:
        with self._lock:
            old, self.kept = self.kept, []
        if (
            self.enabled
            and [tuple(b.shape) for b in old] == shapes
            and all(b.dtype == like.dtype and b.device == like.device and unreferenced(b) for b in old)
        ):
            bufs = old
        else:
            del old
            bufs = [like.new_empty(shape) for shape in shapes]
        if self.enabled:
            with self._lock:
                self.kept = bufs
        return bufs


def _pointers(tensors: list[Tensor]) -> ctypes.Array:
    return (_P * max(len(tensors), 1))(*[t.data_ptr() for t in tensors])


class SequenceProgram:
    """Compiled forward kernel of a traced step, plus reverse kernels built on first use."""

    def __init__(self, traced: TracedStep, *, reuse_buffers: bool = True) -> None:
        self.traced = traced
        spec = traced.spec
        self.lanes = lanes(spec.dtype)
        self.group_sizes = spec.group_sizes
        #: whether the step came from the on-disk program cache (set by :func:`~.cache.load_or_trace`)
        self.from_cache = False
        self._backward: dict[BackwardSpec, Any] = {}  # compiled function or the Future building it
        self._lock = threading.Lock()
        self._source_lock = threading.Lock()
        ll = traced.fields.get("log_likelihood")
        #: the reverse kernel of a training step: gradient of the log-likelihood only
        has_shared = bool(traced.layout.shared)
        self.likely_backward = BackwardSpec((ll[0],), False, has_shared) if ll is not None else None  # the group holding it
        source = forward_source(spec)
        if traced.params and self.likely_backward is not None:
            # parameters that train: build the usual reverse kernel meanwhile, on the other core
            self.prefetch_backward(self.likely_backward)
        lib = compile_library(source, tag="forward")
        self._forward = lib.forward
        self._forward.argtypes = [_I64, _I64, _I64, _I64, _P, _P, _P, _P, _P]
        self._forward.restype = None
        # fresh output memory costs a page fault per 4 KiB, measured at about as much as the UKF kernel
        self._buffers = ReusableBuffers(enabled=reuse_buffers)

    def _build_backward(self, which: BackwardSpec) -> Any:
        with self._source_lock:  # the graph grows while the reverse sweep is written
            source = backward_source(self.traced.spec, which)
        # -O1: the reverse kernels compile ~25 % faster than with -O2 and measured as fast
        fn = compile_library(source, tag="backward", opt="-O1").backward
        fn.argtypes = [_I64, _I64, _I64, _I64, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P]
        fn.restype = None
        return fn

    def prefetch_backward(self, which: BackwardSpec) -> None:
        """Start building the reverse kernel ``which`` in the background (e.g. while the forward
        runs), unless it exists or is being built."""
        with self._lock:
            if which not in self._backward:
                # a pool per process, as wide as the machine: one program's reverse build never
                # queues behind another's (the compiler runs outside the GIL)
                self._backward[which] = _pool(os.cpu_count() or 2, "build").submit(self._build_backward, which)

    def backward_kernel(self, which: BackwardSpec) -> Any:
        self.prefetch_backward(which)
        with self._lock:
            fn = self._backward[which]
        if isinstance(fn, Future):
            fn = fn.result()
            with self._lock:
                self._backward[which] = fn
        return fn

    def _split(self, tiles: int, threads: int, call: Any) -> None:
        chunks = min(max(threads, 1), tiles)
        if chunks <= 1:
            call(0, tiles)
            return
        bounds = [tiles * i // chunks for i in range(chunks + 1)]
        # the calling thread runs the first chunk itself: one hand-over fewer, and no idle wait
        futures = [_pool(chunks - 1).submit(call, bounds[i], bounds[i + 1]) for i in range(1, chunks)]
        try:
            call(bounds[0], bounds[1])
        finally:
            for f in futures:
                f.result()

    def forward(self, state0: Tensor, step_in: Tensor, shared: Tensor, params: Tensor, threads: int) -> list[Tensor]:
        """Outputs ``[T, K_g, Bp]`` per group for ``state0 [S, Bp]``, ``step_in [T, I, Bp]``,
        ``shared [T, J]`` (inputs the same for every trajectory) and ``params [P]``."""
        steps, bp = step_in.shape[0], state0.shape[1]
        outs = self._buffers.get([(steps, k, bp) for k in self.group_sizes], state0)
        ptrs = _pointers(outs)
        args = (steps, bp, state0.data_ptr(), step_in.data_ptr(), shared.data_ptr(), params.data_ptr(), ctypes.cast(ptrs, _P))
        self._split(bp // self.lanes, threads, lambda a, b: self._forward(a, b, *args))
        return outs

    def backward(
        self,
        which: BackwardSpec,
        inputs: tuple[Tensor, Tensor, Tensor, Tensor],
        outs: list[Tensor],
        grads: list[Tensor],
        threads: int,
    ) -> tuple[Tensor, Tensor | None, Tensor | None, Tensor]:
        """Gradients w.r.t. ``inputs = (state0, step_in, shared, params)``: ``step_in`` only if
        ``which.step_grad``, ``shared`` only if ``which.shared_grad``."""
        state0, step_in, shared, params = inputs
        fn = self.backward_kernel(which)
        steps, bp = step_in.shape[0], state0.shape[1]
        tiles = bp // self.lanes
        g_state0 = torch.empty_like(state0)
        g_step = torch.empty_like(step_in) if which.step_grad else step_in.new_empty(0)
        g_shared = shared.new_empty((tiles, *shared.shape)) if which.shared_grad else shared.new_empty(0)
        g_params = params.new_zeros((tiles, params.numel()))
        out_ptrs, grad_ptrs = _pointers(outs), _pointers(grads)
        args = (
            steps, bp, state0.data_ptr(), step_in.data_ptr(), shared.data_ptr(), params.data_ptr(), ctypes.cast(out_ptrs, _P),
            ctypes.cast(grad_ptrs, _P), g_state0.data_ptr(), g_step.data_ptr(), g_shared.data_ptr(), g_params.data_ptr(),
        )  # fmt: skip
        self._split(tiles, threads, lambda a, b: fn(a, b, *args))
        return g_state0, (g_step if which.step_grad else None), (g_shared.sum(0) if which.shared_grad else None), g_params.sum(0)


class _RunSequence(torch.autograd.Function):
    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, program: SequenceProgram, threads: int, state0: Tensor, step_in: Tensor, shared: Tensor, params: Tensor
    ) -> tuple[Tensor, ...]:
        if program.likely_backward is not None:  # compile the usual reverse kernel meanwhile
            program.prefetch_backward(program.likely_backward)
        outs = program.forward(state0, step_in, shared, params, threads)
        ctx.program, ctx.threads = program, threads
        ctx.save_for_backward(state0, step_in, shared, params, *outs)
        ctx.set_materialize_grads(False)
        return tuple(outs)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, *grads: Tensor | None) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        state0, step_in, shared, params, *outs = ctx.saved_tensors
        present = tuple(i for i, g in enumerate(grads) if g is not None)
        which = BackwardSpec(present, bool(ctx.needs_input_grad[3]), bool(ctx.needs_input_grad[4]))
        g = [grads[i].contiguous() for i in present]  # type: ignore[union-attr]
        g_state0, g_step, g_shared, g_params = ctx.program.backward(which, (state0, step_in, shared, params), outs, g, ctx.threads)
        return None, None, g_state0 if ctx.needs_input_grad[2] else None, g_step, g_shared, g_params if ctx.needs_input_grad[5] else None


def run_sequence(
    program: SequenceProgram, state0: Tensor, step_in: Tensor, params: Tensor, *, shared: Tensor | None = None, threads: int = 1
) -> tuple[Tensor, ...]:
    """Differentiable run of ``program``: output groups ``[T, K_g, Bp]`` (see :meth:`SequenceProgram.forward`)."""
    shared = state0.new_zeros(1) if shared is None else shared.contiguous()
    if not torch.is_grad_enabled() or not any(x.requires_grad for x in (state0, step_in, shared, params)):
        return tuple(program.forward(state0.contiguous(), step_in.contiguous(), shared, params.contiguous(), threads))
    return _RunSequence.apply(program, threads, state0.contiguous(), step_in.contiguous(), shared, params.contiguous())
