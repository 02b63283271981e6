"""Synthetic pseudoranges on the smartLoc geometry (experiments.papers.smartloc.synthetic) and the
``smartloc_synthetic_simulator`` scenario adapter: the error model is what it says, the
calibration recovers a known model from a synthetic drive, bad input is refused."""

from __future__ import annotations

import pytest
import torch

from experiments.papers.smartloc import default_smartloc_path, load_smartloc
from experiments.papers.smartloc.synthetic import PseudorangeErrorModel, calibrate_error_model, simulate_smartloc_drives, synthetic_drive

HAVE_SMARTLOC = (default_smartloc_path() / "Berlin_Potsdamer_Platz_Input.txt").exists()
pytestmark = pytest.mark.skipif(not HAVE_SMARTLOC, reason="smartLoc data folder ../shared/data/real not present")
F64 = torch.float64
SEGMENTS = {
    "train": {"start": 0.0, "stop": 0.6, "length": 120},
    "val": {"start": 0.0, "stop": 0.6, "length": 120},
    "test": {"start": 0.6, "stop": 1.0, "length": None, "stride": None},
}


@pytest.fixture(scope="module")
def drive():
    return load_smartloc(slots="satellite")


def _model(**kw) -> PseudorangeErrorModel:
    base = dict(
        los_scale=1.2,
        psi=0.8,
        nlos_leave=0.2,
        nlos_share=(0.6, 0.5, 0.3, 0.2, 0.1),
        nlos_positive=0.75,
        nlos_magnitudes=torch.linspace(60.0, 150.0, 10, dtype=F64),
        clock_drift0=-40.0,
    )
    return PseudorangeErrorModel(**{**base, **kw})


def test_measurements_are_the_filter_model_of_the_true_state_plus_the_error(drive) -> None:
    from experiments.papers.smartloc import make_smartloc_model

    batch, mean0, cov0, extra = simulate_smartloc_drives(drive, [0, 300, 700], 150, _model(), seed=3)
    assert batch.measurements.shape == (3, 150, drive.num_slots) and mean0.shape == (3, 7) and cov0.shape == (3, 7, 7)
    h = make_smartloc_model(drive, robust=None).measurement
    clean = h(extra["state"], {"sat_pos": batch.controls["sat_pos"], "glonass": batch.controls["glonass"]})
    m = batch.mask
    assert torch.allclose(batch.measurements[m], (clean + extra["error"])[m], atol=1e-6)
    assert torch.equal(batch.controls["pr_obs"], batch.measurements)
    # the geometry is the real drive's: reference track, satellites, odometry
    real = drive.batch(F64, elevation_mask_deg=15.0)
    assert torch.equal(batch.truth[1], real.truth[0, 300:450]) and torch.equal(batch.mask[2], real.mask[0, 700:850])
    assert torch.equal(batch.controls["speed"][0], real.controls["speed"][0, :150])
    assert torch.equal(extra["state"][..., :3], batch.truth)
    # the clock follows its drift: bias increments ~ drift x dt
    db = torch.diff(extra["state"][..., 4], dim=1)
    assert torch.allclose(db, extra["state"][:, 1:, 5] * batch.controls["dt"][:, 1:, 0], atol=3.0)
    again = simulate_smartloc_drives(drive, [0, 300, 700], 150, _model(), seed=3)[0]
    other = simulate_smartloc_drives(drive, [0, 300, 700], 150, _model(), seed=4)[0]
    assert torch.equal(again.measurements, batch.measurements) and not torch.equal(other.measurements, batch.measurements)


