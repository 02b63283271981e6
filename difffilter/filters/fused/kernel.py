"""Run a traced step as compiled sequence kernels, with autograd.

:class:`SequenceProgram` owns the forward kernel of one traced step and builds reverse kernels
on demand (one per set of outputs that receive a gradient).  :func:`run_sequence` is the
differentiable call: its backward runs the reverse kernel, which recomputes every step from the
stored beliefs instead of keeping the step's intermediates.
"""

from __future__ import annotations

import ctypes
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from .build import compile_library
from .codegen import BackwardSpec, backward_source, forward_source
from .emit import VECTOR_BYTES
from .trace import TracedStep

__all__ = ["SequenceProgram", "lanes", "run_sequence"]

_P = ctypes.c_void_p
_I64 = ctypes.c_int64
_pools: dict[int, ThreadPoolExecutor] = {}
_pool_lock = threading.Lock()


def lanes(dtype: torch.dtype) -> int:
    """Trajectories per SIMD vector (the batch is padded to a multiple of this)."""
    return VECTOR_BYTES // torch.finfo(dtype).bits * 8


def _pool(threads: int) -> ThreadPoolExecutor:
    with _pool_lock:
        pool = _pools.get(threads)
        if pool is None:
            pool = _pools[threads] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="difffilter-kernel")
        return pool


def _pointers(tensors: list[Tensor]) -> ctypes.Array:
    return (_P * max(len(tensors), 1))(*[t.data_ptr() for t in tensors])


class SequenceProgram:
    """Compiled forward kernel of a traced step, plus reverse kernels built on first use."""

    def __init__(self, traced: TracedStep) -> None:
        self.traced = traced
        spec = traced.spec
        self.lanes = lanes(spec.dtype)
        self.group_sizes = spec.group_sizes
        lib = compile_library(forward_source(spec), tag="forward")
        self._forward = lib.forward
        self._forward.argtypes = [_I64, _I64, _I64, _I64, _P, _P, _P, _P]
        self._forward.restype = None
        self._backward: dict[BackwardSpec, Any] = {}
        self._lock = threading.Lock()

    def backward_kernel(self, which: BackwardSpec) -> Any:
        with self._lock:
            fn = self._backward.get(which)
            if fn is None:
                lib = compile_library(backward_source(self.traced.spec, which), tag="backward")
                fn = lib.backward
                fn.argtypes = [_I64, _I64, _I64, _I64, _P, _P, _P, _P, _P, _P, _P, _P]
                fn.restype = None
                self._backward[which] = fn
            return fn

    def _split(self, tiles: int, threads: int, call: Any) -> None:
        chunks = min(max(threads, 1), tiles)
        if chunks <= 1:
            call(0, tiles)
            return
        bounds = [tiles * i // chunks for i in range(chunks + 1)]
        futures = [_pool(chunks).submit(call, bounds[i], bounds[i + 1]) for i in range(chunks)]
        for f in futures:
            f.result()

    def forward(self, state0: Tensor, step_in: Tensor, params: Tensor, threads: int) -> list[Tensor]:
        """Outputs ``[T, K_g, Bp]`` per group for ``state0 [S, Bp]``, ``step_in [T, I, Bp]``, ``params [P]``."""
        steps, bp = step_in.shape[0], state0.shape[1]
        outs = [state0.new_empty((steps, k, bp)) for k in self.group_sizes]
        ptrs = _pointers(outs)
        args = (steps, bp, state0.data_ptr(), step_in.data_ptr(), params.data_ptr(), ctypes.cast(ptrs, _P))
        self._split(bp // self.lanes, threads, lambda a, b: self._forward(a, b, *args))
        return outs

    def backward(
        self, which: BackwardSpec, state0: Tensor, step_in: Tensor, params: Tensor, outs: list[Tensor], grads: list[Tensor], threads: int
    ) -> tuple[Tensor, Tensor | None, Tensor]:
        """Gradients w.r.t. ``state0``, ``step_in`` (if ``which.step_grad``) and ``params``."""
        fn = self.backward_kernel(which)
        steps, bp = step_in.shape[0], state0.shape[1]
        tiles = bp // self.lanes
        g_state0 = torch.empty_like(state0)
        g_step = torch.empty_like(step_in) if which.step_grad else step_in.new_empty(0)
        g_params = params.new_zeros((tiles, params.numel()))
        out_ptrs, grad_ptrs = _pointers(outs), _pointers(grads)
        args = (
            steps, bp, state0.data_ptr(), step_in.data_ptr(), params.data_ptr(), ctypes.cast(out_ptrs, _P), ctypes.cast(grad_ptrs, _P),
            g_state0.data_ptr(), g_step.data_ptr(), g_params.data_ptr(),
        )  # fmt: skip
        self._split(tiles, threads, lambda a, b: fn(a, b, *args))
        return g_state0, (g_step if which.step_grad else None), g_params.sum(0)


class _RunSequence(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, program: SequenceProgram, threads: int, state0: Tensor, step_in: Tensor, params: Tensor) -> tuple[Tensor, ...]:  # type: ignore[override]
        outs = program.forward(state0, step_in, params, threads)
        ctx.program, ctx.threads = program, threads
        ctx.save_for_backward(state0, step_in, params, *outs)
        ctx.set_materialize_grads(False)
        return tuple(outs)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, *grads: Tensor | None) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        state0, step_in, params, *outs = ctx.saved_tensors
        present = tuple(i for i, g in enumerate(grads) if g is not None)
        which = BackwardSpec(present, bool(ctx.needs_input_grad[3]))
        g = [grads[i].contiguous() for i in present]  # type: ignore[union-attr]
        g_state0, g_step, g_params = ctx.program.backward(which, state0, step_in, params, outs, g, ctx.threads)
        return None, None, g_state0 if ctx.needs_input_grad[2] else None, g_step, g_params if ctx.needs_input_grad[4] else None


def run_sequence(program: SequenceProgram, state0: Tensor, step_in: Tensor, params: Tensor, *, threads: int = 1) -> tuple[Tensor, ...]:
    """Differentiable run of ``program``: output groups ``[T, K_g, Bp]`` (see :meth:`SequenceProgram.forward`)."""
    if not torch.is_grad_enabled() or not (state0.requires_grad or step_in.requires_grad or params.requires_grad):
        return tuple(program.forward(state0.contiguous(), step_in.contiguous(), params.contiguous(), threads))
    return _RunSequence.apply(program, threads, state0.contiguous(), step_in.contiguous(), params.contiguous())
