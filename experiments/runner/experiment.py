"""Build, train and evaluate a filter-learning experiment from a Hydra config.

``run_experiment(cfg)`` (what ``experiments/train.py`` calls) builds the data module, the filter
with the *hand-tuned* parameters, trains a copy with :class:`FilterLearner`, tests it, then
evaluates on the held-out test trajectories

* ``hand-tuned`` - the filter with ``experiment.hand_tuned`` applied (the paper's settings),
* ``learned``    - the trained copy (best validation checkpoint when checkpointing is on),
* ``oracle``     - the filter with the simulator's true parameters (when ``experiment.oracle``),
* every entry of ``experiment.baselines``,

and writes ``results.csv`` / ``results.md`` (pooled rows, consistency per block) and
``per_run.csv`` (every filter's metrics on every test run, for paired comparisons across
filters and seeds: :mod:`difffilter.evaluate.evaluation`) to ``paths.output_dir``.

The ``experiment`` config node (per-paper overlays set it)::

    experiment:
      name: singer2d
      hand_tuned: {tau: 100.0, R: [100.0, 100.0]}  # constrained values set by name before training
      oracle:                     # null: no oracle row
        from_simulator: true      # set the test set's `true_params` (names matched by suffix)
        make_model: false         # or build the filter on the test set's make_model()
        params: {}                # explicit values, applied last
        filter: null              # a filter config replacing ${filter} (different structure)
      baselines:                  # extra filters, evaluated as configured (not trained); with `tune`
                                  # fitted first on the training (EM) or validation (search) data,
                                  # from the hand-tuned values: experiments/runner/baselines.py
        ekf: {filter: {_target_: difffilter.filters.EKF, model: ${model}}, params: {}}
      position_index: [0, 3]      # position components of the state (rmse_pos, figures)
      truth_position_index: null  # the same in the truth (default: position_index)
      state_index: null           # components for NEES / rmse_state (null: all)
      truth_index: null
      state_blocks: null          # {name: state indices}: NEES per block, e.g. {position: [0, 1], velocity: [2, 3]}
      truth_blocks: null          # the blocks' truth components (default: mapped through state_index/truth_index)
      metric: rmse_pos            # learned-filter metric run_experiment returns (Optuna)
      eval_batch_size: null       # test trajectories per evaluation batch (null: all)
      error_quantiles: null       # e.g. [0.5, 0.95]: extra columns pos_err_p50, pos_err_p95 =
                                  # quantiles of the position error norm over all test steps
      test_name: null             # the test set's label in sweep summaries (null: "main" when extra tests exist)
      extra_tests: {}             # {name: simulator config}: more held-out test sets (another scenario
                                  # family), drawn with the test set's size and seed; each gets the same
                                  # filters and files in <output_dir>/extra_tests/<name>/ (the oracle row
                                  # keeps the main test set's true parameters); an entry set to null is
                                  # skipped (an overlay dropping a test set of the experiment it extends)

With a smoother configured (``smoother=rts``, ``cfg.smoother.evaluate``), every filter that a
smoother supports gets a second row ``"<name> (smoothed)"``: the same metrics of the smoothed
states ``x_{t|T}`` over each whole test trajectory (``nis``/``nll`` are the filter's, and
``time_per_step_ms`` covers filter and smoother).

Names in ``hand_tuned``/``params`` follow :func:`difffilter.selection.assign_parameters`
(a vector sets a covariance's diagonal; a scalar sets ``s I`` or a ScaledMatrix's scale).

What the config leaves open comes from the model's
:class:`~difffilter.models.layout.ModelDefaults` (:func:`apply_model_defaults`): ``learn: null``
trains the model's default learnable set, ``experiment.position_index: null`` takes the
positions of its state layout.
"""

from __future__ import annotations

import copy
import csv
import logging
import math
import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytorch_lightning as pl
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict
from pytorch_lightning.callbacks import LearningRateMonitor, ModelCheckpoint, ProgressBar, TQDMProgressBar

