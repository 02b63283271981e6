"""The contract every difffilter estimator satisfies: :class:`Filter` and its :class:`FilterResult`.

A :class:`Filter` is an ``nn.Module`` whose ``forward`` maps measurements ``[B, T, m]`` and the
belief before the first measurement to a :class:`FilterResult` (posterior and prior moments per
step, innovation log-likelihoods, the final belief).  Recursive filters
(:class:`~difffilter.filters.base.RecursiveFilter`: KF, EKF, UKF...), mixers (IMM, Blend) and
whole-trajectory baselines of the papers all implement it, so the learning stack
(:class:`~difffilter.learn.learner.FilterLearner`, ``run_experiment``) accepts any of them.

Belief carry-over: ``result.final_belief`` is a ``dict`` of tensors that
``forward(next_measurements, belief=result.final_belief)`` continues from (truncated
back-propagation, online use).  Estimators without a recursion set ``carries_belief = False``
and reject ``belief=``.

Shared input rules (:meth:`Filter.check_inputs`): ``initial_mean [n]|[B, n]`` and
``initial_cov [n, n]|[B, n, n]`` broadcast over the batch; ``mask [B, T]|[B, T, m]`` False marks
a missing value, which may be NaN and is replaced by zero before any arithmetic; bad input
raises ``TypeError``/``ValueError`` naming the argument and the expected shape (and, for
per-trajectory inputs, the failing batch elements); a non-finite raw parameter is refused before
it reaches the batch.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import torch
from torch import Tensor, nn
from torch.utils import _pytree

from ..linalg import inside_vmap, nonfinite_rows
from ..models.base import Controls, DynamicsModel, MeasurementModel, StateSpaceModel
from ..params import check_covariance

__all__ = ["Belief", "Filter", "FilterResult"]

Belief = dict[str, Tensor]


@dataclass
class FilterResult:
    """Outputs of a filter run over ``T`` steps (batch-first).

    Attributes:
        mean, cov: posterior after the update at every step, ``[B, T, n]``, ``[B, T, n, n]``.
        prior_mean, prior_cov: prior after the prediction at every step.
        log_likelihood: ``[B, T]`` innovation log-likelihood per step (0 for a missing step).
        nis: ``[B, T]`` normalised innovation squared; ``num_observed [B, T]`` its degrees of
            freedom (observed measurement components).
        final_belief: the full belief after the last step, to continue filtering (TBPTT).
        extras: filter-specific per-step outputs (IMM: ``mode_probs [B, T, M]``...), also
            reachable as attributes (``result.mode_probs``).  The recursive filters add
            ``untrusted [B, T]`` (bool): steps whose update could not be vouched for to ``1e-2``
            relative (a repaired innovation covariance, a variance reduction beyond what the
            update's form resolves in this dtype, a non-finite or negative posterior variance).
    """

    mean: Tensor
    cov: Tensor
    prior_mean: Tensor
    prior_cov: Tensor
    log_likelihood: Tensor
    nis: Tensor
    num_observed: Tensor
    final_belief: Belief
    extras: dict[str, Tensor] = field(default_factory=dict)

    def __getattr__(self, name: str) -> Tensor:
        extras = self.__dict__.get("extras", {})
        if name in extras:
            value: Tensor = extras[name]
            return value
        raise AttributeError(name)

    @property
    def total_log_likelihood(self) -> Tensor:
        """``[B]`` sum of the per-step log-likelihoods."""
        return self.log_likelihood.sum(-1)


_RESULT_FIELDS = ("mean", "cov", "prior_mean", "prior_cov", "log_likelihood", "nis", "num_observed", "final_belief", "extras")

# A pytree node, so that torch.func transforms (vmap, grad) can return a FilterResult.
_pytree.register_pytree_node(
    FilterResult,
    lambda r: ([getattr(r, k) for k in _RESULT_FIELDS], None),
    lambda children, _: FilterResult(*children),
    serialized_type_name="difffilter.FilterResult",
)


class Filter(nn.Module):
    """Base of every estimator: ``forward(measurements, initial_mean, initial_cov, mask=None,
    controls=None, *, belief=None) -> FilterResult`` (see the module docstring).

    Subclasses implement :meth:`forward`; they hold parameters, never beliefs, so ``forward`` is a
    pure function of its inputs.

    Args:
        model: the state-space model a single-model filter works on (registered as ``model``;
            its dimensions are the filter's).  Filters that combine other filters (the IMM)
            pass none and define ``state_dim`` and ``measurement_dim`` themselves.
    """

    #: False for estimators that work on whole trajectories and cannot continue from a belief.
    carries_belief: ClassVar[bool] = True

    def __init__(self, model: StateSpaceModel | None = None) -> None:
        super().__init__()
        if model is None:
            return
        if not isinstance(model, StateSpaceModel):
            raise TypeError(f"model must be a difffilter StateSpaceModel, got {type(model).__name__}")
        self.model = model

    @property
    def state_dim(self) -> int:
        return self.model.state_dim

    @property
    def measurement_dim(self) -> int:
        return self.model.measurement_dim

    def forward(
        self,
        measurements: Tensor,
        initial_mean: Tensor | None = None,
        initial_cov: Tensor | None = None,
        mask: Tensor | None = None,
        controls: Controls = None,
        *,
        belief: Belief | None = None,
    ) -> FilterResult:  # pragma: no cover - abstract
        """Filter ``measurements [B, T, m]`` from ``(initial_mean, initial_cov)`` or ``belief``."""
        raise NotImplementedError

    def precompute_controls(self, controls: Controls) -> Controls:
        """``controls [B, T, ...]`` with the entries that this filter's models derive from them
        for every step at once (:meth:`~difffilter.models.base.DynamicsModel.precompute_controls`
        of each dynamics and measurement model, in module order); called by ``forward`` after
        :meth:`check_inputs` and before the time loop.  Unchanged when no model derives any."""
        for module in self.modules():
            if isinstance(module, (DynamicsModel, MeasurementModel)):
                controls = module.precompute_controls(controls)
        return controls

    # -- validation shared by every filter --------------------------------------------------
    def _param_dtype(self) -> torch.dtype | None:
        for p in self.parameters():
            if p.is_floating_point():
                return p.dtype
        for b in self.buffers():
            if b.is_floating_point():
                return b.dtype
        return None

    def check_inputs(
        self, measurements: Tensor, initial_mean: Tensor | None, initial_cov: Tensor | None, mask: Tensor | None, controls: Controls
    ) -> tuple[Tensor, Tensor | None, Tensor | None, Tensor | None]:
        """Validate shapes, dtypes and values; return ``(z, mask [B,T,m] or None, mean, cov)``."""
        # Checks of values (finite, symmetric, positive definite; finite parameters and controls)
        # read the data, which breaks a torch.compile graph: inside a compiled region only shapes
        # and dtypes are checked.
        # The same inside torch.func.vmap, whose per-sample values Python cannot read.
        values = not torch.compiler.is_compiling() and not inside_vmap()
        n, m = self.state_dim, self.measurement_dim
        if not isinstance(measurements, Tensor):
            raise TypeError(f"measurements must be a torch.Tensor [B, T, {m}], got {type(measurements).__name__}")
        if measurements.dtype not in (torch.float32, torch.float64):
            raise TypeError(
                f"measurements must be float32 or float64 (the dtypes difffilter computes in; half precision cannot hold "
                f"covariances), got {measurements.dtype}"
            )
        if measurements.ndim != 3 or measurements.shape[-1] != m:
            raise ValueError(f"measurements must have shape [B, T, {m}], got {tuple(measurements.shape)}")
        bsz, steps = measurements.shape[:2]
        if bsz == 0 or steps == 0:
            raise ValueError(
                f"measurements must hold at least one trajectory and one step (B >= 1, T >= 1), got shape {tuple(measurements.shape)}"
            )
        dtype = measurements.dtype
        pdt = self._param_dtype()
        if pdt is not None and pdt != dtype:
            raise TypeError(f"measurements dtype {dtype} differs from the filter's parameter dtype {pdt}; convert one with .to()")
        if values:
            self.check_parameters()
        if mask is not None:
            if not isinstance(mask, Tensor):
                raise TypeError("mask must be a bool tensor [B, T] or [B, T, m]")
            if mask.shape == (bsz, steps):
                mask = mask[..., None].expand(bsz, steps, m)
            elif mask.shape != (bsz, steps, m):
                raise ValueError(
                    f"mask must have shape [B, T] = [{bsz}, {steps}] or [B, T, m] = [{bsz}, {steps}, {m}], got {tuple(mask.shape)}"
                )
            if mask.dtype != torch.bool:
                if mask.is_complex() or (values and not bool(((mask == 0) | (mask == 1)).all())):
                    raise ValueError("mask must be boolean (True = observed) or hold only 0 and 1")
                mask = mask.to(torch.bool)
        observed = measurements
        if mask is not None:
            observed = torch.where(mask, measurements, torch.zeros((), dtype=dtype, device=measurements.device))
        # one sum decides a finite batch (nonfinite_rows); the element-wise test only finds the culprit
        if values and bool(nonfinite_rows(observed, 0)):
            bad = ~torch.isfinite(observed)
            idx = tuple(int(i) for i in bad.nonzero()[0])
            raise ValueError(
                f"measurements contain a non-finite value at [b, t, i] = {list(idx)} that is not masked; "
                "pass mask=False there to mark it missing"
            )
        measurements = observed
        if initial_mean is not None:
            initial_mean = self._check_mean(initial_mean, bsz, n, dtype, values=values)
        if initial_cov is not None:
            initial_cov = self._check_cov(initial_cov, bsz, n, dtype, values=values)
        self._check_controls(controls, bsz, steps, values=values)
        return measurements, mask, initial_mean, initial_cov

    def check_parameters(self) -> None:
        """Refuse a non-finite raw parameter (e.g. after a diverged optimiser step) before it
        turns a whole batch into NaN; the error names the parameter."""
        for name, p in self.named_parameters():
            if not bool(torch.isfinite(p).all()):
                readable = name.replace("parametrizations.", "").replace(".original", "")
                raise ValueError(
                    f"parameter {readable} ({name}) holds non-finite raw values; set a finite constrained value "
                    f"(e.g. module.{readable.rsplit('.', 1)[-1]} = ...) or restore a checkpoint"
                )

    @staticmethod
    def _check_mean(mean: Tensor, bsz: int, n: int, dtype: torch.dtype, *, values: bool = True) -> Tensor:
        if not isinstance(mean, Tensor):
            raise TypeError(f"initial_mean must be a torch.Tensor [{n}] or [B, {n}]")
        if mean.dtype != dtype:
            raise TypeError(f"initial_mean dtype {mean.dtype} differs from measurements dtype {dtype}")
        if mean.shape == (n,):
            mean = mean.expand(bsz, n)
        elif mean.shape != (bsz, n):
            raise ValueError(f"initial_mean must have shape [{n}] or [B, {n}] = [{bsz}, {n}], got {tuple(mean.shape)}")
        if not values:
            return mean
        bad = ~torch.isfinite(mean).all(-1)
        if bool(bad.any()):
            raise ValueError(f"initial_mean contains non-finite values (batch elements {bad.nonzero().flatten().tolist()[:10]})")
        return mean

    @staticmethod
    def _check_cov(cov: Tensor, bsz: int, n: int, dtype: torch.dtype, *, values: bool = True) -> Tensor:
        if not isinstance(cov, Tensor):
            raise TypeError(f"initial_cov must be a torch.Tensor [{n}, {n}] or [B, {n}, {n}]")
        if cov.dtype != dtype:
            raise TypeError(f"initial_cov dtype {cov.dtype} differs from measurements dtype {dtype}")
        if cov.shape == (n, n):
            # one matrix for the whole batch: checked once, not once per trajectory
            return (check_covariance("initial_cov", cov, n) if values else cov).expand(bsz, n, n)
        if cov.shape != (bsz, n, n):
            raise ValueError(f"initial_cov must have shape [{n}, {n}] or [B, {n}, {n}] = [{bsz}, {n}, {n}], got {tuple(cov.shape)}")
        if not values:
            return cov
        return check_covariance("initial_cov", cov, n, batch_ok=True)

    def _check_controls(self, controls: Controls, bsz: int, steps: int, *, values: bool = True) -> None:
        if controls is None:
            return
        items = [("controls", controls)] if isinstance(controls, Tensor) else [(f"controls[{k!r}]", v) for k, v in dict(controls).items()]
        for name, v in items:
            if not isinstance(v, Tensor):
                raise TypeError(f"{name} must be a tensor [B, T, ...]")
            if v.ndim < 2 or v.shape[0] != bsz or v.shape[1] != steps:
                raise ValueError(f"{name} must have shape [B, T, ...] = [{bsz}, {steps}, ...], got {tuple(v.shape)}")
        parts = [mod for mod in self.modules() if isinstance(mod, (DynamicsModel, MeasurementModel))]
        if parts and not any(part.uses_controls for part in parts):
            raise ValueError(
                "controls were given, but no part of the model uses them (e.g. a LinearModel without B, a "
                "FunctionalModel(controls=False)), so they would be silently ignored: drop controls=, or give the model its "
                "inputs (LinearModel(B=...), FunctionalModel(controls=True))"
            )
        if not values:
            return
        for module in parts:
            module.validate_controls(controls)
