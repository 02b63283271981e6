"""The generated-kernel engine: a filter's own step, traced once, run as compiled C++ over the sequence.

:class:`GeneratedEngine` packs a batch into the kernel layout (batch last, padded to whole SIMD
vectors), runs :func:`~.kernel.run_sequence` and unpacks the output groups into a
:class:`~difffilter.filters.FilterResult`.  Programs are cached per belief layout, dtype,
mask/control structure and :func:`~.trace.fingerprint` of the filter, and on disk between
processes (:mod:`.cache`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from ..filters.base import Belief, FilterResult, RecursiveFilter
from ..filters.update import untrusted_steps
from ..models.base import Controls
from ..threads import caller_threads
from .build import CompileError
from .cache import load_or_trace
from .graph import UnsupportedOp
from .kernel import SequenceProgram, lanes, run_sequence
from .shared import SharedGainMean, SharedGainRecorder, shared_covariance_run, shares_covariance
from .trace import StepLayout, fingerprint

__all__ = ["GeneratedEngine"]


def _pad_lanes(x: Tensor, padded: int) -> Tensor:
    """``[..., B] -> [..., padded]``, the extra trajectories copies of the first (a valid belief)."""
    extra = padded - x.shape[-1]
    if extra == 0:
        return x
    return torch.cat([x, x[..., :1].expand(*x.shape[:-1], extra)], -1)


def _controls_layout(
    controls: Controls, dtype: torch.dtype
) -> tuple[tuple[tuple[str, tuple[int, ...], torch.dtype], ...] | None, list[Tensor]]:
    if controls is None:
        return None, []
    items = [("", controls)] if isinstance(controls, Tensor) else sorted(dict(controls).items())
    layout = tuple((k, tuple(v.shape[2:]), v.dtype) for k, v in items)
    return layout, [v for _, v in items]


class GeneratedEngine:
    """Runs ``filt`` through generated kernels (CPU, float32/float64)."""

    def __init__(
        self, filt: RecursiveFilter, *, threads: int | None = None, reuse_buffers: bool = True, shared_covariance: bool = True
    ) -> None:
        self.filter = filt
        self.shared_covariance = shared_covariance
        #: how the last call ran: "per trajectory" or "shared covariance"
        self.last_path: str | None = None
        self._mean_engine: GeneratedEngine | None = None
        self._cov_engine: GeneratedEngine | None = None
        self.threads = threads
        self.reuse_buffers = reuse_buffers
        self._programs: dict[Any, SequenceProgram] = {}

    def program(self, layout: StepLayout, belief: Belief) -> SequenceProgram:
        """The compiled program for ``layout`` (traced and compiled on first use)."""
        key = (layout, fingerprint(self.filter))
        prog = self._programs.get(key)
        if prog is None:
            example = {k: v[:1].detach() for k, v in belief.items()}
            prog = load_or_trace(self.filter, layout, example, reuse_buffers=self.reuse_buffers)
            self._programs[key] = prog
        return prog

    def __call__(self, z: Tensor, mask: Tensor | None, belief: Belief, controls: Controls) -> FilterResult:
        """``z [B, T, m]`` (validated, masked values zeroed), ``mask [B, T, m]`` or None, a full belief.

        A Kalman filter whose covariances are the same for every trajectory runs its covariance
        recursion once (:mod:`.shared`); ``shared_covariance=False`` turns that off."""
        if self.shared_covariance and shares_covariance(self.filter, mask, belief, controls):
            if self._mean_engine is None or self._cov_engine is None:
                opts = {"threads": self.threads, "reuse_buffers": self.reuse_buffers, "shared_covariance": False}
                self._cov_engine = GeneratedEngine(SharedGainRecorder(self.filter), **opts)  # type: ignore[arg-type]
                self._mean_engine = GeneratedEngine(SharedGainMean(self.filter.model), **opts)
            cov_engine, mean_engine = self._cov_engine, self._mean_engine
            try:
                out = shared_covariance_run(
                    self.filter, z, mask, belief, lambda *a: cov_engine._fields(*a)[0], lambda *a: mean_engine._fields(*a)[0]
                )  # type: ignore[arg-type]
            except (UnsupportedOp, CompileError) as exc:  # the per-trajectory kernel below may still run it
                warnings.warn(f"difffilter: the shared-covariance kernels cannot run ({exc}); running per trajectory", stacklevel=2)
                self.shared_covariance = False
            else:
                self.last_path = "shared covariance"
                return out
        self.last_path = "per trajectory"
        field, prog = self._fields(z, mask, belief, controls)
        mean, cov, prior_cov, loglik = field("mean"), field("cov"), field("prior_cov"), field("log_likelihood")
        extras = {k: field(k) for k in prog.traced.record_keys}
        # the run-wide check of the reference loop, and the steps' own flags
        extras["untrusted"] = untrusted_steps(mean.detach(), cov.detach(), prior_cov.detach(), loglik.detach()) | (
            field("step_untrusted") != 0
        )
        return FilterResult(
            mean=mean,
            cov=cov,
            prior_mean=field("prior_mean"),
            prior_cov=prior_cov,
            log_likelihood=loglik,
            nis=field("nis"),
            num_observed=field("num_observed"),
            # copies: a view would keep the whole output buffers alive (and unusable for the next
            # call's outputs) while a truncated-BPTT loop carries the belief into its next window
            final_belief={k: field(k)[:, -1].clone() for k in prog.traced.belief_keys},
            extras=extras,
        )

    def _fields(
        self, z: Tensor, mask: Tensor | None, belief: Belief, controls: Controls, common: dict[str, Tensor] | None = None
    ) -> tuple[Callable[[str], Tensor], SequenceProgram]:
        """Run the kernel; ``(field, program)`` where ``field(name)`` is output ``name`` ``[B, T, ...]``.

        ``common``: more controls, each ``[T, ...]`` and the same for every trajectory (the
        kernel's ``shared`` input; their gradient arrives as ``[T, ...]``, where a control
        expanded over the batch gets its gradient through a ``[B, T, ...]`` buffer)."""
        bsz, steps, mdim = z.shape
        dtype = z.dtype
        keys = sorted(belief)
        if common:
            if controls is not None and not isinstance(controls, dict):
                raise TypeError("common controls need the other controls as a dict")
            controls = {**(controls or {}), **{k: v[None].expand(bsz, *v.shape) for k, v in common.items()}}
        ctrl_layout, ctrl = _controls_layout(controls, dtype)
        # a control expanded over the batch (stride 0) is read once per step, not once per trajectory
        shared = tuple(k for (k, _, _), c in zip(ctrl_layout or (), ctrl, strict=True) if bsz > 1 and c.stride(0) == 0)
        layout = StepLayout(
            belief=tuple((k, tuple(belief[k].shape[1:]), belief[k].dtype) for k in keys),
            measurement_dim=mdim,
            has_mask=mask is not None,
            controls=ctrl_layout,
            dtype=dtype,
            shared=shared,
        )
        prog = self.program(layout, belief)
        padded = math.ceil(bsz / lanes(dtype)) * lanes(dtype)
        state0 = _pad_lanes(torch.cat([belief[k].reshape(bsz, -1).to(dtype) for k in keys], 1).T, padded)
        per_step = [z.permute(1, 2, 0)]
        if mask is not None:
            per_step.append(mask.to(dtype).permute(1, 2, 0))
        own = [c for (k, _, _), c in zip(ctrl_layout or (), ctrl, strict=True) if k not in shared]
        per_step += [c.reshape(bsz, steps, -1).to(dtype).permute(1, 2, 0) for c in own]
        step_in = _pad_lanes(torch.cat(per_step, 1), padded)
        given = common or {}
        common_in = [
            (given[k] if k in given else c[0]).reshape(steps, -1).to(dtype)
            for (k, _, _), c in zip(ctrl_layout or (), ctrl, strict=True)
            if k in shared
        ]
        trained = dict(self.filter.named_parameters())
        params = [trained[name].reshape(-1) for name, _ in prog.traced.params]
        flat_params = torch.cat(params) if params else z.new_zeros(1)
        threads = self.threads if self.threads is not None else caller_threads()
        outs = run_sequence(prog, state0, step_in, flat_params, shared=torch.cat(common_in, 1) if common_in else None, threads=threads)

        def field(name: str) -> Tensor:
            gi, offset, shape = prog.traced.fields[name]
            out, size = outs[gi], math.prod(shape)
            # slice only what is not the whole buffer: a slice's backward zero-fills a gradient buffer
            if offset or size != out.shape[1]:
                out = out[:, offset : offset + size]
            if bsz != out.shape[2]:
                out = out[..., :bsz]
            out = out.reshape(steps, *shape, bsz).movedim(-1, 0)
            kind = prog.traced.dtypes.get(name, dtype)
            return out if kind == dtype else out.to(kind)

        return field, prog
