"""FusedFilter: run a filter's recursion on a fast engine, with the filter's own interface."""

from __future__ import annotations

import warnings
from typing import Any

from torch import Tensor, nn
from torch.nn.utils import parametrize

from ..filters._common import cast_controls
from ..filters.base import Belief, FilterResult, RecursiveFilter, slice_controls, through_diffuse_phase
from ..filters.diffuse import DIFFUSE_COV
from ..filters.isolation import isolated_run
from ..models.base import Controls
from ..threads import scoped_forward
from .build import CompileError
from .generated import GeneratedEngine
from .graph import UnsupportedOp
from .inductor import InductorEngine

__all__ = ["ENGINES", "FusedFilter", "fuse"]

ENGINES = ("auto", "generated", "inductor", "eager")


class FusedFilter(nn.Module):
    """A filter run by a fast engine: same arguments, validation and :class:`FilterResult`.

    ``FusedFilter(filt)(measurements, initial_mean, initial_cov, mask=None, controls=None,
    belief=None)`` returns what ``filt(...)`` returns (same mask, log-likelihood and belief
    conventions); the wrapped filter's model and parameters are shared, not copied, so training
    through it trains ``filt``.

    Engines:

    * ``"generated"`` (CPU): the filter's own ``predict``/``update`` is traced once (batch size
      one, fake tensors), written out as scalar arithmetic and compiled to C++ that runs the
      whole sequence, one SIMD vector of trajectories at a time, with the belief in registers.
      Its backward is a generated reverse sweep that recomputes each step from the stored
      beliefs.  Works for any filter or mixer whose step has no Python decision on data values
      (KF, EKF, UKF in every variant, SimplifiedUKF, IMM of any bank, angular models...).
      Where the reference branches on data, the kernel computes both sides and selects per
      trajectory (the Joseph-form fallback of :func:`~difffilter.filters.update.gaussian_update`,
      the semi-definite square root of :func:`~difffilter.linalg.psd_sqrt`); the one
      difference: an innovation covariance that is not positive definite has its non-positive
      pivots clamped to ``n * eps * max|diag| + tiny`` where the reference adds jitter (both flag
      the step in ``extras["untrusted"]``).  Kernels are cached on disk
      (:func:`~difffilter.engines.build.cache_dir`); the first build of a kernel takes
      seconds to a minute, later processes load it.
    * ``"inductor"``: the filter's own step (the same ``predict``/``update`` as ``"generated"``
      and the filter itself), batch-first, with its small linear algebra (Cholesky, triangular
      solves, QR, small products) done element-wise and the same branch-free helpers
      (:mod:`.step`, :mod:`.branchfree`), compiled by ``torch.compile`` per step (any device
      inductor supports, CUDA included); if compilation fails, a warning and the eager step.
      Clamped pivots of the innovation covariance per step in ``extras["cholesky_clamps"]``.
    * ``"eager"``: the inductor engine's step uncompiled (for debugging and tests).
    * ``"auto"`` (default): ``"generated"`` on CPU, else ``"inductor"``; if the generated engine
      cannot run the filter (a warning says why), ``"inductor"``.  ``compile=False`` selects
      ``"eager"``.

    Every engine starts from the filter's own :meth:`~RecursiveFilter.start_belief`: a diffuse
    prior's first steps run in the filter's exact two-part form, the remaining steps on the
    engine; ``extras["untrusted"]`` is computed as the reference loop computes it.

    Args:
        filt: the filter or mixer (any :class:`RecursiveFilter`).
        engine: one of :data:`ENGINES`.
        compile: False selects the eager engine (when ``engine="auto"``).
        compile_options: extra keyword arguments for ``torch.compile`` (inductor engine).
        threads: generated engine: threads over groups of trajectories (``None``:
            ``torch.get_num_threads()``); inductor engine: inductor's ``cpp.threads`` (``None``:
            torch's default).  Default 1.
        cpp_wrapper: inductor's C++ wrapper (inductor engine).
        reuse_buffers: reuse the output buffers of the previous call when nothing references
            them any more (generated engine: any call; inductor and eager engines: no-grad calls).
    """

    def __init__(
        self,
        filt: RecursiveFilter,
        *,
        engine: str = "auto",
        compile: bool = True,  # noqa: A002
        compile_options: dict[str, Any] | None = None,
        threads: int | None = 1,
        cpp_wrapper: bool = True,
        reuse_buffers: bool = True,
    ) -> None:
        super().__init__()
        if not isinstance(filt, RecursiveFilter):
            raise TypeError(f"FusedFilter needs a difffilter filter (a RecursiveFilter), got {type(filt).__name__}")
        if engine not in ENGINES:
            raise ValueError(f"engine must be one of {list(ENGINES)}, got {engine!r}")
        if threads is not None and (not isinstance(threads, int) or threads < 1):
            raise ValueError(f"threads must be a positive int or None, got {threads!r}")
        if engine == "auto" and not compile:
            engine = "eager"
        self.engine = engine
        self.filter = filt
        self.threads = threads
        self.compile_options = dict(compile_options or {})
        if "mode" not in self.compile_options:  # torch.compile accepts either a mode or options
            opts = dict(self.compile_options.get("options") or {})
            if threads is not None:
                opts.setdefault("cpp.threads", threads)
            opts.setdefault("cpp_wrapper", bool(cpp_wrapper))
            self.compile_options["options"] = opts
        self.reuse_buffers = bool(reuse_buffers)
        #: the engine that ran the last call: "generated", "inductor", "eager" or "reference"
        self.last_engine: str | None = None
        self._generated: GeneratedEngine | None = None
        self._generated_failed: str | None = None
        self._inductor = InductorEngine(
            filt, compile=engine != "eager", compile_options=self.compile_options, reuse_buffers=self.reuse_buffers
        )

    @property
    def model(self) -> nn.Module:
        return self.filter.model

    @property
    def _compile_failed(self) -> bool:
        return self._inductor.compile_failed

    @property
    def state_dim(self) -> int:
        return self.filter.state_dim

    @property
    def measurement_dim(self) -> int:
        return self.filter.measurement_dim

    def initial_belief(
        self, initial_mean: Tensor, initial_cov: Tensor, batch_size: int | None = None, *, controls: Controls = None
    ) -> Belief:
        """The wrapped filter's :meth:`~RecursiveFilter.initial_belief`."""
        return self.filter.initial_belief(initial_mean, initial_cov, batch_size, controls=controls)

    def step(
        self, belief: Belief, measurement: Tensor, mask: Tensor | None = None, controls: Controls = None
    ) -> tuple[Belief, Belief, Any]:
        """One online step: the wrapped filter's own :meth:`~RecursiveFilter.step` (engines run
        whole sequences)."""
        return self.filter.step(belief, measurement, mask, controls)

    def generated_engine(self) -> GeneratedEngine:
        """The generated-kernel engine of this filter (created on first use)."""
        if self._generated is None:
            self._generated = GeneratedEngine(self.filter, threads=self.threads, reuse_buffers=self.reuse_buffers)
        return self._generated

    def _fallback(self, reason: str) -> None:
        self._generated_failed = reason
        name = type(self.filter).__name__
        warnings.warn(f"FusedFilter: the generated engine cannot run {name} ({reason}); using the inductor engine", stacklevel=3)

    @scoped_forward
    def forward(
        self,
        measurements: Tensor,
        initial_mean: Tensor | None = None,
        initial_cov: Tensor | None = None,
        mask: Tensor | None = None,
        controls: Controls = None,
        *,
        belief: Belief | None = None,
    ) -> FilterResult:
        """Same arguments and result as :meth:`RecursiveFilter.forward` of the wrapped filter
        (a non-finite trajectory passes no gradient to the others:
        :func:`~difffilter.filters.isolation.isolated_run`)."""
        return isolated_run(self._run, measurements, initial_mean, initial_cov, mask, controls, belief)

    def _run_rest(self, measurements: Tensor, *, mask: Tensor | None, controls: Controls, belief: Belief) -> FilterResult:
        return self._run(measurements, None, None, mask, controls, belief=belief)

    def _run(
        self,
        measurements: Tensor,
        initial_mean: Tensor | None,
        initial_cov: Tensor | None,
        mask: Tensor | None,
        controls: Controls,
        *,
        belief: Belief | None = None,
    ) -> FilterResult:
        filt = self.filter
        controls = cast_controls(controls, measurements)
        z, mask3, mean0, cov0 = filt.check_inputs(measurements, initial_mean, initial_cov, mask, controls)
        controls = filt.precompute_controls(controls)
        if belief is None:
            if mean0 is None or cov0 is None:
                raise ValueError("initial_mean and initial_cov are required unless belief= is given")
            with parametrize.cached():
                belief = filt.start_belief(mean0, cov0, slice_controls(controls, 0))
        if DIFFUSE_COV in belief:
            # a diffuse prior's first steps run in the filter's exact two-part form (reference code)
            self.last_engine = "reference"
            return through_diffuse_phase(filt, self._run_rest, z, mask3, controls, belief)
        bsz, n = z.shape[0], filt.state_dim
        if belief["mean"].shape != (bsz, n) or belief["cov"].shape != (bsz, n, n):
            raise ValueError(f"belief must hold mean [B, n] = [{bsz}, {n}] and cov [B, n, n], got {tuple(belief['mean'].shape)}")
        engine = self.engine
        if engine in ("auto", "generated") and z.device.type != "cpu":
            if engine == "generated":
                raise ValueError(f"the generated engine runs on CPU tensors, got {z.device}")
            engine = "inductor"
        if engine in ("auto", "generated") and self._generated_failed is None:
            try:
                out = self.generated_engine()(z, mask3, belief, controls)
                self.last_engine = "generated"
                return out
            except (UnsupportedOp, CompileError) as exc:
                if engine == "generated":
                    raise
                self._fallback(str(exc))
        out = self._inductor(z, mask3, belief, controls)
        self.last_engine = "inductor" if self._inductor.use_compile and not self._inductor.compile_failed else "eager"
        return out


def fuse(
    filt: RecursiveFilter,
    *,
    engine: str = "auto",
    compile: bool = True,  # noqa: A002
    threads: int | None = 1,
    cpp_wrapper: bool = True,
    reuse_buffers: bool = True,
    **compile_options: Any,
) -> FusedFilter:
    """``FusedFilter(filt, engine=..., compile=..., threads=..., cpp_wrapper=..., reuse_buffers=...,
    compile_options=compile_options)``."""
    return FusedFilter(
        filt,
        engine=engine,
        compile=compile,
        compile_options=compile_options,
        threads=threads,
        cpp_wrapper=cpp_wrapper,
        reuse_buffers=reuse_buffers,
    )
