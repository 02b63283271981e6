"""The ``torch.compile`` engine: the filter's own step, with element-wise small linear algebra.

Each step runs exactly the body of :meth:`RecursiveFilter.forward`'s loop (``predict``,
``update``, ``finalize_belief``, ``record``) of the wrapped filter or mixer, batch-first, inside
:class:`~.step.SmallLinalg` (element-wise Cholesky, triangular solves, QR and small products)
and :func:`~.branchfree.branch_free` (no Python decision on data values).  The step is compiled
by ``torch.compile`` (inductor: any device it supports, CUDA included) once per shape and called
from a Python time loop; ``compile=False`` runs the same step eagerly.

The first step of every call runs uncompiled: it fills lazily built caches (sigma-point
weights) and gives the belief layout of the steady steps (a filter may add entries after its
first step), so the compiled step is specialised once, on batch size, dtype, grad mode, belief
layout and the presence of masks and controls.  Without autograd the per-step means and
covariances go straight into preallocated buffers, optionally reused across calls.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor
from torch.nn.utils import parametrize

from ..filters.base import Belief, FilterResult, RecursiveFilter, slice_controls
from ..filters.update import untrusted_steps
from ..models.base import Controls
from .branchfree import branch_free, step_flag
from .kernel import ReusableBuffers
from .step import SmallLinalg

__all__ = ["InductorEngine"]

_MIN_RECOMPILE_LIMIT = 64
_FIELDS = ("mean", "cov", "prior_mean", "prior_cov")


def _contiguous(belief: Belief) -> Belief:
    # compiled outputs may come back in another memory layout: fixed strides keep the compiled
    # step from being specialised again
    return {k: v.contiguous() for k, v in belief.items()}


class InductorEngine:
    """Runs ``filt``'s own step with element-wise linear algebra, compiled or eager."""

    def __init__(self, filt: RecursiveFilter, *, compile: bool, compile_options: dict[str, Any], reuse_buffers: bool) -> None:  # noqa: A002
        self.filter = filt
        self.use_compile = compile
        self.compile_options = compile_options
        self.buffers = ReusableBuffers(enabled=reuse_buffers)  # reused across no-grad calls
        self._compiled: Callable[..., Any] | None = None
        self.compile_failed = False

    def step(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Any, ...]:
        """One step of the reference loop: ``(posterior belief, prior mean, prior cov,
        log-likelihood, NIS, observed count, step flag, clamped pivots of S, records)``."""
        filt = self.filter
        with SmallLinalg():
            prior = filt.predict(belief, u)
            post, info = filt.update(prior, z, mask, u)
            post = filt.finalize_belief(post)
            rec = filt.record(post)
            clamps = torch.zeros_like(info.log_likelihood) if info.jitter is None else info.jitter.to(info.log_likelihood.dtype)
            return post, prior["mean"], prior["cov"], info.log_likelihood, info.nis, info.num_observed, step_flag(info), clamps, rec

    def _step_fn(self) -> Callable[..., Any]:
        if not self.use_compile or self.compile_failed:
            return self.step
        if self._compiled is None:
            # Graphs are specialised on grad mode, requires_grad of the carried belief, masks and
            # batch size, and every engine shares the step's code object: allow enough variants
            # that a few filters never fall back to eager execution.
            cfg = torch._dynamo.config
            name = "recompile_limit" if hasattr(cfg, "recompile_limit") else "cache_size_limit"
            if getattr(cfg, name) < _MIN_RECOMPILE_LIMIT:
                setattr(cfg, name, _MIN_RECOMPILE_LIMIT)
            self._compiled = torch.compile(self.step, dynamic=False, **self.compile_options)
        return self._compiled

    def _run(self, step: Callable[..., Any], args: tuple[Any, ...]) -> tuple[Any, ...]:
        """``step(*args)``; a compiler failure switches this engine to the eager step (with a warning)."""
        if step is self.step:
            return step(*args)
        try:
            return step(*args)
        except Exception as exc:  # noqa: BLE001 - any compiler failure falls back to the eager step
            reason = f"{type(exc).__name__}: {str(exc)[:500]}"
            warnings.warn(f"FusedFilter: torch.compile failed ({reason}); running the step eagerly", stacklevel=4)
            self.compile_failed = True
            return self.step(*args)

    def __call__(self, z: Tensor, mask: Tensor | None, belief: Belief, controls: Controls) -> FilterResult:
        """``z [B, T, m]`` (validated, masked values zeroed), ``mask [B, T, m]`` or None, a full belief
        without a diffuse part."""
        bsz, steps, _ = z.shape
        n = self.filter.state_dim
        # Without autograd, the per-step means and covariances go straight into preallocated
        # buffers.  With autograd, in-place writes into one buffer would chain T copy nodes, so
        # the lists are kept and stacked.
        direct = not torch.is_grad_enabled()
        bufs = self.buffers.get([(bsz, steps, *s) for s in ((n,), (n, n), (n,), (n, n))], z) if direct else None
        cols: list[list[Any]] = [[] for _ in range(10)]  # 4 belief fields, 5 statistics, records
        belief = _contiguous(belief)
        with parametrize.cached(), branch_free():
            for t in range(steps):
                step = self.step if t == 0 else self._step_fn()
                args = (belief, z[:, t], None if mask is None else mask[:, t], slice_controls(controls, t))
                res = self._run(step, args)
                belief = _contiguous(res[0])
                vals = (belief["mean"], belief["cov"], res[1], res[2])
                if bufs is not None:
                    for buf, val in zip(bufs, vals, strict=True):
                        buf[:, t] = val
                else:
                    for col, val in zip(cols[:4], vals, strict=True):
                        col.append(val)
                for col, val in zip(cols[4:], res[3:], strict=True):
                    col.append(val)
        if bufs is not None:  # views: while a result holds one, the buffer counts as referenced
            mean, cov, prior_mean, prior_cov = (b[...] for b in bufs)
        else:
            mean, cov, prior_mean, prior_cov = (torch.stack(c, 1) for c in cols[:4])
        ll, nis, nobs, flags, clamps = (torch.stack(c, 1) for c in cols[4:9])
        extras = {k: torch.stack([r[k] for r in cols[9]], 1) for k in cols[9][0]}
        # the reference loop's flags: the run-wide check and the steps' own flags
        extras["untrusted"] = untrusted_steps(mean.detach(), cov.detach(), prior_cov.detach(), ll.detach()) | (flags != 0)
        extras["cholesky_clamps"] = clamps
        return FilterResult(
            mean=mean,
            cov=cov,
            prior_mean=prior_mean,
            prior_cov=prior_cov,
            log_likelihood=ll,
            nis=nis,
            num_observed=nobs,
            final_belief=belief,
            extras=extras,
        )
