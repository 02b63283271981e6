"""Every config in conf/ composes (Hydra compose API) and builds its objects; every experiment
overlay present (including the per-paper ones) builds its data, filter and learner and runs a
few filter steps.  Running each experiment end-to-end is the slow variant."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest
import pytorch_lightning as pl
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from difffilter._util import as_dtype
from difffilter.filters import Filter
from difffilter.learn.data import TrajectoryDataModule
from difffilter.learn.learner import FilterLearner
from difffilter.models.base import StateSpaceModel
from experiments.runner.experiment import apply_model_defaults, build_filter, build_learner, run_experiment
from tests.smoke_helpers import config_files, needs_smartloc_drive, plugin_installed

CONF = Path(__file__).resolve().parents[1] / "conf"
# Groups of train.yaml (hydra/ is Hydra's own; a directory named like another primary config,
# e.g. benchmark/ for benchmark.yaml, belongs to that config).
PRIMARIES = sorted(p.stem for p in CONF.glob("*.yaml"))
# train.yaml's groups: those of its defaults list (conf/common.yaml), other than Hydra's own
TRAIN_GROUPS = sorted(
    next(iter(d)) for d in OmegaConf.load(CONF / "common.yaml").defaults if isinstance(d, DictConfig) and next(iter(d)) != "hydra"
)
# hparams_search needs an optional Hydra plugin: composed by tests/test_cluster_configs.py
OPTIONS = {g: [p.stem for p in config_files(g)] for g in TRAIN_GROUPS if g not in ("experiment", "debug", "hparams_search")}
# Groups whose options work with any experiment are composed together, one option of each per
# round (composition is the slow part); model and scenario options depend on the experiment.
GENERIC = [g for g in OPTIONS if g not in ("model", "scenario")]
ROUNDS = [{g: OPTIONS[g][i % len(OPTIONS[g])] for g in GENERIC} for i in range(max(len(OPTIONS[g]) for g in GENERIC))]
EXPERIMENTS = [p.stem for p in config_files("experiment")]
_NEEDS_DRIVE = needs_smartloc_drive()


def _with_data(*values: str) -> object:
    """A parameter set that skips (with the reason) when it names a smartLoc option and the data are absent."""
    return pytest.param(*values, marks=_NEEDS_DRIVE) if any(v.startswith("smartloc") for v in values) else pytest.param(*values)


def _compose(tmp_path: Path, overrides: list[str], name: str = "train", **kw) -> DictConfig:
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        extra = [f"paths.output_dir={tmp_path}", f"paths.log_dir={tmp_path}/logs"] if name == "train" else []
        return compose(config_name=name, overrides=[*overrides, *extra], **kw)


def _small_data(cfg: DictConfig) -> TrajectoryDataModule:
    return instantiate(cfg.data, _convert_="all", train_size=2, val_size=1, test_size=2, batch_size=2, max_steps=5)


def test_every_group_has_options_and_train_composes(tmp_path):
    assert {"model", "filter", "scenario", "loss", "trainer", "logger", "callbacks", "paths", "experiment", "debug"} <= set(TRAIN_GROUPS)
    cfg = _compose(tmp_path, [])
    assert OmegaConf.missing_keys(cfg) == set()
    assert cfg.experiment.name == "singer2d"


def _check_node(group: str, node, dtype: torch.dtype) -> None:
    if group == "model":
        assert isinstance(instantiate(node, _convert_="all"), StateSpaceModel)
    elif group == "filter":
        assert isinstance(build_filter(node, dtype=dtype), Filter)
    elif group == "scenario":
        sim = instantiate(node, _convert_="all")
        kw = {"num_steps": 3} if "num_steps" in inspect.signature(sim).parameters else {}
        data = sim(batch_size=2, seed=0, dtype=dtype, **kw)
        assert data.measurements.shape[0] == 2
    elif group == "loss":
        assert callable(instantiate(node, _convert_="all"))
    elif group == "optimizer":
        opt = instantiate(node, _convert_="all")([torch.nn.Parameter(torch.zeros(2))])
        assert isinstance(opt, torch.optim.Optimizer)
    elif group == "scheduler":
        opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(2))], lr=0.1)
        if node:
            assert hasattr(instantiate(node, _convert_="all")(opt), "step")
    elif group == "trainer":
        if node.get("accelerator") == "gpu" and not torch.cuda.is_available():
            return  # composed only
        assert isinstance(instantiate(node, _convert_="all", logger=False, callbacks=[]), pl.Trainer)
    elif group in ("logger", "callbacks"):
        for value in (node or {}).values():
            assert instantiate(value, _convert_="all") is not None
    else:
        assert node is not None


@pytest.mark.parametrize("choice", ROUNDS, ids=[",".join(r.values()) for r in ROUNDS])
def test_group_options_compose_and_instantiate(tmp_path, choice):
    cfg = _compose(tmp_path, [f"{g}={o}" for g, o in choice.items()])
    for group in choice:
        _check_node(group, cfg.get(group), as_dtype(cfg.dtype))


def _owning_experiment(group: str, option: str) -> str | None:
    for path in config_files("experiment"):
        if re.search(rf"override /{group}: {re.escape(option)}\s*$", path.read_text(), re.M):
            return path.stem
    return None


@pytest.mark.parametrize(("group", "option"), [_with_data(g, o) for g in ("model", "scenario") for o in OPTIONS.get(g, [])])
def test_model_and_scenario_options_instantiate(tmp_path, group, option):
    # A paper's model/scenario option is composed with the experiment overlay that selects it
    # (its settings interpolate the overlay's model); the others with the default experiment.
    owner = _owning_experiment(group, option)
    cfg = _compose(tmp_path, ([f"experiment={owner}"] if owner else []) + [f"{group}={option}"])
    _check_node(group, cfg.get(group), as_dtype(cfg.dtype))


@pytest.mark.parametrize("experiment", [_with_data(e) for e in EXPERIMENTS])
def test_experiment_overlay_builds_and_filters(tmp_path, experiment):
    cfg = _compose(tmp_path, [f"experiment={experiment}"])
    assert OmegaConf.missing_keys(cfg) == set(), "an overlay must fill every ??? value"
    for key in ("hand_tuned", "oracle", "baselines", "position_index", "metric"):
        assert key in cfg.experiment, f"experiment.{key} missing"
    dtype = as_dtype(cfg.dtype)
    dm = _small_data(cfg)
    hand = build_filter(cfg.filter, dtype=dtype, params=cfg.experiment.hand_tuned)
    learner = build_learner(cfg, hand)  # the learner.* keys mapped onto the learner's arguments
    assert isinstance(learner, FilterLearner) and learner.learned_names
    batch = dm.dataset("train").all()
    res = learner(batch)
    assert bool(torch.isfinite(res.mean).all())
    loss = learner.loss_fn(res, batch)
    assert loss.shape == (2,) and bool(torch.isfinite(loss).all())
    for spec in (OmegaConf.to_container(cfg.experiment.baselines, resolve=True) or {}).values():
        assert isinstance(build_filter(spec.get("filter") or cfg.filter, dtype=dtype, params=spec.get("params")), Filter)


@pytest.mark.parametrize("experiment", [_with_data(e) for e in EXPERIMENTS])
def test_learner_checkpoint_of_every_experiment_loads_without_arguments(tmp_path, experiment):
    # run_experiment's learner (a paper's factory may reshape the filter: p003's grouped Q,
    # smartLoc's soft gate) keeps in its hyperparameters how to rebuild it, so that
    # FilterLearner.load_from_checkpoint(path) alone gives the same filter.
    cfg = _compose(tmp_path, [f"experiment={experiment}"])
    dtype = as_dtype(cfg.dtype)
    hand = build_filter(cfg.filter, dtype=dtype, params=cfg.experiment.hand_tuned)
    apply_model_defaults(cfg, hand)
    learner = build_learner(cfg, hand)
    with torch.no_grad():  # learned values that differ from every config value
        for p in learner.filter.parameters():
            if p.requires_grad:
                p.add_(0.05)
    path = tmp_path / "learner.ckpt"
    torch.save(
        {"state_dict": learner.state_dict(), "hyper_parameters": dict(learner.hparams), "pytorch-lightning_version": pl.__version__}, path
    )
    loaded = FilterLearner.load_from_checkpoint(str(path))  # torch.load(weights_only=True) inside
    # (torch.nn.utils.parametrize makes a class per module: compare the names)
    assert type(loaded.filter).__name__ == type(learner.filter).__name__ and type(loaded.loss_fn) is type(learner.loss_fn)
    batch = _small_data(cfg).dataset("test").all()
    with torch.no_grad():
        a, b = learner(batch), loaded(batch)
    torch.testing.assert_close(b.mean, a.mean, rtol=0, atol=0, equal_nan=True)
    torch.testing.assert_close(b.cov, a.cov, rtol=0, atol=0, equal_nan=True)


def test_debug_and_hydra_launcher_configs_compose(tmp_path):
    cfg = _compose(tmp_path, ["debug=smoke"])
    assert cfg.trainer.max_epochs <= 2 and cfg.data.max_steps is not None
    for launcher in sorted(p.stem for p in (CONF / "hydra" / "launcher").glob("*.yaml")):
        if launcher.startswith("slurm") and not plugin_installed("hydra_submitit_launcher"):
            continue  # extends the optional submitit plugin's configs (tests/test_cluster_configs.py)
        hcfg = _compose(tmp_path, [f"hydra/launcher={launcher}"], return_hydra_config=True)
        assert hcfg.hydra.launcher._target_.startswith("hydra_plugins.")


@pytest.mark.parametrize("primary", [p for p in PRIMARIES if p != "train"])
def test_other_primary_configs_compose(tmp_path, primary):
    cfg = _compose(tmp_path, [], name=primary)
    assert isinstance(cfg, DictConfig)
    group = CONF / primary
    if group.is_dir():
        for option in sorted(p.stem for p in group.glob("*.yaml")):
            assert isinstance(_compose(tmp_path, [f"{primary}={option}"], name=primary), DictConfig)


@pytest.mark.slow
@pytest.mark.parametrize("experiment", [_with_data(e) for e in EXPERIMENTS])
def test_experiment_runs_end_to_end_with_debug_smoke(tmp_path, experiment):
    cfg = _compose(tmp_path, [f"experiment={experiment}", "debug=smoke", "logger=none", "callbacks=none"])
    out = run_experiment(cfg)
    assert (tmp_path / "results.csv").exists() and (tmp_path / "results.md").exists()
    assert {r["filter"] for r in out["rows"]} >= {"hand-tuned", "learned"}
