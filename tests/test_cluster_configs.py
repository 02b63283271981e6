"""Configs for outgrowing one machine compose: Lightning multi-node DDP, Hydra's submitit
launchers (SLURM, local) and the Optuna hyperparameter search; a job of the local submitit
launcher stopped by its time-limit signal leaves a checkpoint and an `interrupted` status.  The
Hydra plugins are optional (extra `sweep`): a test needing one skips cleanly when it is not
installed."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from tests.smoke_helpers import ROOT, plugin_installed

CONF = ROOT / "conf"


def _plugin(name: str) -> bool:
    return plugin_installed(name)


def _compose(tmp_path: Path, overrides: list[str], **kw):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("train", overrides=[*overrides, f"paths.output_dir={tmp_path}", f"paths.log_dir={tmp_path}/logs"], **kw)


def test_multinode_ddp_trainer_config():
    cfg = _compose(Path("/unused"), ["trainer=ddp_multinode", "trainer.num_nodes=4"])
    assert cfg.trainer.num_nodes == 4 and cfg.trainer.use_distributed_sampler is False
    strategy = instantiate(cfg.trainer.strategy)
    assert type(strategy).__name__ == "DDPStrategy"
    # everything else is the default trainer's
    assert cfg.trainer.max_epochs == 25 and cfg.trainer.gradient_clip_val == 10.0


@pytest.mark.parametrize("launcher", ["slurm", "slurm_local"])
def test_submitit_launchers_compose(tmp_path, launcher):
    if not _plugin("hydra_submitit_launcher"):
        pytest.skip("hydra-submitit-launcher is not installed (optional extra `sweep`)")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cfg = _compose(tmp_path, [f"hydra/launcher={launcher}", "hydra.launcher.timeout_min=30"], return_hydra_config=True)
    # the configs extend the plugin's own (no deprecated schema matching by name, no unknown field)
    assert not [str(w.message) for w in caught if "schema" in str(w.message)]
    launcher_cls = cfg.hydra.launcher._target_.rsplit(".", 1)
    module = importlib.import_module(launcher_cls[0])
    assert hasattr(module, launcher_cls[1])
    assert cfg.hydra.launcher.timeout_min == 30
    assert str(cfg.hydra.launcher.submitit_folder).startswith(str(cfg.hydra.sweep.dir))
    if launcher == "slurm":  # this project's resources over the plugin's defaults; its other fields kept
        assert cfg.hydra.launcher.cpus_per_task == 2 and cfg.hydra.launcher.signal_delay_s == 120
        assert "partition" in cfg.hydra.launcher and "array_parallelism" in cfg.hydra.launcher


def test_optuna_search_composes_and_selects_on_validation(tmp_path):
    if not _plugin("hydra_optuna_sweeper"):
        pytest.skip("hydra-optuna-sweeper is not installed (optional extra `sweep`)")
    cfg = _compose(tmp_path, ["hparams_search=optuna"], return_hydra_config=True)
    assert cfg.optimized_metric == "val/loss"  # never a test metric
    sweeper = cfg.hydra.sweeper
    assert sweeper._target_.endswith("OptunaSweeper") and sweeper.direction == "minimize"
    assert set(sweeper.params) == {"optimizer.lr", "data.window", "data.batch_size"}
    assert cfg.hydra.mode.name == "MULTIRUN"


@pytest.mark.slow
def test_optuna_search_runs_two_trials(tmp_path):
    if not _plugin("hydra_optuna_sweeper"):
        pytest.skip("hydra-optuna-sweeper is not installed (optional extra `sweep`)")
    sweep = tmp_path / "sweep"
    cmd = [
        sys.executable,
        str(ROOT / "experiments" / "train.py"),
        "hparams_search=optuna",
        "debug=smoke",
        "hydra.sweeper.n_trials=2",
        "hydra.sweeper.sampler.n_startup_trials=2",
        f"hydra.sweep.dir={sweep}",
        "logger=csv",
        "trainer.enable_progress_bar=false",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=900, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 0, proc.stderr[-3000:]
    best = OmegaConf.load(sweep / "optimization_results.yaml")
    assert set(best.best_params) == {"optimizer.lr", "data.window", "data.batch_size"}
    assert (sweep / "summary.md").exists() and len(list(sweep.glob("*/results.csv"))) == 2


@pytest.mark.slow
def test_submitit_time_limit_signal_writes_a_checkpoint_and_marks_the_job(tmp_path):
    # hydra/launcher=slurm_local: submitit's local executor sends SIGUSR2 30 s before the job's time
    # limit (1 min), as SLURM does signal_delay_s before it; the job is still training then and must
    # stop at a batch boundary with last.ckpt, status `interrupted` and the command that resumes it.
    if not _plugin("hydra_submitit_launcher"):
        pytest.skip("hydra-submitit-launcher is not installed (optional extra `sweep`)")
    sweep = tmp_path / "sweep"
    cmd = [
        sys.executable,
        str(ROOT / "experiments" / "train.py"),
        "-m",
        "seed=0",
        "debug=smoke",
        "trainer.max_epochs=100000",  # far longer than the time limit
        "logger=none",
        "trainer.enable_progress_bar=false",
        "hydra/launcher=slurm_local",
        "hydra.launcher.timeout_min=1",
        f"hydra.sweep.dir={sweep}",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode != 0  # the launcher reports the unfinished job: no success recorded
    status = json.loads((sweep / "0" / "status.json").read_text())
    assert status["status"] == "interrupted" and status["signal"] == "SIGUSR2", status
    assert status["checkpoint"] == str(sweep / "0" / "checkpoints" / "last.ckpt") and Path(status["checkpoint"]).is_file()
    assert f"hydra.run.dir={sweep / '0'}" in status["resume"] and "resume=true" in status["resume"]
    assert not (sweep / "0" / "results.csv").exists() and not (sweep / "summary.md").exists()