from difffilter._util import as_dtype
from difffilter.evaluate.evaluation import EXTRA_TESTS_DIR, PER_RUN_FILE, consistency_table, evaluate_filter, evaluate_runs, write_per_run
from difffilter.filters.protocol import Filter
from difffilter.learn.callbacks import EpochSummary, GracefulInterrupt
from difffilter.learn.data import TrajectorySet
from difffilter.learn.divergence import DivergenceGuard
from difffilter.learn.learner import FilterLearner
from difffilter.learn.plots import DiagnosticFigures
from difffilter.models.layout import model_defaults
from difffilter.selection import assign_parameters, parameter_owners
from difffilter.smoothers import make_smoother, smoother_spec

from .baselines import tune_baseline
from .config_check import check_config
from .learner_config import figure_callback, finish_learner, split_learner_config
from .reporting import log_results, parameter_summary, parameter_values
from .runs import checkpoint_config, resume_checkpoint, run_status

# pytorch_lightning 2.6's pytree helper still builds torch's deprecated LeafSpec, a FutureWarning printed
# on every fit that nobody running these scripts can act on (the library itself does not filter it)
warnings.filterwarnings("ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated", category=FutureWarning)

__all__ = [
    "apply_model_defaults",
    "build_filter",
    "best_logged_value",
    "build_learner",
    "evaluate_experiment",
    "evaluate_filter",
    "format_results",
    "rebuild_filter",
    "run_experiment",
    "write_results",
]

log = logging.getLogger(__name__)

COLUMNS = (
    "filter",
    "rmse_pos",
    "rmse_state",
    "anees",
    "anees_dof",
    "anees_run_ci_lo",
    "anees_run_ci_hi",
    "anees_step_band_frac",
    "nis",
    "nis_dof",
    "nis_run_ci_lo",
    "nis_run_ci_hi",
    "nis_step_band_frac",
    "nll",
    "time_per_step_ms",
)


def _plain(node: Any) -> Any:
    return OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig | ListConfig) else node


def build_filter(filter_cfg: Any, *, dtype: torch.dtype, params: Mapping[str, Any] | None = None, **overrides: Any) -> Filter:
    """Instantiate a filter config (``overrides`` replace config entries, e.g. ``model=``), convert
    it to ``dtype`` and set ``params`` (constrained values by name; a null value sets nothing)."""
    filt = instantiate(filter_cfg, _convert_="all", **overrides)
    if not isinstance(filt, Filter):
        raise TypeError(f"the filter config must build a difffilter Filter, got {type(filt).__name__}")
    filt = filt.to(dtype)
    # a null value sets nothing: a baseline's params can drop a hand-tuned value its filter lacks
    values = {k: v for k, v in dict(_plain(params) or {}).items() if v is not None}
    if values:
        assign_parameters(filt, values)
    return filt


