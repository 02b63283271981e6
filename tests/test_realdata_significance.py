"""The smartLoc protocol's significance gate (``selection.significance``, protocol v5): a learned model
replaces the non-learned candidates only when a paired block bootstrap of the validation score says
it is better than every one of them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from experiments.papers.smartloc import significance
from experiments.papers.smartloc.report import run_protocol

ROOT = Path(__file__).resolve().parents[1]
OPTS = {"level": 0.95, "block": 20, "draws": 800, "seed": 0}


def _ar1(n: int, seed: int, scale: float = 3.0) -> torch.Tensor:
    """Positive serially correlated "errors" ``[n]`` (an AR(1) magnitude around 10 m)."""
    gen = torch.Generator().manual_seed(seed)
    e = torch.randn(n, generator=gen, dtype=torch.float64)
    x = torch.zeros(n, dtype=torch.float64)
    for t in range(1, n):
        x[t] = 0.9 * x[t - 1] + e[t]
    return 10.0 + scale * x.abs()


def test_options_are_checked_and_completed() -> None:
    assert significance.significance_options(None) is None
    assert significance.significance_options({"start_candidate": True}) is None
    assert significance.significance_options({"significance": None}) is None
    full = significance.significance_options({"significance": {"level": 0.9}})
    assert full == {"level": 0.9, "block": 50, "draws": 4000, "seed": 0}
    with pytest.raises(ValueError, match=r"selection\.significance: unknown key\(s\) \['blocks'\]"):
        significance.significance_options({"significance": {"blocks": 10}})
    with pytest.raises(ValueError, match=r"selection\.significance\.level must be in \(0, 1\), got 1\.0"):
        significance.significance_options({"significance": {"level": 1.0}})
    with pytest.raises(ValueError, match=r"selection\.significance\.block must be a positive integer"):
        significance.significance_options({"significance": {"block": 0}})


def _lower_median_plus_rms(x: np.ndarray) -> float:
    return float(np.sort(x)[(len(x) - 1) // 2] + np.sqrt((x**2).mean()))


def test_the_weighted_score_equals_the_score_of_the_resampled_series() -> None:
    """Weights = how often each element was drawn: the weighted lower median + RMS equals the plain
    score (torch.median's lower median + RMS) of the explicitly resampled series, draw by draw."""
    x = torch.rand(41, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 20.0
    assert significance.median_plus_rms(x).item() == pytest.approx(float(x.median() + x.pow(2).mean().sqrt()), rel=1e-14)
    w = significance.epoch_weights(torch.arange(41), block=5, draws=30, seed=3)
    got = significance.median_plus_rms(x, w).numpy()
    for d in range(30):
        resampled = np.repeat(x.numpy(), w[d].long().numpy())
        assert len(resampled) == 41
        assert got[d] == pytest.approx(_lower_median_plus_rms(resampled), rel=1e-13)


def test_repeated_epochs_count_once_in_the_resampling() -> None:
    """A series whose every epoch appears four times (overlapping windows) gets exactly the interval
    of the series with each epoch once; resampling the repeated elements as if independent would
    give a narrower one."""
    ref, cand = _ar1(300, 0), _ar1(300, 7) - 1.0
    once = significance.significantly_better(cand, {"r": ref}, OPTS)[1]["r"]
    groups = torch.arange(300).repeat(4)
    four = significance.significantly_better(cand.repeat(4), {"r": ref.repeat(4)}, OPTS, groups)[1]["r"]
    assert four == pytest.approx(once, rel=1e-12)
    naive = significance.significantly_better(cand.repeat(4), {"r": ref.repeat(4)}, OPTS)[1]["r"]
    assert naive[1] - naive[0] < 0.75 * (once[1] - once[0])
    with pytest.raises(ValueError, match="groups must give one epoch per error"):
        significance.significantly_better(cand, {"r": ref}, OPTS, groups)


def test_a_clear_gain_passes_and_noise_does_not() -> None:
    ref = _ar1(600, 0)
    better, iv = significance.significantly_better(ref - 4.0, {"hand-tuned": ref}, OPTS)
    assert better and iv["hand-tuned"][1] < 0.0
    # the same error process with another draw: a difference of scores inside the noise
    other = _ar1(600, 5)
    better, iv = significance.significantly_better(other, {"hand-tuned": ref}, OPTS)
    lo, hi = iv["hand-tuned"]
    assert not better and lo < 0.0 < hi
    # better than one reference but not the other: not adopted
    better, iv = significance.significantly_better(ref - 4.0, {"hand-tuned": ref, "start": ref - 4.5}, OPTS)
    assert not better and iv["hand-tuned"][1] < 0.0 and iv["start"][0] > 0.0
    # a diverged candidate never passes
    bad = ref.clone()
    bad[3] = float("inf")
    assert significance.significantly_better(bad, {"hand-tuned": ref}, OPTS)[0] is False


def test_the_gate_falls_back_to_the_better_non_learned_candidate(monkeypatch) -> None:
    """With the filters replaced by their error series: a passing learned model is kept; otherwise
    the lower-scoring of the hand-tuned filter and the start (the hand-tuned filter on a tie)."""
    monkeypatch.setattr(significance, "horizontal_errors", lambda filt, sets: filt)
    ref = _ar1(600, 0)
    hand = {"hand-tuned": (ref, 93.0)}
    kind, rec = significance.significance_gate(ref - 4.0, hand, ("start", ref + 1.0, 95.0), None, OPTS)
    assert kind == "learned" and rec["passed"] and set(rec["intervals"]) == {"hand-tuned", "start"}
    noise = _ar1(600, 5)
    assert significance.significance_gate(noise, hand, ("start", ref + 1.0, 95.0), None, OPTS)[0] == "hand-tuned"
    assert significance.significance_gate(noise, hand, ("start", ref, 92.0), None, OPTS)[0] == "start"
    assert significance.significance_gate(noise, hand, ("start", ref, 93.0), None, OPTS)[0] == "hand-tuned"
    assert significance.significance_gate(noise, {}, ("start", ref, 93.0), None, OPTS)[0] == "start"
    # a diverged non-learned candidate (infinite validation score) is no reference and no fallback
    inf = float("inf")
    kind, rec = significance.significance_gate(noise, {"hand-tuned": (ref, inf)}, ("start", ref, 95.0), None, OPTS)
    assert kind == "start" and set(rec["intervals"]) == {"start"}
    assert significance.significance_gate(noise, {"hand-tuned": (ref, inf)}, ("start", ref, inf), None, OPTS)[0] == "learned"


def test_the_protocol_refuses_significance_without_the_start_as_a_candidate(tmp_path) -> None:
    cfg = {"selection": {"hand_tuned_candidate": True, "significance": {"level": 0.95}}}
    with pytest.raises(ValueError, match=r"selection\.significance needs selection\.start_candidate: true"):
        run_protocol(cfg, tmp_path)


def test_v5_is_v4_with_the_gate() -> None:
    """conf/realdata/smartloc_v5.yaml changes only the selection: v4's candidates plus the gate."""
    v4 = OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "realdata" / "smartloc_v4.yaml"), resolve=True)
    v5 = OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "realdata" / "smartloc_v5.yaml"), resolve=True)
    assert v5["defaults"] == ["smartloc_v4", "_self_"]
    assert set(v5) - {"defaults"} == {"selection"} and "selection" not in v4
    assert v5["selection"] == {
        "hand_tuned_candidate": True,
        "start_candidate": True,
        "significance": {"level": 0.95, "block": 50, "draws": 4000, "seed": 0},
    }
    assert significance.significance_options(v5["selection"]) == v5["selection"]["significance"]


