"""Issue 25's data-efficiency and transfer summaries (experiments/efficiency_transfer.py), their
table renderer, and the overlays of results/p00_efficiency_transfer.md.

The summaries are checked on synthetic sweeps against differences computed here by hand; the
overlays against their families (each transfer target's test set is the same simulator as the
source's extra test set)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from experiments.efficiency_transfer import Pair, best_baseline, summarize_efficiency, summarize_transfer
from experiments.results_tables import check_text, read_rows, render_text

ROOT = Path(__file__).resolve().parents[1]


def _job(root: Path, overrides: list[str], per_run: dict[str, list[float]], cpu: dict[str, float], extra: dict | None = None) -> None:
    """A finished job of ``experiments/train.py``: overrides, per_run.csv, results.csv (and extra test sets)."""
    (root / ".hydra").mkdir(parents=True)
    (root / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    (root / ".hydra" / "config.yaml").write_text("experiment:\n  test_name: own\n")
    for directory, values in [(root, per_run), *((root / "extra_tests" / k, v) for k, v in (extra or {}).items())]:
        directory.mkdir(parents=True, exist_ok=True)
        with (directory / "per_run.csv").open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["filter", "run", "rmse_pos"])
            w.writerows([name, r, v] for name, vals in values.items() for r, v in enumerate(vals))
        with (directory / "results.csv").open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["filter", "rmse_pos", "tuning_cpu_s"])
            w.writerows([name, 0.0, cpu.get(name, "nan")] for name in values)


def _pick(rows, group, name, qty, ref=""):
    return next(r for r in rows if (r.group, r.filter, r.quantity, r.reference) == (group, name, qty, ref))


def test_best_baseline_leaves_out_learned_and_truth_rows():
    mats = {n: torch.full((2, 3), v) for n, v in [("hand-tuned", 3.0), ("oracle", 0.5), ("learned", 1.0), ("exact UKF", 0.7), ("em", 2.0)]}
    assert best_baseline(mats) == "em"
    assert best_baseline(mats, exclude=("em",)) == "hand-tuned"


def test_efficiency_pairs_learned_and_em_with_the_best_other_baseline(tmp_path):
    gen = torch.Generator().manual_seed(1)
    runs, seeds = 7, 3
    hand = (2.0 + torch.rand(runs, generator=gen, dtype=torch.float64)).tolist()
    data = {}
    for size in (1, 4):
        for s in range(seeds):
            em = [h - 0.3 + 0.01 * s - 0.05 * size for h in hand]  # the best baseline; depends on the seed
            search = [h - 0.2 for h in hand]  # the best of the others
            learned = [h - 0.2 * size + 0.02 * r for r, h in enumerate(hand)]
            per_run = {"hand-tuned": hand, "learned": learned, "oracle": [h - 1.5 for h in hand], "em": em, "validation-search": search}
            data[(size, s)] = per_run
            cpu = {"learned": 10.0 * size + s, "em": 1.0}
            _job(tmp_path / f"{size}_{s}", [f"data.train_size={size}", f"seed={s}", "experiment=x"], per_run, cpu)
    rows = read_rows(summarize_efficiency(tmp_path, tmp_path / "eff.csv"))
    assert sorted({r.group for r in rows}) == ["N=1", "N=4"]
    for size in (1, 4):
        g = f"N={size}"
        learned = torch.tensor([data[(size, s)]["learned"] for s in range(seeds)], dtype=torch.float64)
        em = torch.tensor([data[(size, s)]["em"] for s in range(seeds)], dtype=torch.float64)
        search = torch.tensor([data[(size, s)]["validation-search"] for s in range(seeds)], dtype=torch.float64)
        want = float((learned - em).mean() / em.mean() * 100)
        assert _pick(rows, g, "learned", "diff_pct", "em").estimate == pytest.approx(want, rel=1e-9)
        assert _pick(rows, g, "em", "diff", "validation-search").estimate == pytest.approx(float((em - search).mean()), rel=1e-9)
        assert _pick(rows, g, "learned", "tuning_cpu_s").estimate == pytest.approx(10.0 * size + 1.0)
        hand_row = _pick(rows, g, "hand-tuned", "rmse_pos")
        assert hand_row.seeds == "1" and hand_row.estimate == pytest.approx(sum(data[(size, 0)]["hand-tuned"]) / runs)
    # learned - em = 0.3 - 0.15 size + 0.02 r - 0.01 s: a loss at N=1, a win at N=4
    assert _pick(rows, "N=1", "learned", "diff_pct", "em").lo > 0
    assert _pick(rows, "N=4", "learned", "diff_pct", "em").hi < 0


def test_efficiency_leaves_out_a_size_with_fewer_seeds(tmp_path):
    for size, seeds in ((1, 3), (4, 1)):
        for s in range(seeds):
            per_run = {"hand-tuned": [1.0, 2.0, 3.0], "learned": [0.5, 1.5, 2.0 + 0.1 * s]}
            _job(tmp_path / f"{size}_{s}", [f"data.train_size={size}", f"seed={s}"], per_run, {})
    rows = read_rows(summarize_efficiency(tmp_path, tmp_path / "eff.csv"))
    assert {r.group for r in rows} == {"N=1"}


def _transfer_sweeps(tmp_path: Path, shift: float = 0.0) -> tuple[dict, dict]:
    runs, seeds = 6, 3
    hand = [2.0 + 0.1 * r for r in range(runs)]
    src, tgt = {}, {}
    for s in range(seeds):
        own_src = {"hand-tuned": [h + 1.0 for h in hand], "learned": [h - 0.5 for h in hand]}
        on_target = {"hand-tuned": [h + shift for h in hand], "learned": [h - 0.2 - 0.01 * s for h in hand], "em": [h - 0.1 for h in hand]}
        own_tgt = {"hand-tuned": hand, "learned": [h - 0.4 + 0.01 * r for r, h in enumerate(hand)], "sage-husa": [h - 0.3 for h in hand]}
        _job(tmp_path / "a" / str(s), [f"seed={s}", "data.train_size=16"], own_src, {}, extra={"b-test": on_target})
        _job(tmp_path / "b" / str(s), [f"seed={s}"], own_tgt, {}, extra={"a-test": own_src})
        src[s], tgt[s] = on_target, own_tgt
    return src, tgt


def _transfer_rows(tmp_path: Path) -> tuple[list, dict, dict]:
    """The a -> b pair's summary rows over :func:`_transfer_sweeps`, and the sweeps' per-run
    values stacked ``[seeds, runs]`` (``src``: the source model on the target's test set)."""
    src, tgt = _transfer_sweeps(tmp_path)
    pair = Pair("a->b", "a", ("data.train_size=16", "test=b-test"), "b", ("test=own",))
    rows = read_rows(summarize_transfer(tmp_path, tmp_path / "t.csv", pairs=[pair]))

    def stack(values: dict) -> dict:
        return {k: torch.tensor([values[s][k] for s in sorted(values)], dtype=torch.float64) for k in values[0]}

    return rows, stack(src), stack(tgt)


def test_transfer_pairs_the_source_model_with_the_targets_rows(tmp_path):
    rows, src, tgt = _transfer_rows(tmp_path)
    moved, own, best = src["learned"], tgt["learned"], tgt["sage-husa"]
    got = _pick(rows, "a->b", "learned on a", "diff", "learned on target")
    assert got.estimate == pytest.approx(float((moved - own).mean()), rel=1e-9)
    assert _pick(rows, "a->b", "learned on a", "diff_pct", "sage-husa (target)").estimate == pytest.approx(
        float((moved - best).mean() / best.mean() * 100), rel=1e-9
    )
    assert _pick(rows, "a->b", "em (a)", "rmse_pos").estimate == pytest.approx(float(src["em"][0].mean()))


def test_transfer_refuses_sweeps_tested_on_different_runs(tmp_path):
    _transfer_sweeps(tmp_path, shift=1e-3)
    pair = Pair("a->b", "a", ("data.train_size=16", "test=b-test"), "b", ("test=own",))
    with pytest.raises(ValueError, match="not tested on the same runs"):
        summarize_transfer(tmp_path, tmp_path / "t.csv", pairs=[pair])


def test_paired_tables_render_and_check(tmp_path):
    runs = 8
    hand = [1.0 + 0.05 * r for r in range(runs)]
    for s in range(2):
        per_run = {"hand-tuned": hand, "learned": [h - 0.3 + 0.01 * s for h in hand], "em": [h + 0.1 for h in hand]}
        _job(tmp_path / "sweep" / str(s), [f"seed={s}", "data.train_size=4"], per_run, {"learned": 3.0})
    summarize_efficiency(tmp_path / "sweep", tmp_path / "data.csv")
    text = "x\n<!-- table: t renderer=paired group_title=size source=data.csv -->\n<!-- /table -->\n"
    rendered = render_text(text, tmp_path)
    assert check_text(rendered, tmp_path) == []
    line = next(ln for ln in rendered.splitlines() if ln.startswith("| N=4 | learned |"))
    assert "| 3 |" in line and "| hand-tuned |" in line and line.endswith("| win |")
    assert check_text(rendered.replace("| win |", "| tie |"), tmp_path)  # a changed cell is caught


def _compose(experiment: str) -> dict:
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"experiment={experiment}"])
    out = {"experiment": OmegaConf.to_container(cfg.experiment, resolve=False), "train_size": cfg.data.train_size}
    out["test"] = OmegaConf.to_container(cfg.data.test_simulator, resolve=True)
    extra = cfg.experiment.extra_tests or {}
    out["extra"] = {k: None if v is None else OmegaConf.to_container(v, resolve=True) for k, v in extra.items()}
    return out