def format_results(rows: list[dict[str, Any]], *, title: str = "results", note: str = "") -> str:
    """A markdown table of evaluation rows, then the consistency table (per state block)."""
    extra = sorted(k for k in {k for r in rows for k in r} - set(COLUMNS) - {"parameters", "parameter_values"} if not k.startswith("nees_"))
    cols = [c for c in COLUMNS if any(c in r for r in rows)] + extra + (["parameters"] if any("parameters" in r for r in rows) else [])
    fmt = lambda v: v if isinstance(v, str) else ("nan" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.4g}")  # noqa: E731
    lines = [f"# {title}", "", note, "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r.get(c, float("nan"))) for c in cols) + " |" for r in rows]
    table = consistency_table(rows)
    if table:
        lines += [
            "",
            "Consistency: run-level mean [95 % t-interval over test runs] (value of a consistent filter), and the",
            "fraction of steps whose mean over runs lies in the per-step 95 % chi-square band.",
            "",
            table,
        ]
    return "\n".join(lines) + "\n"


def write_results(rows: list[dict[str, Any]], output_dir: str | Path, *, title: str = "results", note: str = "") -> tuple[Path, Path]:
    """Write ``results.csv`` (one row per filter) and ``results.md`` to ``output_dir``."""
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    cols = [c for c in COLUMNS if any(c in r for r in rows)] + sorted({k for r in rows for k in r} - set(COLUMNS))
    csv_path, md_path = out / "results.csv", out / "results.md"
    with csv_path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        writer.writeheader()
        for r in rows:
            writer.writerow({c: r.get(c, "") for c in cols})
    md_path.write_text(format_results(rows, title=title, note=note))
    return csv_path, md_path


def _oracle(cfg: DictConfig, hand: Filter, test: TrajectorySet, dtype: torch.dtype) -> Filter | None:
    spec = cfg.experiment.get("oracle")
    if spec is None:
        return None
    spec = _plain(spec)
    overrides: dict[str, Any] = {}
    if spec.get("make_model"):
        overrides["model"] = test.source.make_model()
    filter_cfg = spec.get("filter") or cfg.filter
    filt = build_filter(filter_cfg, dtype=dtype, **overrides) if (overrides or spec.get("filter")) else copy.deepcopy(hand)
    if spec.get("from_simulator"):
        true = getattr(test.source, "true_params", None)
        if not true:
            raise ValueError("experiment.oracle.from_simulator needs a simulator whose output has `true_params`")
        known = set(parameter_owners(filt))
        usable = {k: v for k, v in true.items() if any(n == k or n.endswith("." + k) for n in known)}
        assign_parameters(filt, usable)
    if spec.get("params"):
        assign_parameters(filt, spec["params"])
    return filt


def apply_model_defaults(cfg: DictConfig, filt: Filter) -> None:
    """Fill ``cfg.learn`` and ``cfg.experiment.position_index`` where they are null from the
    :class:`~difffilter.models.layout.ModelDefaults` of ``filt``'s model (in place, so the
    config's interpolations, e.g. ``learner.learn: ${learn}``, see the values).  Nothing changes
    for a model without defaults."""
    defaults = model_defaults(filt)
    if defaults is None:
        return
    with open_dict(cfg):
        if cfg.get("learn") is None:
            cfg.learn = list(defaults.learn)
        if cfg.experiment.get("position_index") is None:
            cfg.experiment.position_index = list(defaults.layout.position)


def rebuild_filter(
    filter: Mapping[str, Any],  # noqa: A002 - the field's word
    *,
    dtype: str = "float64",
    params: Mapping[str, Any] | None = None,
    learner: Mapping[str, Any] | None = None,
) -> Filter:
    """The filter a learner trains, rebuilt from the configs that built it (what a learner
    checkpoint's ``filter_config`` calls; values are then loaded from the state dict): the
    ``filter`` config with ``params`` (the hand-tuned values) set, then, when ``learner`` is a
    learner factory other than :class:`FilterLearner` (a paper's, which may reshape the filter,
    e.g. p003's grouped process noise), that factory applied to it."""
    filt = build_filter(filter, dtype=as_dtype(dtype), params=_plain(params))
    if learner is not None and learner.get("_target_") not in (None, _LEARNER_TARGET):
        factory, _ = split_learner_config(_plain(learner))
        factory = {k: v for k, v in factory.items() if k not in ("optimizer", "scheduler", "prior")}
        filt = instantiate(factory, _convert_="all", filter=filt, loss="nll").filter
    return filt


_LEARNER_TARGET = f"{FilterLearner.__module__}.{FilterLearner.__qualname__}"


def build_learner(cfg: DictConfig, hand: Filter) -> FilterLearner:
    """The learner of ``cfg`` on a copy of the hand-tuned filter, with the ``filter_config`` that
    rebuilds it (so that its checkpoints load with ``FilterLearner.load_from_checkpoint(path)``)
    and the loss as a config (kept in the checkpoint too)."""
    recipe = {
        "_target_": f"{rebuild_filter.__module__}.rebuild_filter",
        "_recursive_": False,  # rebuild_filter instantiates the configs itself, in order
        "filter": _plain(cfg.filter),
        "dtype": str(cfg.dtype),
        "params": _plain(cfg.experiment.get("hand_tuned")) or None,
        "learner": _plain(cfg.learner),
    }
    factory, settings = split_learner_config(_plain(cfg.learner))
    filt = copy.deepcopy(hand)
    if settings.get("dtype") is not None:
        filt = filt.to(as_dtype(settings["dtype"]))
    learner = instantiate(factory, _convert_="all", filter=filt, loss=instantiate(cfg.loss, _convert_="all"))
    if not isinstance(learner, FilterLearner):
        raise TypeError(f"learner config must build a FilterLearner, got {type(learner).__name__}")
    finish_learner(learner, settings)
    # Set after construction: Hydra would instantiate configs passed as arguments.  The
    # checkpoint's hyperparameters are these entries (FilterLearner.load_from_checkpoint).
    learner.hparams.update(filter_config=recipe, loss=_plain(cfg.loss))
    return learner


def _trainer(cfg: DictConfig) -> tuple[pl.Trainer, list[Any]]:
    loggers = [instantiate(v, _convert_="all") for v in (cfg.get("logger") or {}).values() if v is not None]
    callbacks = [instantiate(v, _convert_="all") for v in (cfg.get("callbacks") or {}).values() if v is not None]
    if not loggers:  # Lightning refuses a learning-rate monitor without a logger to write to
        callbacks = [c for c in callbacks if not isinstance(c, LearningRateMonitor)]
    # always on: a line per epoch, and a checkpoint when a signal stops training
    for kind in (EpochSummary, GracefulInterrupt):
        if not any(isinstance(c, kind) for c in callbacks):
            callbacks.append(kind())
    if not any(isinstance(c, DiagnosticFigures) for c in callbacks):  # every learner.figure_every_n_epochs, and the test set
        callbacks.append(figure_callback(_plain(cfg.get("learner"))))
    # always on unless divergence.enabled=false: a run that walks off stops as `diverged`
    if not any(isinstance(c, DivergenceGuard) for c in callbacks):
        callbacks.append(DivergenceGuard(**(_plain(cfg.get("divergence")) or {})))
    # Lightning's tqdm bar, chosen here so that the console looks the same on every machine
    # (Lightning would pick its rich bar where the rich package happens to be installed); not in
    # the callbacks config, which trainer.enable_progress_bar=false would contradict.
    if cfg.trainer.get("enable_progress_bar", True) and not any(isinstance(c, ProgressBar) for c in callbacks):
        callbacks.append(TQDMProgressBar())
    trainer = instantiate(cfg.trainer, _convert_="all", logger=loggers or False, callbacks=callbacks)
    return trainer, loggers


def run_experiment(cfg: DictConfig) -> dict[str, Any]:
    """Train and evaluate as configured; returns ``{"metric": the learned filter's
    experiment.metric, "optimized": what a sweeper minimises (cfg.optimized_metric), "rows": [...],
    ...}``.

    ``cfg.train: false`` evaluates the checkpoint ``cfg.ckpt_path`` instead of training (what
    ``experiments/eval.py`` runs), under the config stored in the checkpoint unless
    ``cfg.config_from_checkpoint`` is false (:func:`~experiments.runner.runs.checkpoint_config`);
    with ``cfg.train: true``, ``cfg.ckpt_path`` or ``cfg.resume`` continue an interrupted training
    run (:func:`~experiments.runner.runs.resume_checkpoint`).  The run directory gets a
    ``status.json`` (:func:`~experiments.runner.runs.run_status`)."""
    check_config(cfg)  # a number typed as text fails here, naming its key
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    train = bool(cfg.get("train", True))
    if not train:
        if not cfg.get("ckpt_path"):
            raise ValueError("train=false evaluates a checkpoint: give ckpt_path=<file>")
        if cfg.get("config_from_checkpoint", True):
            cfg = checkpoint_config(cfg, str(cfg.ckpt_path))
    with run_status(Path(cfg.paths.output_dir)):
        return _run(cfg, train)


def _run(cfg: DictConfig, train: bool) -> dict[str, Any]:
    pl.seed_everything(int(cfg.seed), workers=True, verbose=False)
    dtype = as_dtype(cfg.dtype)
    exp = cfg.experiment
    datamodule = instantiate(cfg.data, _convert_="all")
    hand = build_filter(cfg.filter, dtype=dtype, params=exp.get("hand_tuned"))
    apply_model_defaults(cfg, hand)
    learner = build_learner(cfg, hand)
    learner.run_config = OmegaConf.to_container(cfg, resolve=True)  # type: ignore[assignment]
    trainer, loggers = _trainer(cfg)
    optimized = math.nan
    fit_cpu = time.process_time()
    if train:
        trainer.fit(learner, datamodule=datamodule, ckpt_path=resume_checkpoint(cfg))
        if cfg.get("optimized_metric"):
            optimized = best_logged_value(trainer, str(cfg.optimized_metric))
        best = getattr(trainer.checkpoint_callback, "best_model_path", "") if trainer.checkpoint_callback else ""
        trainer.test(learner, datamodule=datamodule, ckpt_path="best" if best else None)
    else:
        trainer.test(learner, datamodule=datamodule, ckpt_path=str(cfg.ckpt_path))
    fit_cpu = time.process_time() - fit_cpu
    if not trainer.is_global_zero:
        return {}
    test = datamodule.dataset("test")
    baselines = build_baselines(cfg, hand, learner, datamodule)
    if train:
        baselines.learned_info["tuning_cpu_s"] = fit_cpu
    rows, note = evaluate_experiment(cfg, hand, learner, test, baselines=baselines)
    title = f"difffilter results: {exp.get('name', '')}"
    output_dir = Path(cfg.paths.output_dir)
    write_results(rows, output_dir, title=title, note=note)
    for test_name, sim_cfg in (_plain(exp.get("extra_tests")) or {}).items():
        if sim_cfg is None:  # an overlay's way to drop a test set of the experiment it extends
            continue
        log.info("extra test set %s", test_name)
        extra = datamodule.simulate(instantiate(sim_cfg, _convert_="all"), "test")
        extra_dir = output_dir / EXTRA_TESTS_DIR / str(test_name)
        extra_dir.mkdir(parents=True, exist_ok=True)
        extra_rows, extra_note = evaluate_experiment(
            cfg, hand, learner, extra, output_dir=extra_dir, label=str(test_name), oracle_source=test, baselines=baselines
        )
        write_results(extra_rows, extra_dir, title=title, note=extra_note)
    text = format_results(rows, title=f"results ({output_dir})", note=note)
    print(text)
    log_results(
        loggers, config=learner.run_config or {}, rows=rows, text=format_results(rows, title=title, note=note), step=trainer.global_step
    )
    learned = next(r for r in rows if r["filter"] == "learned")
    metric = float(learned.get(exp.get("metric", "rmse_pos"), math.nan))
    optimized = optimized if cfg.get("optimized_metric") else metric
    return {"metric": metric, "optimized": optimized, "rows": rows, "output_dir": str(output_dir), "trainer": trainer}


def best_logged_value(trainer: pl.Trainer, name: str) -> float:
    """The best value of the logged metric ``name`` during training: the checkpoint callback's
    best score when it monitors ``name``, else the last logged value."""
    keeper = trainer.checkpoint_callback
    if isinstance(keeper, ModelCheckpoint) and keeper.monitor == name and keeper.best_model_score is not None:
        return float(keeper.best_model_score)
    if name not in trainer.callback_metrics:
        raise ValueError(f"optimized_metric {name!r} was not logged; logged: {sorted(trainer.callback_metrics)}")
    return float(trainer.callback_metrics[name])


@dataclass
class Baselines:
    """The baseline filters of an experiment, built once for every test set: ``filters`` by row
    name, ``info`` their extra columns (``tuning_cpu_s``, ``tuning``), ``learned_info`` the
    learned row's (its training's CPU seconds)."""

    filters: dict[str, Filter] = field(default_factory=dict)
    info: dict[str, dict[str, Any]] = field(default_factory=dict)
    learned_info: dict[str, Any] = field(default_factory=dict)


def build_baselines(cfg: DictConfig, hand: Filter, learner: FilterLearner, datamodule: Any) -> Baselines:
    """Every entry of ``experiment.baselines``: built from its ``filter`` (default the
    experiment's) with its ``params``; an entry with ``tune`` starts from the hand-tuned values
    (then its ``params``, where a null drops a hand-tuned value the filter lacks) and is fitted on the training or validation data
    (:mod:`experiments.runner.baselines`), which ``datamodule`` must then give."""
    dtype = as_dtype(cfg.dtype)
    exp = cfg.experiment
    out = Baselines()
    indices = {k: exp.get(k) for k in ("position_index", "truth_position_index")}
    indices = {k: None if v is None else [int(i) for i in v] for k, v in indices.items()}
    for name, spec in (_plain(exp.get("baselines")) or {}).items():
        tune = spec.get("tune")
        if not tune:
            out.filters[name] = build_filter(spec.get("filter") or cfg.filter, dtype=dtype, params=spec.get("params"))
            continue
        if datamodule is None:
            raise ValueError(f"experiment.baselines.{name} has tune: it needs the experiment's data module (build_baselines's datamodule)")
        # a null in the entry's params drops that hand-tuned value (a filter that lacks the parameter)
        params = {k: v for k, v in {**(_plain(exp.get("hand_tuned")) or {}), **(spec.get("params") or {})}.items() if v is not None}
        filt = build_filter(spec.get("filter") or cfg.filter, dtype=dtype, params=params or None)
        out.info[name] = tune_baseline(
            filt,
            tune,
            name=str(name),
            train=datamodule.dataset("train"),
            val=datamodule.dataset("val"),
            initial_mean=learner.initial_mean,
            initial_cov=learner.initial_cov,
            **indices,
        )
        out.filters[name] = filt
    return out


def evaluate_experiment(
    cfg: DictConfig,
    hand: Filter,
    learner: FilterLearner,
    test: TrajectorySet,
    *,
    output_dir: str | Path | None = None,
    label: str = "",
    oracle_source: TrajectorySet | None = None,
    baselines: Baselines | None = None,
) -> tuple[list[dict[str, Any]], str]:
    """The results rows of the hand-tuned, learned, oracle and baseline filters on the test set
    (``per_run.csv`` written to ``output_dir``, default ``cfg.paths.output_dir``) and the table's
    note; ``label`` names an extra test set in the note, whose oracle keeps the true parameters of
    ``oracle_source`` (the main test set).  ``baselines``: the baseline filters built (and tuned)
    once by :func:`build_baselines` (built here, untuned entries only, when not given)."""
    dtype = as_dtype(cfg.dtype)
    exp = cfg.experiment
    filters: dict[str, Filter] = {"hand-tuned": hand, "learned": learner.filter}
    oracle = _oracle(cfg, hand, oracle_source if oracle_source is not None else test, dtype)
    if oracle is not None:
        filters["oracle"] = oracle
    if baselines is None:
        baselines = build_baselines(cfg, hand, learner, None)
    filters.update(baselines.filters)
    info = {"learned": baselines.learned_info, **baselines.info}
    indices = {k: exp.get(k) for k in ("position_index", "truth_position_index", "state_index", "truth_index")}
    indices = {k: None if v is None else [int(i) for i in v] for k, v in indices.items()}
    blocks = {str(k): [int(i) for i in v] for k, v in (_plain(exp.get("state_blocks")) or {}).items()} or None
    truth_blocks = {str(k): [int(i) for i in v] for k, v in (_plain(exp.get("truth_blocks")) or {}).items()} or None
    per_run: dict[str, dict[str, torch.Tensor]] = {}
    learned_names = list(cfg.get("learn") or [])
    spec = smoother_spec(_plain(cfg.get("smoother")))
    smoothed_rows = spec is not None and bool(spec.get("evaluate", True))
    kwargs = {
        "initial_mean": learner.initial_mean,
        "initial_cov": learner.initial_cov,
        "batch_size": exp.get("eval_batch_size"),
        "max_jitter": cfg.learner.get("max_jitter"),
        "error_quantiles": None if exp.get("error_quantiles") is None else [float(q) for q in exp.error_quantiles],
        "blocks": blocks,
        "truth_blocks": truth_blocks,
        **indices,
    }
    rows = []
    for k, (name, filt) in enumerate(filters.items(), start=1):
        log.info("evaluating %s (%d/%d) on %d test trajectories x %d steps", name, k, len(filters), len(test), test.num_steps)
        tic = time.perf_counter()
        filt = filt.to(dtype).eval()
        row: dict[str, Any] = {"filter": name, **info.get(name, {})}
        evaluation = evaluate_runs(filt, test, **kwargs)
        row.update(evaluation.summary)
        per_run[name] = evaluation.per_run
        if learned_names:
            try:
                row["parameters"] = parameter_summary(filt, learned_names)
                row["parameter_values"] = parameter_values(filt, learned_names)
            except ValueError:
                row["parameters"] = row["parameter_values"] = ""
        rows.append(row)
        metric = exp.get("metric", "rmse_pos")
        log.info("evaluated %s: %s %.4g (%.1f s)", name, metric, row.get(metric, math.nan), time.perf_counter() - tic)
        if smoothed_rows:
            assert spec is not None
            try:
                smoother = make_smoother(filt, spec["kind"], lag=spec.get("lag"), time_chunk=spec.get("time_chunk"))
            except (TypeError, ValueError) as exc:  # e.g. a Blend baseline: no smoother, say so
                log.info("no smoothed row for %s: %s", name, exc)
                continue
            smoothed = evaluate_runs(filt, test, smoother=smoother, **kwargs)
            rows.append({"filter": f"{name} (smoothed)", **smoothed.summary})
            per_run[f"{name} (smoothed)"] = smoothed.per_run
            for key in ("parameters", "parameter_values"):
                if key in row:
                    rows[-1][key] = row[key]
    write_per_run(per_run, Path(output_dir if output_dir is not None else cfg.paths.output_dir) / PER_RUN_FILE)
    note = (
        f"experiment `{exp.get('name', '')}`{f' (test set `{label}`)' if label else ''}: {len(test)} held-out test trajectories "
        f"x {test.num_steps} steps, "
        f"loss `{cfg.loss.get('_target_', cfg.loss)}`, learned {learned_names}; rmse in the truth's units; "
        "anees/nis: run-level means with 95 % t-intervals over runs (_run_ci_lo/hi) and the fraction of steps inside the "
        "per-step chi-square band (_step_band_frac); nll per observed step (nats); time_per_step_ms for the whole test batch; "
        "parameters: learned values in short (matrices by their diagonal), full values in results.csv."
    )
    if smoothed_rows:
        assert spec is not None
        kind = spec["kind"] if spec["kind"] == "rts" else f"fixed-lag (L = {spec.get('lag')})"
        note += (
            f" '(smoothed)' rows: the same filter followed by the {kind} smoother over each whole test trajectory "
            f"(training {'on smoothed' if spec.get('train', True) else 'on filtered'} states); their nis/nll are the filter's."
        )
    return rows, note
