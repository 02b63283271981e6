"""p002's disturbed family and in-family walks: the injected disturbances have the stated
statistics, the in-family walks come from the filter's own model with p002's GPS availability."""

from __future__ import annotations

import csv
import math

import pytest
import torch

from difffilter.evaluate.intervals import crossed_interval
from experiments.papers.p002 import arc_bursts, gps_availability, p002_infamily, pdr_model, simulate_p002, sweep_table, turn_heading_error
from experiments.papers.p002.model import wrap_angle
from experiments.papers.p002.report import between_sweeps, main

f64 = torch.float64


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def test_turn_heading_error_is_one_relative_error_per_turn():
    dpsi = torch.zeros(2000, 30, dtype=f64)
    dpsi[:, 5] = math.radians(90.0)  # a corner
    dpsi[:, 12:20] = math.radians(2.0)  # an arc: one turn of 8 steps
    err = turn_heading_error(_gen(0), dpsi, 0.09, math.radians(0.5))
    assert bool((err[:, dpsi[0] == 0] == 0).all())
    rel_arc = err[:, 12:20] / dpsi[:, 12:20]
    torch.testing.assert_close(rel_arc, rel_arc[:, :1].expand_as(rel_arc))  # constant over the turn
    rel = torch.stack([err[:, 5] / dpsi[:, 5], rel_arc[:, 0]])
    assert float(rel.std()) == pytest.approx(0.09, rel=0.05) and abs(float(rel.mean())) < 0.01
    assert abs(float(torch.corrcoef(rel)[0, 1])) < 0.1  # turns are independent


def test_arc_bursts_cover_the_expected_share_of_the_walk():
    arc = torch.linspace(0.0, 360.0, 515, dtype=f64).expand(2000, 515)
    inside = arc_bursts(_gen(1), arc, 0.01, (5.0, 20.0))
    # Poisson bursts of mean length 12.5 m at 0.01 per m: coverage 1 - exp(-0.125) away from the start
    assert float(inside[:, 100:].double().mean()) == pytest.approx(1 - math.exp(-0.125), abs=0.01)


def test_simulator_disturbances_have_the_papers_statistics():
    base = simulate_p002(400, seed=3, blockage_prob=0.0)
    turns = simulate_p002(400, seed=3, blockage_prob=0.0, turn_scale_std=0.09)
    true_turn = base.truth[..., 3].diff(dim=1)
    corner = true_turn.abs() > math.radians(45.0)  # the corner nodes of p002's path
    extra = (turns.controls["dtheta"] - base.controls["dtheta"])[..., 0][:, 1:]
    rel = extra[corner] / true_turn[corner]
    assert float(rel.std()) == pytest.approx(0.09, rel=0.1)
    noisy = simulate_p002(400, seed=3, blockage_prob=0.0, interference_burst_rate=0.01)
    err = torch.rad2deg(wrap_angle(noisy.compass_raw - noisy.truth[..., 3]))
    quiet = torch.rad2deg(wrap_angle(base.compass_raw - base.truth[..., 3]))
    changed = (err - quiet).abs() > 1e-9
    assert 0.05 < float(changed.double().mean()) < 0.2
    # inside a burst the compass error is p002's interference level (49.7 deg RMSE; wrapping trims the tails)
    assert 40.0 < float(err[changed].pow(2).mean().sqrt()) < 55.0
    assert float(quiet.pow(2).mean().sqrt()) == pytest.approx(11.4, rel=0.1)


def test_gps_availability_follows_fixes_and_blockage():
    times = torch.arange(0.0, 200.0, 0.5, dtype=f64).expand(300, -1)
    cold = torch.full((300,), 5.0, dtype=f64)
    ok, blocked = gps_availability(_gen(2), times, cold, torch.zeros(300, dtype=f64), gps_interval=1.0, outage_window=5.0)
    assert int(ok[0].sum()) == 195 and not bool(blocked.any())  # one fix per second from 5 s on
    ok, blocked = gps_availability(_gen(2), times, cold, torch.full((300,), 0.4, dtype=f64), gps_interval=1.0, outage_window=5.0)
    assert float(blocked.double().mean()) == pytest.approx(0.4, abs=0.02)
    assert not bool((ok & blocked).any())


def test_infamily_walks_come_from_the_filters_model():
    model = pdr_model(Q_std=[0.06, 0.06, 0.01, 0.5], R_std=[1.888, 1.888, 11.4])
    truth = {"R": [7.1289, 7.1289, math.radians(5.0) ** 2]}
    d = p002_infamily(model=model, batch_size=300, seed=4, true_params=truth, blockage_prob=0.4)
    compass = d.measurements[..., 2] - d.truth[..., 3]
    assert float(torch.rad2deg(compass).std()) == pytest.approx(5.0, rel=0.03)
    gps = (d.measurements[..., :2] - d.truth[..., :2])[d.mask[..., :2]]
    assert float(gps.std()) == pytest.approx(2.67, rel=0.03)
    # dynamics: E_k - E_{k-1} - L_{k-1} sin(theta_{k-1}) is the process noise (0.06 m)
    x = torch.cat([d.initial_state[:, None], d.truth], 1)
    step = x[:, 1:, 0] - x[:, :-1, 0] - x[:, :-1, 2] * torch.sin(x[:, :-1, 3])
    assert float(step.std()) == pytest.approx(0.06, rel=0.03)
    torch.testing.assert_close(d.true_params["measurement.R"].diagonal(), torch.tensor(truth["R"], dtype=f64))
    assert float(d.mask[..., 0].double().mean()) < 0.5 and bool(d.mask[..., 2].all())
    assert float(model.R[0, 0].detach()) == pytest.approx(1.888**2)  # the filter's model is left alone