def test_transfer_targets_are_tested_on_the_sources_extra_test_sets():
    pdr, disturbed, infamily = (_compose(e) for e in ("p002_pdr_efficiency", "p002_disturbed_transfer", "p002_infamily_transfer"))
    assert pdr["extra"]["disturbed-P0.4"] == disturbed["test"]
    assert pdr["extra"]["in-family"] == infamily["test"]
    assert disturbed["extra"]["pdr-P0.4"] == pdr["test"] == infamily["extra"]["pdr-P0.4"]
    assert pdr["test"]["blockage_prob"] == disturbed["test"]["blockage_prob"] == infamily["test"]["blockage_prob"] == 0.4
    assert disturbed["train_size"] == infamily["train_size"] == 16
    for cfg in (pdr, disturbed):  # the base family's other blockage levels are dropped
        assert all(v is None for k, v in cfg["extra"].items() if k.startswith("P="))


def test_efficiency_overlay_only_adds_baselines():
    base, new = _compose("p000_infamily"), _compose("p000_infamily_efficiency")
    added = new["experiment"].pop("baselines")
    assert new["experiment"].pop("name") == "p000_infamily_efficiency"
    base["experiment"].pop("baselines"), base["experiment"].pop("name")
    assert new == base
    assert added["em"]["tune"] == {"method": "em", "learn": ["R"], "num_iters": 20}
    assert "validation-search" in added and added["validation-search"]["tune"]["method"] == "grid"


def test_collect_copies_the_summaries_into_results_data(tmp_path):
    from experiments.efficiency_transfer import DATA_FILES
    from experiments.results_report import collect

    for s in range(2):
        _job(tmp_path / "sweep" / str(s), [f"seed={s}", "data.train_size=1"], {"hand-tuned": [1.0, 2.0], "learned": [0.5, 1.5]}, {})
    source, data = DATA_FILES[0]
    (tmp_path / "results" / "data").mkdir(parents=True)
    summarize_efficiency(tmp_path / "sweep", tmp_path / source)
    assert collect(tmp_path) == [tmp_path / source]
    assert (tmp_path / data).read_text() == (tmp_path / source).read_text()


def test_transfer_gives_the_targets_own_verdict_too(tmp_path):
    rows, _, tgt = _transfer_rows(tmp_path)
    own, best = tgt["learned"], tgt["sage-husa"]
    got = _pick(rows, "a->b", "learned on target", "diff", "sage-husa (target)")
    assert got.estimate == pytest.approx(float((own - best).mean()), rel=1e-9)