def test_error_model_statistics(drive) -> None:
    """Without NLOS the error is an AR(1) of the stated scale and coefficient; with NLOS the
    episodes have the stated share per C/N0 bin, sign and magnitudes."""
    starts = list(range(0, 1100, 25))
    _, _, _, ex = simulate_smartloc_drives(drive, starts, 200, _model(nlos_share=(0.0,) * 5), seed=0)
    batch = simulate_smartloc_drives(drive, starts, 200, _model(nlos_share=(0.0,) * 5), seed=0)[0]
    a = ex["error"] / batch.controls["pr_var"].sqrt()
    m = batch.mask
    assert not ex["nlos"].any()
    assert float(a[m].std()) == pytest.approx(1.2, rel=0.03)
    pair = m[:, 1:] & m[:, :-1]
    lag1 = float(torch.corrcoef(torch.stack([a[:, :-1][pair], a[:, 1:][pair]]))[0, 1])
    assert lag1 == pytest.approx(0.8, abs=0.02)
    model = _model()
    batch, _, _, ex = simulate_smartloc_drives(drive, starts, 200, model, seed=1)
    m, nl = batch.mask, ex["nlos"]
    cn0 = drive.cn0[torch.tensor(starts)[:, None] + torch.arange(200)]
    share = model.share(cn0)
    for c, target in enumerate(model.nlos_share):
        sel = m & (share == target)
        if int(sel.sum()) > 2000:
            assert float(nl[sel].double().mean()) == pytest.approx(target, abs=0.05), c
    pos = float((ex["error"][nl] > 0).double().mean())
    assert pos == pytest.approx(0.75, abs=0.04)
    assert float(ex["error"][nl].abs().median()) > 50.0


def test_calibration_recovers_a_known_model_from_a_synthetic_drive(drive) -> None:
    """Measured on three seeds: los_scale 1.12-1.22 (true 1.2), psi 0.72-0.75 (0.8; biased low by
    the clock estimate, see calibrate_error_model), shares within 0.07, nlos_positive 0.71-0.72
    (0.75; LOS tails beyond the cut are symmetric)."""
    truth = _model()
    syn, _ = synthetic_drive(drive, truth, seed=0)
    est = calibrate_error_model(syn, 0, drive.num_epochs)
    assert est.los_scale == pytest.approx(1.2, rel=0.08)
    assert 0.7 < est.psi < 0.85
    assert max(abs(a - b) for a, b in zip(est.nlos_share, truth.nlos_share, strict=True)) < 0.08
    assert est.nlos_positive == pytest.approx(0.75, abs=0.06)
    assert 0.15 < est.nlos_leave < 0.3
    assert est.clock_drift0 == pytest.approx(-40.0, abs=15.0)
    # a different model is told apart: small, nearly white errors, no NLOS
    est2 = calibrate_error_model(synthetic_drive(drive, _model(los_scale=0.5, psi=0.2, nlos_share=(0.0,) * 5), seed=1)[0], 0, 800)
    assert est2.los_scale == pytest.approx(0.5, rel=0.12) and abs(est2.psi - 0.2) < 0.1 and max(est2.nlos_share) < 0.03


def test_bad_input_is_refused(drive) -> None:
    with pytest.raises(ValueError, match="psi"):
        _model(psi=1.0)
    with pytest.raises(ValueError, match="nlos_share"):
        _model(nlos_share=(0.1, 0.2))
    with pytest.raises(ValueError, match="nlos_magnitudes"):
        _model(nlos_magnitudes=torch.tensor([]))
    with pytest.raises(ValueError, match="windows"):
        simulate_smartloc_drives(drive, [1300], 100, _model(), seed=0)
    with pytest.raises(ValueError, match="initial_sd"):
        simulate_smartloc_drives(drive, [0], 100, _model(), seed=0, initial_sd=(1.0, 2.0))
    with pytest.raises(ValueError, match="first < stop"):
        calibrate_error_model(drive, 500, 400)


