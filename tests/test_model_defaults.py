"""Models carry their state layout, what they learn and a default belief (``model.defaults``), so
that ``python experiments/train.py model=<any model> filter=ukf debug=smoke`` composes and runs.

The acceptance case: a coordinated-turn model defined in one Python file and one YAML outside the
package (``tests/assets``), put on Hydra's search path and run end to end with learnable ``Q``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from difffilter.filters import UKF
from difffilter.models import ModelDefaults, StateLayout, describe, model_defaults, tracking_model
from difffilter.models.motion import Singer
from difffilter.sim import ModelSimulator
from experiments.runner.experiment import run_experiment
from tests.assets.ct_model import ct_model
from tests.smoke_helpers import config_files, needs_smartloc_drive, read_rows

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
ASSETS = Path(__file__).resolve().parent / "assets"
_NEEDS_DRIVE = needs_smartloc_drive()
MODELS = [pytest.param(p.stem, marks=_NEEDS_DRIVE) if p.stem.startswith("smartloc") else p.stem for p in config_files("model")]
F64 = torch.float64


def _compose(tmp_path: Path, overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        # the papers' config folders (train.yaml's search path) and the test assets' model group
        paths = [*OmegaConf.load(CONF / "train.yaml").hydra.searchpath, f"file://{ASSETS / 'conf'}"]
        extra = [f"hydra.searchpath=[{','.join(paths)}]", f"paths.output_dir={tmp_path}", f"paths.log_dir={tmp_path}"]
        return compose("train", overrides=[*overrides, *extra])


# ---------------------------------------------------------------------------------------- layout
def test_state_layout_validates_and_indexes():
    layout = StateLayout.kinematic(axes=2, order=3)
    assert layout.names == ("x", "vx", "ax", "y", "vy", "ay") and layout.position == (0, 3) and layout.dim == 6
    assert layout.units[1] == "m/s" and layout.index("vy", "x") == [4, 0]
    with pytest.raises(ValueError, match="units"):
        StateLayout(names=("a", "b"), units=("m",), position=(0,))
    with pytest.raises(ValueError, match="position"):
        StateLayout(names=("a", "b"), units=("m", "m"), position=(2,))
    with pytest.raises(ValueError, match="angles"):
        StateLayout(names=("a", "b"), units=("m", "m"), position=(0,), angles=(1, 1))
    with pytest.raises(ValueError, match="unknown"):
        layout.index("z")


def test_model_defaults_validate_and_are_found_through_filters():
    layout = StateLayout(names=("a", "b"), units=("m", "m/s"), position=(0,))
    with pytest.raises(ValueError, match="initial_mean"):
        ModelDefaults(layout=layout, learn=("R",), initial_mean=(0.0,), initial_var=(1.0, 1.0))
    with pytest.raises(ValueError, match="positive"):
        ModelDefaults(layout=layout, learn=("R",), initial_mean=(0.0, 0.0), initial_var=(1.0, 0.0))
    with pytest.raises(ValueError, match="both"):
        ModelDefaults(layout=layout, learn=("R",), initial_mean=(0.0, 0.0))
    model = tracking_model(dynamics=Singer(axes=2, dt=1.0, tau=10.0, sigma_a=1.0, dtype=F64), R=[4.0, 4.0])
    assert model.defaults.learn == ("tau", "sigma_a", "R") and model.defaults.layout.position == (0, 3)
    assert model_defaults(UKF(model)) is model.defaults
    with pytest.raises(ValueError, match="layout has 2"):
        describe(model, layout=layout, learn=["R"])


def test_model_simulator_takes_what_the_arguments_leave_open_from_the_model():
    model = ct_model(q=[0.01] * 5, r=4.0, initial_mean=[0.0, 0.0, 10.0, 0.0, 0.05], initial_var=[1.0] * 5)
    model.defaults = ModelDefaults(**{**model.defaults.__dict__, "reference": {"R": [9.0, 9.0]}})
    sim = ModelSimulator(model=model, num_steps=5)
    torch.testing.assert_close(sim.initial_mean, torch.tensor([0.0, 0.0, 10.0, 0.0, 0.05], dtype=F64))
    torch.testing.assert_close(sim.model.measurement.R, 9.0 * torch.eye(2, dtype=F64))  # the reference truth
    explicit = ModelSimulator(model=model, num_steps=5, initial_mean=[1.0] * 5, initial_cov=[2.0] * 5, true_params={})
    torch.testing.assert_close(explicit.model.measurement.R, 4.0 * torch.eye(2, dtype=F64))
    assert explicit(batch_size=3, seed=0).truth.shape == (3, 5, 5)
    bare = tracking_model(dynamics=Singer(axes=1, dt=1.0, tau=10.0, sigma_a=1.0, dtype=F64), R=[4.0])
    with pytest.raises(ValueError, match="default belief"):
        ModelSimulator(model=bare, num_steps=5)


# ------------------------------------------------------------------- the acceptance: model=ct
def test_coordinated_turn_model_from_the_test_folder_runs_with_ukf(tmp_path):
    cfg = _compose(tmp_path, ["model=ct", "filter=ukf", "debug=smoke", "logger=none", "callbacks=none"])
    assert cfg.experiment.name == "in_family"
    out = run_experiment(cfg)
    assert cfg.learn == ["Q", "R"] and list(cfg.experiment.position_index) == [0, 1]
    rows = {r["filter"]: r for r in read_rows(tmp_path / "results.csv")}
    assert set(rows) == {"hand-tuned", "learned", "oracle"}
    assert all(float(r["rmse_pos"]) > 0 for r in rows.values())
    # the table column summarises the 5x5 Q (issue 18: no whole matrices in tables); the CSV keeps it whole
    assert "Q=diag of 5 in [" in rows["learned"]["parameters"] and "Q=[[" in rows["learned"]["parameter_values"]
    # Q trained: the learned filter's Q moved away from the configured (= hand-tuned) one
    learned = out["trainer"].lightning_module.filter.model.dynamics.Q.detach()
    assert not torch.allclose(learned, torch.diag(torch.tensor([0.01, 0.01, 0.04, 1e-4, 1e-5], dtype=F64)))


def test_coordinated_turn_runs_through_the_entry_point(tmp_path):
    # the user's model module must be importable: here the repository root holds `tests.assets`
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)}
    cmd = [sys.executable, str(ROOT / "experiments" / "train.py"), "model=ct", "filter=ukf", "debug=smoke"]
    cmd += [f"hydra.searchpath=[file://{ASSETS / 'conf'}]", f"hydra.run.dir={tmp_path}", f"paths.log_dir={tmp_path}/logs"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600, env=env)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert "| learned |" in (tmp_path / "results.md").read_text()


# ------------------------------------------------------------------- every model of conf/model
@pytest.mark.parametrize("model", MODELS)
def test_every_model_config_carries_its_defaults(tmp_path, model):
    cfg = _compose(tmp_path, [f"model={model}"])
    built = instantiate(cfg.model, _convert_="all")
    defaults = model_defaults(built)
    assert defaults is not None, f"conf/model/{model}.yaml builds a model without defaults"
    assert defaults.layout.dim == built.state_dim and defaults.learn and defaults.initial_mean is not None
    assert OmegaConf.missing_keys(cfg) == set()


@pytest.mark.parametrize("model", MODELS)
def test_every_model_runs_with_ukf_at_debug_smoke(tmp_path, model):
    cfg = _compose(tmp_path, [f"model={model}", "filter=ukf", "debug=smoke", "logger=none", "callbacks=none"])
    run_experiment(cfg)
    rows = {r["filter"]: r for r in read_rows(tmp_path / "results.csv")}
    assert {"hand-tuned", "learned", "oracle"} <= set(rows)