def test_sweep_table_arranges_the_summary(tmp_path):
    head = ["group", "filter", "quantity", "estimate", "lo", "hi", "seeds", "runs", "reference"]
    rows = [
        ["filter=p002_rcukf scenario=p002_pdr test=P=0.8", "hand-tuned", "rmse_pos", "3.0", "2.5", "3.5", "1", "50", ""],
        ["filter=p002_rcukf scenario=p002_pdr test=P=0.8", "learned", "rmse_pos", "2.0", "1.8", "2.2", "5", "50", ""],
        ["filter=p002_rcukf scenario=p002_pdr test=P=0.8", "learned", "diff", "-1.0", "-1.2", "-0.8", "5", "50", ""],
        ["filter=p002_rcukf scenario=p002_pdr test=P=0.8", "learned", "diff_pct", "-33", "-40", "-26", "5", "50", ""],
        ["filter=p002_ukf scenario=p002_pdr test=P=0.8", "hand-tuned", "rmse_pos", "2.9", "2.4", "3.4", "1", "50", ""],
        ["filter=p002_rcukf scenario=p002_pdr test=P=0.05", "GPS only", "rmse_pos", "2.7", "2.6", "2.8", "1", "50", ""],
    ]
    with (tmp_path / "summary.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        w.writerows(rows)
    text = sweep_table(tmp_path)
    assert "### scenario=p002_pdr" in text and "| P=0.8 | P=0.05 |" in text
    assert "| RC-UKF learned | 2 [1.8, 2.2] | - |" in text
    assert "| RC-UKF hand-tuned | 3 [2.5, 3.5] [6.78] | - [1.94] |" in text
    assert "| UKF hand-tuned | 2.9 [2.4, 3.4] [7.38] |" in text and "| GPS only | - [12.17] | 2.7 [2.6, 2.8] [2.67] |" in text
    assert "| RC-UKF learned - RC-UKF hand-tuned | -1 [-1.2, -0.8]; -33 [-40, -26] % |" in text


def test_sweep_table_of_one_sweep_per_filter(tmp_path):
    """Single-filter sweeps keep filter= and scenario= only in summary.md's "Overrides of every job" line."""
    head = ["group", "filter", "quantity", "estimate", "lo", "hi", "seeds", "runs", "reference"]
    for name, filt, hand in (("rc", "p002_rcukf", "3.0"), ("ukf", "p002_ukf", "2.9")):
        d = tmp_path / name
        d.mkdir()
        with (d / "summary.csv").open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(head)
            w.writerow(["test=P=0.8", "hand-tuned", "rmse_pos", hand, "2.4", "3.5", "1", "50", ""])
            w.writerow(["test=P=0.8", "learned", "rmse_pos", "2.0", "1.8", "2.2", "5", "50", ""])
        (d / "summary.md").write_text(
            "# Sweep summary\n\nOverrides of every job: "
            f"`experiment=p002_pdr filter={filt} learn=[Q,R] scenario=p002_pdr ~experiment.hand_tuned.rho=null`.\n"
        )
    text = sweep_table([tmp_path / "rc", tmp_path / "ukf"])
    assert "### scenario=p002_pdr" in text
    assert "| RC-UKF hand-tuned | 3 [2.4, 3.5] [6.78] |" in text and "| UKF hand-tuned | 2.9 [2.4, 3.5] [7.38] |" in text
    assert "| UKF learned | 2 [1.8, 2.2] |" in text and "| RC-UKF learned | 2 [1.8, 2.2] |" in text
    # the command line: several directories, then an optional metric
    assert main([str(tmp_path / "rc"), str(tmp_path / "ukf")]) == text


def test_between_sweeps_pairs_seeds_and_runs(tmp_path):
    """learned of one sweep - learned of another on the same seeds and test runs: the crossed interval of the differences."""
    vals = {"a": [[1.0, 2.0, 3.0], [1.5, 2.5, 2.0]], "b": [[2.0, 2.0, 4.0], [2.5, 3.0, 3.5]]}
    for name, seeds in vals.items():
        for s, runs in enumerate(seeds):
            job = tmp_path / name / str(s)
            (job / ".hydra").mkdir(parents=True)
            (job / ".hydra" / "overrides.yaml").write_text(f"- seed={s}\n")
            rows = "".join(f"learned,{r},{v}\n" for r, v in enumerate(runs))
            (job / "per_run.csv").write_text("filter,run,rmse_pos\n" + rows)
    text = between_sweeps(tmp_path / "a", tmp_path / "b")
    ref = crossed_interval(torch.tensor(vals["a"], dtype=torch.float64) - torch.tensor(vals["b"], dtype=torch.float64))
    assert f"| main | {ref.estimate:.3g} [{ref.lo:.3g}, {ref.hi:.3g}] |" in text
    (tmp_path / "b" / "1" / "per_run.csv").write_text("filter,run,rmse_pos\nlearned,0,1.0\n")
    with pytest.raises(ValueError, match="different test runs"):
        between_sweeps(tmp_path / "a", tmp_path / "b")
