"""Training that diverges fails; a run killed by SIGKILL is not reported as running.

* :class:`~difffilter.learn.divergence.DivergenceGuard` trips on a non-finite parameter, a
  variance that moved more than ``max_scale_ratio`` from its start, an absurd loss and a run of
  skipped steps, and leaves an ordinary run alone;
* ``python experiments/train.py debug=smoke optimizer.lr=1e6`` (which used to exit 0 with a
  learned R of 1.5e-154 and status ``completed``) exits non-zero with ``diverged``;
* a process killed by SIGKILL inside :func:`~experiments.runner.runs.run_status` reads as
  ``killed``; a heartbeat that stopped reads as ``stale``; a live run reads as ``running``.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch
from torch import nn

from difffilter.learn.divergence import DivergenceGuard, TrainingDivergedError, scale_parameters
from difffilter.params import Interval, Positive, PositiveDefinite, register_constrained
from experiments.runner.liveness import assess
from experiments.runner.runs import read_status, run_status
from experiments.runner.sweep import unfinished_jobs

_ROOT = Path(__file__).resolve().parents[1]
F64 = torch.float64


class _Toy(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        register_constrained(self, "R", torch.diag(torch.tensor([4.0, 9.0], dtype=F64)), PositiveDefinite())
        register_constrained(self, "q", torch.tensor([0.5], dtype=F64), Positive())
        register_constrained(self, "rho", torch.tensor([0.0], dtype=F64), Interval(-1.0, 1.0, log_scale=False))


def _guard(toy: nn.Module) -> DivergenceGuard:
    guard = DivergenceGuard()
    guard.start = {k: v.to(F64) for k, v in scale_parameters(toy).items()}
    return guard


def test_scale_parameters_are_the_variances_and_positive_values_only() -> None:
    toy = _Toy()
    scales = scale_parameters(toy)
    assert set(scales) == {"R", "q"}  # rho is an Interval: no scale
    assert torch.allclose(scales["R"], torch.tensor([4.0, 9.0], dtype=F64))


def test_an_ordinary_change_passes() -> None:
    toy = _Toy()
    guard = _guard(toy)
    guard.check(toy, 10.0)
    toy.R = torch.diag(torch.tensor([4e-6, 9e5], dtype=F64))  # 6 orders of magnitude: learning, not divergence
    toy.q = torch.tensor([0.5e8], dtype=F64)
    toy.rho = torch.tensor([0.99], dtype=F64)
    guard.check(toy, -3e6)  # |L - L0| = 3e6 + 10 < 1e6 * max(|10|, 1)


@pytest.mark.parametrize(
    ("name", "value", "match"),
    [
        ("R", torch.diag(torch.tensor([4.0, 1.5e-154], dtype=F64)), "R moved from 9 to 1.5e-154"),
        ("R", torch.diag(torch.tensor([4e13, 9.0], dtype=F64)), "max_scale_ratio"),
        ("q", torch.tensor([1e-13], dtype=F64), "q moved"),
    ],
)
def test_a_variance_beyond_the_scale_ratio_trips(name: str, value: torch.Tensor, match: str) -> None:
    toy = _Toy()
    guard = _guard(toy)
    setattr(toy, name, value)
    with pytest.raises(TrainingDivergedError, match=match):
        guard.check(toy, None)


def test_a_non_finite_parameter_trips() -> None:
    toy = _Toy()
    guard = _guard(toy)
    with torch.no_grad():
        toy.parametrizations.rho.original.fill_(float("nan"))
    with pytest.raises(TrainingDivergedError, match="rho.*not finite"):
        guard.check(toy, None)


def test_an_absurd_loss_trips() -> None:
    toy = _Toy()
    guard = _guard(toy)
    guard.check(toy, 0.2)  # the first loss; |L0| < 1 uses 1 as the scale
    guard.check(toy, 9e5)
    with pytest.raises(TrainingDivergedError, match="max_loss_ratio"):
        guard.check(toy, 2e6)


def test_consecutive_skipped_steps_trip() -> None:
    toy = _Toy()
    guard = DivergenceGuard(max_skipped_steps=3)
    guard.start = scale_parameters(toy)
    toy.skipped_steps = 0  # type: ignore[assignment]
    loss = torch.tensor(1.0)
    guard.on_train_batch_end(None, toy, {"loss": loss}, None, 0)  # type: ignore[arg-type]
    for i in range(2):
        toy.skipped_steps += 1  # type: ignore[operator]
        guard.on_train_batch_end(None, toy, {"loss": torch.tensor(0.0)}, None, i)  # type: ignore[arg-type]
    toy.skipped_steps += 1  # type: ignore[operator]
    with pytest.raises(TrainingDivergedError, match="3 consecutive steps"):
        guard.on_train_batch_end(None, toy, {"loss": torch.tensor(0.0)}, None, 3)  # type: ignore[arg-type]


@pytest.mark.parametrize(("key", "value"), [("max_scale_ratio", 0.5), ("max_loss_ratio", float("inf")), ("max_skipped_steps", 0)])
def test_bad_limits_name_the_key(key: str, value: float) -> None:
    with pytest.raises(ValueError, match=f"divergence.{key}"):
        DivergenceGuard(**{key: value})


@pytest.mark.slow
def test_train_with_a_huge_learning_rate_exits_non_zero_as_diverged(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(_ROOT), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "experiments/train.py", "debug=smoke", "optimizer.lr=1e6", "logger=[]", f"hydra.run.dir={run_dir}"]
    proc = subprocess.run(cmd, cwd=_ROOT, capture_output=True, text=True, env=env, timeout=600)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0, out[-3000:]
    assert "training diverged" in out
    state = read_status(run_dir)
    assert state is not None and state["status"] == "diverged", state
    assert "max_scale_ratio" in state["error"] or "max_loss_ratio" in state["error"] or "not finite" in state["error"]
    assert not (run_dir / "results.md").exists()  # no results table for a run that diverged


_HOLD = textwrap.dedent(
    """
    import sys, time
    from experiments.runner.runs import run_status
    with run_status(sys.argv[1], heartbeat_s=0.5):
        print("started", flush=True)
        time.sleep(120)
    """
)


def test_a_run_killed_by_sigkill_reads_as_killed(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(_ROOT), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-c", _HOLD, str(tmp_path)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "started"
        first = json.loads((tmp_path / "status.json").read_text())["heartbeat"]
        time.sleep(1.5)  # several heartbeats
        alive = read_status(tmp_path)
        assert alive is not None and alive["status"] == "running" and alive["pid"] == proc.pid
        assert alive["heartbeat"] >= first
        # the unfinished-jobs census of a sweep lists a running job as running
        assert [why for _, why in unfinished_jobs(tmp_path)] == ["running"]
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert json.loads((tmp_path / "status.json").read_text())["status"] == "running"  # what the file says
    state = read_status(tmp_path)
    assert state is not None and state["status"] == "killed" and state["recorded_status"] == "running"
    assert str(proc.pid) in state["reason"]
    assert read_status(tmp_path, raw=True)["status"] == "running"  # type: ignore[index]
    ((job, why),) = unfinished_jobs(tmp_path)
    assert why.startswith("killed")


def test_a_heartbeat_that_stopped_reads_as_stale() -> None:
    old = (dt.datetime.now(dt.timezone.utc) - dt.timedelta(minutes=10)).isoformat(timespec="seconds")
    remote = {"status": "running", "pid": 1, "host": socket.gethostname() + "-elsewhere", "heartbeat": old, "heartbeat_interval_s": 30}
    state = assess(remote)
    assert state["status"] == "stale" and "no heartbeat for" in state["reason"]
    fresh = dict(remote, heartbeat=dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"))
    assert assess(fresh)["status"] == "running"
    assert assess({"status": "completed", "pid": 1})["status"] == "completed"


def test_a_completed_run_stops_its_heartbeat(tmp_path: Path) -> None:
    with run_status(tmp_path, heartbeat_s=0.05):
        time.sleep(0.2)
    before = (tmp_path / "status.json").read_text()
    time.sleep(0.3)
    assert (tmp_path / "status.json").read_text() == before
    assert json.loads(before)["status"] == "completed"
