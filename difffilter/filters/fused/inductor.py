"""The ``torch.compile`` engine: the batch-last step of :mod:`.step`, compiled once per shape and
called from a Python time loop (any device inductor supports, CUDA included), or run eagerly.

Compilation is specialised on batch size, dtype, grad mode and the presence of masks and
controls.  Without autograd the per-step outputs go straight into preallocated batch-last
buffers, optionally reused across calls.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from ...models.base import Controls, DynamicsModel, MeasurementModel
from ..base import Belief, FilterResult, RecursiveFilter, slice_controls
from ..update import untrusted_steps
from .kernel import ReusableBuffers
from .step import SmallMatmulAsSum, batch_last_step, to_batch_last, transpose01

__all__ = ["InductorEngine"]

_MIN_RECOMPILE_LIMIT = 64


def _overridden(obj: nn.Module, base: type, name: str) -> bool:
    return getattr(type(obj), name) is not getattr(base, name)


class InductorEngine:
    """Runs ``filt`` (of step kind ``kind``) with the batch-last step, compiled or eager."""

    def __init__(self, filt: RecursiveFilter, kind: str, *, compile: bool, compile_options: dict[str, Any], reuse_buffers: bool) -> None:  # noqa: A002
        self.filter = filt
        self.kind = kind
        self.use_compile = compile
        self.compile_options = compile_options
        self.buffers = ReusableBuffers(enabled=reuse_buffers)  # reused across no-grad calls
        dyn, meas = filt.model.dynamics, filt.model.measurement
        self._static_q = not _overridden(dyn, DynamicsModel, "process_noise")
        self._static_r = not _overridden(meas, MeasurementModel, "measurement_noise")
        self._compiled: Callable[..., Any] | None = None
        self.compile_failed = False

    def step(self, *args: Any) -> tuple[Tensor, ...]:
        with SmallMatmulAsSum():
            return batch_last_step(self.filter, self.kind, *args)

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

    def __call__(self, z: Tensor, mask: Tensor | None, belief: Belief, controls: Controls) -> FilterResult:
        """``z [B, T, m]`` (validated), ``mask [B, T, m]`` or None, a ``{"mean", "cov"}`` belief."""
        filt = self.filter
        bsz, steps, _ = z.shape
        n = filt.state_dim
        mean = transpose01(belief["mean"]).contiguous()
        cov = belief["cov"].permute(1, 2, 0).contiguous()
        observed_all = None if mask is None else mask.to(z.dtype).permute(1, 2, 0)  # [T, m, B]
        outs: list[tuple[Tensor, ...]] = []
        # Without autograd, the per-step means and covariances go straight into preallocated
        # batch-last buffers and each step's memory is reused by the next one.  With autograd,
        # in-place writes into one buffer would chain T copy nodes, so the list is kept.
        direct = not torch.is_grad_enabled()
        if direct:
            bufs = self.buffers.get([(steps, *shape) for shape in ((n, bsz), (n, n, bsz), (n, bsz), (n, n, bsz))], z)
        with parametrize.cached():
            dyn, meas = filt.model.dynamics, filt.model.measurement
            q_static = to_batch_last(dyn.Q, 2) if self._static_q else None
            r_static = to_batch_last(meas.R, 2) if self._static_r else None
            if self.kind in ("ukf", "sukf"):  # fill the weight cache now: a first fill inside the graph forces a recompile
                filt.sigma_points.weights(n, z.dtype, z.device)
            step = self._step_fn()
            compiled = self.use_compile and not self.compile_failed
            for t in range(steps):
                observed = None if observed_all is None else observed_all[t]
                args = (mean, cov, z[:, t], observed, slice_controls(controls, t), q_static, r_static)
                if compiled and t == 0:
                    try:
                        res = step(*args)
                    except Exception as exc:  # noqa: BLE001 - any compiler failure falls back to the eager step
                        warnings.warn(
                            f"FusedFilter: torch.compile failed ({type(exc).__name__}: {exc}); running the step eagerly", stacklevel=3
                        )
                        self.compile_failed = True
                        step = self.step
                        res = step(*args)
                else:
                    res = step(*args)
                # compiled outputs may come back in another memory layout: keep the inputs'
                # strides fixed so that the compiled step is not specialised again
                mean, cov = res[0].contiguous(), res[1].contiguous()
                if direct:
                    for buf, val in zip(bufs, res[:4], strict=True):
                        buf[t] = val
                    outs.append(res[4:])
                else:
                    outs.append(res)
        if direct:
            cols = [()] * 4 + list(zip(*outs, strict=False))
            post_mean, post_cov, prior_mean, prior_cov = (b.movedim(-1, 0) for b in bufs)
        else:
            cols = list(zip(*outs, strict=False))
            post_mean = torch.stack(cols[0]).permute(2, 0, 1)
            post_cov = torch.stack(cols[1]).permute(3, 0, 1, 2)
            prior_mean = torch.stack(cols[2]).permute(2, 0, 1)
            prior_cov = torch.stack(cols[3]).permute(3, 0, 1, 2)
        ll, nis, nobs, clamps, s_clamps = (torch.stack(c, 1) for c in cols[4:])
        # the reference loop's flags: the run-wide check and an innovation covariance that needed repair
        untrusted = untrusted_steps(post_mean.detach(), post_cov.detach(), prior_cov.detach(), ll.detach()) | (s_clamps != 0)
        return FilterResult(
            mean=post_mean,
            cov=post_cov,
            prior_mean=prior_mean,
            prior_cov=prior_cov,
            log_likelihood=ll,
            nis=nis,
            num_observed=nobs,
            final_belief={"mean": post_mean[:, -1], "cov": post_cov[:, -1]},
            extras={"cholesky_clamps": clamps, "untrusted": untrusted},
        )
