"""Training survives interruption: a run stopped by SIGTERM, SIGINT or SIGUSR2 (submitit's warning
before a SLURM time limit) in the middle of an epoch writes a checkpoint, exits non-zero and is
marked interrupted; resuming it (``resume=true`` in its directory, or ``ckpt_path=`` into a new
one) gives exactly the results of the uninterrupted run (data order, optimizer, carried TBPTT
belief and generator states restored)."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from difffilter.learn.callbacks import TrainingInterrupted
from difffilter.learn.data import TrajectorySet, WindowedTrajectories
from difffilter.sim import ModelSimulator
from experiments.runner.experiment import run_experiment
from experiments.runner.runs import read_status
from tests.smoke_helpers import ROOT, TIMING_COLUMNS, read_rows
from tests.test_learn import CV_PRIOR, cv_model

f64 = torch.float64
# 16 training trajectories in batches of 4, 2 windows each: 8 optimiser steps per epoch, shuffled.
RUN = [
    "debug=smoke",
    "data.train_size=16",
    "data.batch_size=4",
    "trainer.limit_train_batches=null",
    "trainer.max_epochs=3",
    "logger=csv",
    "trainer.enable_progress_bar=false",
]


def _cfg(run_dir: Path, extra: list[str] = ()):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose("train", overrides=[*RUN, *extra, f"paths.output_dir={run_dir}", f"paths.log_dir={run_dir.parent}/logs"])


def _rows(run_dir: Path) -> list[dict[str, str]]:
    # everything but the wall time: every metric, consistency figure and learned value (full precision)
    return [{k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in read_rows(run_dir / "results.csv")]


def _killer(step: int, signum: int) -> list[str]:
    return ["+callbacks.kill._target_=tests.smoke_helpers.SignalAt", f"+callbacks.kill.step={step}", f"+callbacks.kill.signum={signum}"]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> list[dict[str, str]]:
    run_dir = tmp_path_factory.mktemp("full")
    run_experiment(_cfg(run_dir))
    return _rows(run_dir)


@pytest.mark.parametrize(
    ("step", "signum"),
    [(5, signal.SIGTERM), (8, signal.SIGINT), (3, signal.SIGUSR2)],
    ids=["sigterm-mid-epoch", "sigint-last-batch-of-epoch", "sigusr2-submitit-warning"],
)
def test_interrupted_run_resumes_bit_identically(tmp_path, uninterrupted, step, signum):
    first = tmp_path / "interrupted"
    with pytest.raises(TrainingInterrupted) as info:
        run_experiment(_cfg(first, _killer(step, int(signum))))
    assert info.value.code == 128 + int(signum)  # a scheduler sees a failure, not success
    last = first / "checkpoints" / "last.ckpt"
    assert last.is_file() and not (first / "results.csv").exists()
    status = read_status(first)
    assert status["status"] == "interrupted" and status["signal"] == signal.Signals(signum).name
    assert status["checkpoint"] == str(last)
    # resume into a new run directory from the file
    second = tmp_path / "resumed"
    run_experiment(_cfg(second, [f"ckpt_path={last}"]))
    assert _rows(second) == uninterrupted
    assert read_status(second)["status"] == "completed"


@pytest.mark.slow
def test_resume_true_continues_the_run_directory_and_cli_exit_status(tmp_path, uninterrupted):
    run_dir = tmp_path / "run"
    cmd = [sys.executable, str(ROOT / "experiments" / "train.py"), *RUN, f"hydra.run.dir={run_dir}", f"paths.log_dir={tmp_path}/logs"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([*cmd, *_killer(11, int(signal.SIGTERM))], capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    assert proc.returncode == 143, proc.stderr[-3000:]
    status = json.loads((run_dir / "status.json").read_text())
    assert status["status"] == "interrupted" and "resume=true" in status["resume"]
    proc = subprocess.run([*cmd, "resume=true"], capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert _rows(run_dir) == uninterrupted
    assert json.loads((run_dir / "status.json").read_text())["status"] == "completed"
    # the resumed run's ModelCheckpoint took the interrupted run's last.ckpt over (no last-v1.ckpt)
    assert sorted(p.name for p in (run_dir / "checkpoints").glob("last*.ckpt")) == ["last.ckpt"]


def test_failed_run_is_marked(tmp_path):
    run_dir = tmp_path / "run"
    with pytest.raises(Exception, match="matches nothing"):
        run_experiment(_cfg(run_dir, ["learn=[no_such_parameter_name]"]))
    status = read_status(run_dir)
    assert status is not None and status["status"] == "failed" and status["error"]


# -- the loader's resumable order ---------------------------------------------------------------
def _set(n=10, steps=6) -> TrajectorySet:
    sim = ModelSimulator(model=cv_model(), num_steps=steps, initial_mean=CV_PRIOR[0], initial_cov=CV_PRIOR[1])
    return TrajectorySet.from_simulation(sim(batch_size=n, seed=1), f64)


def _ids(batches) -> list[tuple[int, ...]]:
    return [(*b["index"].tolist(), b["window_index"]) for b in batches]


def test_loader_state_resumes_mid_epoch_and_reshuffles_per_epoch():
    data = _set()
    done = {"n": 0}
    loader = WindowedTrajectories(data, batch_size=3, window=4, shuffle=True, seed=7, progress=lambda: (done["n"], math.inf))
    epoch0 = _ids(loader)
    loader.set_epoch(1)
    epoch1 = _ids(loader)
    assert len(epoch0) == len(loader) == 8  # ceil(10 / 3) batches x 2 windows
    assert epoch0 != epoch1  # a new order every epoch, from seed + epoch
    # interrupted after 3 batches of epoch 1: the state holds the epoch and the position
    loader.set_epoch(1)
    it = iter(loader)
    for _ in range(3):
        next(it)
    done["n"] = 3
    state = loader.state_dict()
    assert state == {"seed": 7, "epoch": 1, "position": 3}
    fresh = WindowedTrajectories(data, batch_size=3, window=4, shuffle=True, seed=7)
    fresh.load_state_dict(state)
    assert _ids(fresh) == epoch1[3:]
    assert _ids(fresh) == epoch1  # the next pass starts at 0 (the epoch stays until set_epoch)
    # an epoch whose batches are all done is recorded as the start of the next one
    done["n"] = len(loader)
    assert loader.state_dict() == {"seed": 7, "epoch": 2, "position": 0}
    with pytest.raises(ValueError, match="seed"):
        WindowedTrajectories(data, batch_size=3, seed=8).load_state_dict(state)