def test_validation_epochs_follow_the_validation_windows(tmp_path) -> None:
    """The epoch of each validation error: the reference track at those epochs is the validation
    sets' truth, element by element, for overlapping windows and for whole blocks."""
    from experiments.papers.smartloc import protocol

    from .librsf_fixture import HAVE_DATA, write_drive
    from .test_realdata_protocol import _v3_config

    if not HAVE_DATA:
        pytest.skip("the smartLoc excerpt is missing")
    write_drive(tmp_path, "Cut", start=100.0, stop=140.0)
    cfg = _v3_config(tmp_path)
    for vwin in ({"length": 10, "stride": 5}, {"length": None, "stride": None}):
        cfg["val_windows"] = vwin
        _, drives = protocol.cached_drives(json.dumps(cfg, sort_keys=True))
        for fold in cfg["folds"]:
            sets = protocol.fold_data(cfg, drives, fold)["val"]
            ids = significance.validation_epochs(cfg, drives, fold)
            truth = torch.cat([s.truth[..., :2].reshape(-1, 2) for s in sets])
            assert ids.shape[0] == truth.shape[0]
            assert (len(torch.unique(ids)) < ids.numel()) == (vwin["length"] is not None)  # overlapping windows repeat epochs
            torch.testing.assert_close(drives[0].data.truth_enu[ids, :2], truth, rtol=0, atol=0)


@pytest.mark.slow
@pytest.mark.parametrize("passes", [True, False])
def test_v5_end_to_end_uses_the_learned_model_only_when_the_gate_passes(tmp_path, monkeypatch, passes) -> None:
    """v5's wiring on a cut drive: the point-estimate rule is made to pick the learned model (its
    last epoch) and the bootstrap's verdict is forced; the learned row is that learned model when
    the gate passes, else the better non-learned candidate by validation score, and every
    selection records the gate's intervals."""
    from experiments.papers.smartloc import report

    from .librsf_fixture import HAVE_DATA, write_drive
    from .test_realdata_protocol import _v3_config

    if not HAVE_DATA:
        pytest.skip("the smartLoc excerpt is missing")
    monkeypatch.setattr(report, "select_with_fallbacks", lambda learned, **kw: ("learned", 0, len(learned[0]) - 1))
    calls = []

    def verdict(candidate, references, options, groups=None):
        calls.append((candidate.shape, groups.shape, sorted(references)))
        return passes, {name: (-2.0, -1.0) if passes else (-1.0, 1.0) for name in references}

    monkeypatch.setattr(significance, "significantly_better", verdict)
    drives = tmp_path / "drives"
    write_drive(drives, "Cut", start=100.0, stop=140.0)
    cfg = _v3_config(drives)
    cfg["selection"]["significance"] = {"level": 0.95, "block": 10, "draws": 200, "seed": 0}
    summary = run_protocol(cfg, tmp_path / "run", workers=1)
    assert len(calls) == len(summary["folds"]) and all(c[0] == c[1] and c[2] == ["hand-tuned", "start"] for c in calls)
    for fs in summary["folds"].values():
        sel = fs["selection"]["learned-elev_cn0"]
        rec = sel["best_learned"]["significance"]
        assert rec["passed"] is passes and set(rec["intervals"]) == {"hand-tuned", "start"}
        hand = fs["hand_val"]["median"] + fs["hand_val"]["rms"]
        start = fs["val_scores"]["elev_cn0/seedstart"][0]
        if passes:
            assert sel["seed"] == 0 and sel["epoch"] == len(fs["val_scores"]["elev_cn0/seed0"]) - 1
        else:
            assert sel["seed"] == ("start" if start < hand else "hand-tuned")
            assert sel["val_score"] == pytest.approx(min(hand, start))
    json.dumps(summary, default=float)