def test_scenario_adapter_synthetic_train_real_test() -> None:
    from experiments.papers.smartloc import smartloc_simulator, smartloc_synthetic_simulator

    train = smartloc_synthetic_simulator(batch_size=4, seed=0, segments=SEGMENTS)
    val = smartloc_synthetic_simulator(batch_size=2, seed=1, segments=SEGMENTS, dtype="float32")
    test = smartloc_synthetic_simulator(batch_size=1, seed=2, segments=SEGMENTS)
    real_test = smartloc_simulator(batch_size=1, seed=2, segments=SEGMENTS)
    assert train.measurements.shape[:2] == (4, 120) and val.measurements.dtype == torch.float32
    assert torch.equal(test.measurements, real_test.measurements) and torch.equal(test.initial_mean, real_test.initial_mean)
    starts = train.start.tolist()
    assert all(0 <= s <= 823 - 120 for s in starts)
    assert not set(val.start.tolist()) >= set(starts)  # different seeds draw different windows
    real = smartloc_simulator(batch_size=1, seed=0, segments={"train": {"start": starts[0], "stop": starts[0] + 120, "length": None}})
    assert torch.equal(train.mask[0], real.mask[0]) and torch.equal(train.truth[0], real.truth[0])
    assert not torch.allclose(train.measurements[0][train.mask[0]], real.measurements[0][real.mask[0]])
    cut = smartloc_synthetic_simulator(batch_size=2, seed=0, segments=SEGMENTS, num_steps=30, error_model={"nlos_share": [0.0] * 5})
    assert cut.measurements.shape[1] == 30
    with pytest.raises(ValueError, match="unknown fields"):
        smartloc_synthetic_simulator(batch_size=1, seed=0, segments=SEGMENTS, error_model={"psy": 0.5})
    with pytest.raises(ValueError, match="synthetic names"):
        smartloc_synthetic_simulator(batch_size=1, seed=0, segments={"test": SEGMENTS["test"]}, synthetic=["train"], calibration="test")


@pytest.mark.slow
def test_experiment_smoke_with_synthetic_training(tmp_path) -> None:
    import csv
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    from experiments.runner.experiment import run_experiment

    root = Path(__file__).resolve().parents[1]
    with initialize_config_dir(config_dir=str(root / "conf"), version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[
                "experiment=smartloc_real",
                "scenario=smartloc_sim_train_early",
                "debug=smoke",
                f"paths.output_dir={tmp_path}",
                f"paths.log_dir={tmp_path}/logs",
            ],
        )
    run_experiment(cfg)
    with (tmp_path / "results.csv").open() as fh:
        table = list(csv.DictReader(fh))
    assert [r["filter"] for r in table] == ["hand-tuned", "learned", "ekf-gated", "ekf-no-gate", "snapshot-wls"]
    assert all(float(r["pos_err_p50"]) > 0 for r in table)


def _paired_module():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "experiments" / "smartloc_paired.py"
    spec = importlib.util.spec_from_file_location("difffilter_smartloc_paired", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_block_bootstrap_intervals() -> None:
    boot = _paired_module().block_bootstrap
    gen = torch.Generator().manual_seed(0)
    # a slowly varying error series (AR(1), like a filter's): a constant shift is found exactly,
    # and the interval of a pure-noise difference covers 0 and is wider with longer blocks
    x = torch.zeros(600, dtype=F64)
    w = torch.randn(600, generator=gen, dtype=F64)
    for k in range(1, 600):
        x[k] = 0.95 * x[k - 1] + w[k]
    a = 10.0 + x
    same = boot(a + 1.0, a, block=50, draws=500)
    assert same["median"] == pytest.approx((1.0, 1.0), abs=1e-9)
    y = torch.zeros(600, dtype=F64)
    v = torch.randn(600, generator=gen, dtype=F64)
    for k in range(1, 600):
        y[k] = 0.95 * y[k - 1] + v[k]
    short = boot(10.0 + y, a, block=1, draws=2000)["median"]
    long = boot(10.0 + y, a, block=50, draws=2000)["median"]
    assert long[0] < 0.0 < long[1] and (long[1] - long[0]) > 1.5 * (short[1] - short[0])
    with pytest.raises(ValueError, match="paired"):
        boot(a, a[:10], block=5, draws=10)
    with pytest.raises(ValueError, match="block"):
        boot(a, a, block=0, draws=10)
