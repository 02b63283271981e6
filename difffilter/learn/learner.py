"""Lightning module that learns a filter's parameters by back-propagation through the filter.

:class:`FilterLearner` wraps any difffilter filter or mixer (a
:class:`~difffilter.filters.protocol.Filter`): the filter's constrained parameters named in
``learn`` train (``requires_grad_``), everything else stays fixed.  Training batches are
truncated-BPTT windows (:mod:`difffilter.learn.data`): window ``k > 0`` of a batch continues
from the detached final belief of window ``k - 1``, so a trajectory of any length trains in
memory bounded by the window; each window is one optimiser step.

What the learner is given, and what it is not:

* the filter runs as given (convert it first, ``filter.double()``, for float64 learning), on the
  engine the policy picks (``DIFFFILTER_ENGINE``, default ``auto``: the compiled engine once the
  training calls add up, see :mod:`difffilter.engines.policy`); a
  :class:`~difffilter.engines.FusedFilter` wrapping it pins the compiled engine from the first
  step, while parameters, their names and checkpoints stay the filter's;
* :class:`LearnerOptions` holds the plain settings (initial belief, jitter bound, smoother,
  metric indices, scheduler interval): plain values, kept in checkpoints;
* a :class:`~difffilter.learn.losses.LogPrior` adds ``-weight * sum log p(value)`` to the loss;
* figures are the :class:`~difffilter.learn.plots.DiagnosticFigures` callback, a seeded
  perturbation of the start values is
  :func:`~difffilter.learn.replicates.perturb_initial_values` (both called by the runner).

Stability: ``options.max_jitter`` bounds the Cholesky jitter
(:func:`~difffilter.linalg.jitter_bound`); trajectories with a non-finite loss are
left out of the batch mean and counted (``stability/nonfinite_trajectories``); a step whose loss
or gradient is not finite is skipped (gradients cleared, so the optimiser leaves the parameters
and its state alone) and counted (``stability/skipped_steps``).  Each kind warns once.
Gradient clipping is the Trainer's ``gradient_clip_val``.

Smoothing (``options.smoother="rts"`` or a mapping ``{kind, lag, time_chunk, train, evaluate}``,
see :func:`difffilter.smoothers.smoother_spec`): with ``train`` (default) every window is
smoothed after filtering and the loss receives the :class:`~difffilter.smoothers.SmootherResult`
(state losses then score ``x_{t|T}``); the belief carried to the next window is still the
filter's.  Validation and test also log ``smoothed_rmse_pos``, ``smoothed_rmse_state`` and
``smoothed_anees``.

Logged to every logger: ``train/loss``, ``val/loss`` and ``val/{rmse_pos, rmse_state, anees,
nis, nll}`` (``test/...`` likewise) and every element of every learnable constrained value each
epoch (``params/model.measurement.R[0,0]``...).

Checkpoints load back without arguments: ``FilterLearner.load_from_checkpoint(path)`` rebuilds
the filter from ``filter_config`` (which :func:`~experiments.runner.experiment.run_experiment`
sets) and loads its parameters; :func:`load_filter` returns the learned filter alone.  A
checkpoint also carries what resuming needs (:mod:`difffilter.learn.checkpoints`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import pytorch_lightning as pl
import torch
from hydra.utils import instantiate
from torch import Tensor, nn

from .. import linalg
from ..engines import FusedFilter
from ..evaluate.stability import OnceWarner
from ..filters.base import detach_belief
from ..filters.protocol import Belief, Filter, FilterResult
from ..selection import learnable_values, match_parameters, parameter_owners, select_parameters
from ..smoothers import Smoother, SmootherResult, make_smoother, smoother_spec
from .checkpoints import CHECKPOINT_KEY, learner_state, restore_learner_state, set_rng_state
from .eval_steps import EvaluationSteps
from .losses import FilterLoss, LogPrior, make_loss
from .options import LearnerOptions
from .reporting import parameter_scalars

__all__ = ["FilterLearner", "LearnerOptions", "load_filter", "make_loss", "parameter_scalars"]


class FilterLearner(EvaluationSteps, pl.LightningModule):
    """Learn a filter's parameters from trajectories.

    Args:
        filter: the filter or mixer to train (any :class:`~difffilter.filters.protocol.Filter`),
            or a :class:`~difffilter.engines.FusedFilter` wrapping it (trained through the
            compiled engine; :attr:`filter` is then the wrapped filter); may be left out when
            ``filter_config`` is given.
        loss: ``"mse"``, ``"nll"``, ``"nees"``, a Hydra loss config (``{"_target_": ...}``) or a
            callable ``(result, batch) -> [B]`` (see :mod:`difffilter.learn.losses`).  Names and
            configs are kept in the checkpoint's hyperparameters, callables are not.
        learn: names of the parameters to train (``["R", "Q", "tau", "transition"]``; matched as
            in :mod:`difffilter.selection`); ``None`` trains every parameter.
        optimizer: ``params -> torch.optim.Optimizer`` (a Hydra ``_partial_``); default Adam(lr=0.01).
        scheduler: optional ``optimizer -> LR scheduler`` (a Hydra ``_partial_``); its interval
            and monitored metric are ``options.scheduler_interval`` and ``options.monitor``.
        prior: a :class:`~difffilter.learn.losses.LogPrior`; the loss becomes
            ``data_loss - prior.weight * sum log p(value)``.
        options: :class:`LearnerOptions` (or a mapping of its fields).
        filter_config: a Hydra config that builds the filter's structure (its values come from
            the state dict), kept in the checkpoint so that ``load_from_checkpoint(path)`` needs
            no argument; builds ``filter`` when that is left out.  ``run_experiment`` sets it
            (:func:`~experiments.runner.experiment.rebuild_filter`).

    Example::

        learner = FilterLearner(UKF(model).double(), "nll", learn=["Q", "R"])
        pl.Trainer(max_epochs=20).fit(learner, datamodule=TrajectoryDataModule(simulator))
        learned = FilterLearner.load_from_checkpoint(path, filter=UKF(model)).filter
    """

    def __init__(
        self,
        filter: Filter | FusedFilter | None = None,  # noqa: A002 - the field's word
        loss: FilterLoss | str | Mapping[str, Any] = "nll",
        *,
        learn: Sequence[str] | None = None,
        optimizer: Callable[[Iterable[nn.Parameter]], torch.optim.Optimizer] | None = None,
        scheduler: Callable[[torch.optim.Optimizer], Any] | None = None,
        prior: LogPrior | None = None,
        options: LearnerOptions | Mapping[str, Any] | None = None,
        filter_config: Mapping[str, Any] | None = None,
    ) -> None:
        super().__init__()
        if filter is None and filter_config is not None:
            filter = instantiate(dict(filter_config), _convert_="all")  # noqa: A001
        if filter is None:
            raise TypeError(
                "FilterLearner needs filter= (or filter_config=); a checkpoint saved without filter_config loads with "
                "FilterLearner.load_from_checkpoint(path, filter=<a filter of the same structure>)"
            )
        engine = filter if isinstance(filter, FusedFilter) else None
        if engine is not None:
            filter = engine.filter  # noqa: A001
        if not isinstance(filter, Filter):
            raise TypeError(
                "filter must be a difffilter Filter (a RecursiveFilter, formerly GaussianFilter; a mixer; a baseline) "
                f"or a FusedFilter wrapping one, got {type(filter).__name__}"
            )
        if prior is not None and not isinstance(prior, LogPrior):
            raise TypeError(f"prior must be a difffilter.learn.losses.LogPrior, got {type(prior).__name__}")
        # names and configs are kept (load_from_checkpoint rebuilds from them); objects are not
        ignore = ["filter", "optimizer", "scheduler", "prior", "options"] + ([] if isinstance(loss, str | Mapping) else ["loss"])
        self.save_hyperparameters(ignore=ignore)
        self.filter = filter
        self.loss_fn = make_loss(loss)
        self.learned_names = select_parameters(self.filter, None if learn is None else list(learn))
        # An empty config group (scheduler: none) arrives as an empty mapping: no scheduler.
        self.optimizer_factory = optimizer or None
        self.scheduler_factory = scheduler or None
        self.prior = prior
        self.prior_names = {} if prior is None else {k: match_parameters(self.filter, [k])[k] for k in prior.priors}
        self.set_engine(engine)
        self.set_options(LearnerOptions.of(options))
        self.skipped_steps = 0
        self.nonfinite_trajectories = 0
        self._warn = OnceWarner()
        self._carries: dict[int, Belief] = {}
        self._carry_index: Tensor | None = None
        self._skip_pending = False
        self._sums: dict[str, Tensor] = {}
        self._restored_rng: Mapping[str, Any] | None = None
        self._restored_carry = False
        #: the resolved experiment config (kept in checkpoints; set by run_experiment)
        self.run_config: dict[str, Any] | None = None

    def set_options(self, options: LearnerOptions) -> None:
        """Use ``options`` (the initial belief buffers, the smoother and the indices follow them)."""
        self.options = options
        self.hparams["options"] = options.as_dict()
        pdt = next((p.dtype for p in self.filter.parameters()), torch.get_default_dtype())
        mean0, cov0 = options.initial_mean, options.initial_cov
        self.register_buffer("initial_mean", None if mean0 is None else torch.as_tensor(mean0, dtype=pdt))
        cov0 = None if cov0 is None else torch.as_tensor(cov0, dtype=pdt)
        self.register_buffer("initial_cov", torch.diag_embed(cov0) if cov0 is not None and cov0.ndim == 1 else cov0)
        spec = smoother_spec(options.smoother)
        built = None if spec is None else make_smoother(self.filter, spec["kind"], lag=spec.get("lag"), time_chunk=spec.get("time_chunk"))
        object.__setattr__(self, "_smoother", built)  # shares self.filter; kept out of the module tree
        self.smooth_training = spec is not None and bool(spec.get("train", True))
        self.indices = options.indices

    @property
    def engine(self) -> FusedFilter | None:
        """The :class:`~difffilter.engines.FusedFilter` that runs :attr:`filter`, or ``None``
        (the filter runs itself)."""
        return self._engine

    def set_engine(self, engine: FusedFilter | None) -> None:
        """Run :attr:`filter` through ``engine`` (a ``FusedFilter(learner.filter)``) from now on;
        ``None``: the filter itself.  Kept outside the module tree: parameter names and the
        state dict stay the filter's own."""
        if engine is not None and (not isinstance(engine, FusedFilter) or engine.filter is not self.filter):
            raise ValueError("engine must be a FusedFilter wrapping this learner's filter (FusedFilter(learner.filter)) or None")
        object.__setattr__(self, "_engine", engine)

    # -- running the filter -------------------------------------------------------------------
    def initial_belief(self, batch: Mapping[str, Any]) -> tuple[Tensor, Tensor]:
        """``(mean, cov)`` from the batch, else the learner's own initial belief."""
        mean, cov = batch.get("initial_mean"), batch.get("initial_cov")
        mean = self.initial_mean if mean is None else mean
        cov = self.initial_cov if cov is None else cov
        if mean is None or cov is None:
            raise ValueError("no initial belief: the batches carry none, so give LearnerOptions(initial_mean=..., initial_cov=...)")
        return mean, cov

    def forward(self, batch: Mapping[str, Any], belief: Belief | None = None) -> FilterResult | SmootherResult:  # type: ignore[override]
        """Run the filter on a batch dict (from ``belief`` if given, else the initial belief), then
        the smoother when it is configured for training."""
        result = self.run_filter(batch, belief)
        return self.smooth(result, batch, belief) if self.smooth_training else result

    def run_filter(self, batch: Mapping[str, Any], belief: Belief | None = None) -> FilterResult:
        """The filter's result on a batch dict (from ``belief`` if given, else the initial belief)."""
        mean, cov = self.initial_belief(batch)
        with linalg.jitter_bound(self.options.max_jitter):
            return (self._engine or self.filter)(
                batch["measurements"],
                None if belief is not None else mean,
                None if belief is not None else cov,
                mask=batch.get("mask"),
                controls=batch.get("controls"),
                belief=belief,
            )

    @property
    def smoother(self) -> Smoother | None:
        """The configured smoother (sharing :attr:`filter`), or ``None``."""
        return self._smoother

    def smooth(self, result: FilterResult, batch: Mapping[str, Any], belief: Belief | None = None) -> SmootherResult:
        """The configured smoother's backward pass over the filter ``result`` of ``batch``."""
        if self._smoother is None:
            raise ValueError("FilterLearner has no smoother: pass options=LearnerOptions(smoother='rts') (or a mapping)")
        if belief is None:
            mean, cov = self.initial_belief(batch)
            belief = self.filter.initial_belief(mean, cov, batch_size=int(batch["measurements"].shape[0]))
        with linalg.jitter_bound(self.options.max_jitter):
            return self._smoother.smooth(result, belief, batch.get("controls"))

    def log_prior(self) -> Tensor | None:
        """Sum of the configured parameter log-priors (``None`` without priors)."""
        if self.prior is None:
            return None
        owners = parameter_owners(self.filter)
        total: Tensor | None = None
        for key, prior in self.prior.priors.items():
            for name in self.prior_names[key]:
                mod, attr, _ = owners[name]
                lp = prior.log_prob(getattr(mod, attr))
                total = lp if total is None else total + lp
        return total

    def _zero_loss(self) -> Tensor:
        """A zero loss connected to every trainable parameter (backward runs, gradients are 0),
        so that DDP processes stay in step when one of them has nothing finite to learn from."""
        params = [p for p in self.filter.parameters() if p.requires_grad]
        return sum((p * 0).sum() for p in params)  # type: ignore[return-value]

    def _reduce_loss(self, per_trajectory: Tensor, stage: str) -> tuple[Tensor | None, int]:
        finite = torch.isfinite(per_trajectory)
        bad = int((~finite).sum())
        if bad and stage == "train":
            self.nonfinite_trajectories += bad
            self._warn(
                "trajectory",
                f"{bad} trajectories with a non-finite loss were left out of the batch mean "
                "(counted in stability/nonfinite_trajectories; warning shown once)",
            )
        if not bool(finite.any()):
            return None, bad
        return per_trajectory[finite].mean(), bad

    # -- Lightning hooks ----------------------------------------------------------------------
    def training_step(self, batch: Mapping[str, Any], batch_idx: int) -> Tensor:
        index = batch.get("index")
        if index is None:  # batches from elsewhere: whole trajectories, no carry-over
            index = torch.arange(batch["measurements"].shape[0], device=batch["measurements"].device)
        window = int(batch.get("window_index", 0))
        same = self._carry_index is not None and torch.equal(self._carry_index.to(index.device), index)
        if not same:
            self._carries, self._carry_index = {}, index
        belief = self._carries.get(window - 1) if window > 0 else None
        if window > 0 and belief is None:
            self._warn("carry", "a continuation window arrived without its previous window; restarting from the initial belief")
        self._restored_carry = False
        result = self(batch, belief)
        # Keyed by window so that an optimiser re-evaluating a window (LBFGS closures) still
        # starts it from the previous window's belief.
        self._carries = {k: v for k, v in self._carries.items() if k >= window - 1}
        self._carries[window] = detach_belief(result.final_belief)
        loss, _ = self._reduce_loss(self.loss_fn(result, batch), "train")
        prior = self.log_prior()
        if loss is not None and prior is not None:
            loss = loss - self.prior.weight * prior  # type: ignore[union-attr]
        if loss is None or not bool(torch.isfinite(loss)):
            self._skip_pending = True
            loss = self._zero_loss()
        else:
            self.log("train/loss", loss, on_step=True, on_epoch=True, prog_bar=True, batch_size=int(index.numel()), sync_dist=True)
        return loss

    def on_before_optimizer_step(self, optimizer: torch.optim.Optimizer) -> None:
        params = [p for group in optimizer.param_groups for p in group["params"]]
        bad = self._skip_pending or any(p.grad is not None and not bool(torch.isfinite(p.grad).all()) for p in params)
        flag = torch.tensor(float(bad), dtype=torch.float64, device=self.device)
        if self.trainer.world_size > 1:
            flag = self.trainer.strategy.reduce(flag, reduce_op="sum")
        self._skip_pending = False
        if float(flag) > 0:
            for p in params:
                p.grad = None
            self.skipped_steps += 1
            self._warn(
                "step",
                "an optimiser step with a non-finite loss or gradient was skipped (counted in stability/skipped_steps; warning shown once)",
            )
        self.log("stability/skipped_steps", float(self.skipped_steps), on_step=True, on_epoch=False, batch_size=1)

    def on_train_epoch_end(self) -> None:
        scalars: dict[str, float] = {}
        for name, value in learnable_values(self.filter).items():
            scalars.update(parameter_scalars(f"params/{name}", value, self.options.max_logged_elements))
        scalars["stability/nonfinite_trajectories"] = float(self.nonfinite_trajectories)
        # covariance factorisations that failed even at the largest allowed jitter (identity
        # factor substituted): process-wide count from difffilter.linalg
        scalars["stability/cholesky_failures"] = float(linalg.cholesky_failure_count())
        # identical on every process (parameters are synchronised by DDP); sync_dist averages
        # equal values, which leaves them unchanged
        self.log_dict(scalars, on_step=False, on_epoch=True, batch_size=1, sync_dist=True)

    def on_train_epoch_start(self) -> None:
        if not self._restored_carry:  # a run resumed mid-epoch continues the batch in progress
            self._carries, self._carry_index = {}, None
        self._restored_carry = False

    def on_train_start(self) -> None:
        # the generators continue from the checkpoint's states once nothing else draws from them
        if self._restored_rng is not None:
            set_rng_state(self._restored_rng)
            self._restored_rng = None

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint[CHECKPOINT_KEY] = learner_state(self)

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        stored = checkpoint.get("hyper_parameters") or {}
        if "options" not in stored:  # a checkpoint from before LearnerOptions: the same fields, flat
            legacy = {f.name: stored[f.name] for f in dataclasses.fields(LearnerOptions) if f.name in stored}
            if legacy:
                self.set_options(LearnerOptions(**legacy))
        restore_learner_state(self, checkpoint.get(CHECKPOINT_KEY))

    def configure_optimizers(self) -> Any:
        params = [p for p in self.filter.parameters() if p.requires_grad]
        if not params:
            raise ValueError("FilterLearner has no trainable parameter: check `learn`")
        factory = self.optimizer_factory or functools.partial(torch.optim.Adam, lr=1e-2)
        optimizer = factory(params)
        if self.scheduler_factory is None:
            return optimizer
        scheduler = self.scheduler_factory(optimizer)
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": self.options.scheduler_interval, "monitor": self.options.monitor},
        }


def load_filter(path: str, **kwargs: Any) -> Filter:
    """The learned filter of a :class:`FilterLearner` checkpoint, in evaluation mode on the CPU:
    ``FilterLearner.load_from_checkpoint(path, map_location="cpu", **kwargs).filter`` (the
    filter rebuilt from the checkpoint's ``filter_config``; pass ``filter=`` for a checkpoint
    saved without one)."""
    learner = FilterLearner.load_from_checkpoint(str(path), map_location="cpu", **kwargs)
    return learner.filter.eval()
