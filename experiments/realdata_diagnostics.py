"""Training / validation-block diagnostics of the smartLoc real-data protocol (issue 15, v2 design).

Only the train and validation blocks of the folds are filtered here, never a fold's test block
(the two folds share the validation block; fold A's train block is fold B's test block and vice
versa, so a continuous run over one fold's non-test part repeats the other fold's test numbers of
the fixed baselines, which were public before v2).

    python experiments/realdata_diagnostics.py                       # windows, burn-in, continuous non-test runs, gate sweep
    python experiments/realdata_diagnostics.py --pilot 20            # + v2 pilot: 1 seed per fold x variant, validation scores only
"""

from __future__ import annotations

import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import argparse  # noqa: E402
import copy  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from difffilter.evaluate.metrics import nll_per_step  # noqa: E402
from difffilter.learn.data import TrajectorySet  # noqa: E402
from experiments.holdout import contiguous_blocks  # noqa: E402
from experiments.papers.smartloc.protocol import block_sets, cached_drives, fold_coefficients, hand_tuned_filter, train_jobs  # noqa: E402
from experiments.papers.smartloc.report import _baselines, resolve_config  # noqa: E402

GATES = [(2.5, 8.0), (3.0, 8.0), (3.5, 8.0), (3.72, 8.0), (4.0, 8.0), (4.5, 8.0), (5.0, 8.0), (4.2, 16.0), (2.5, 16.0), (1e6, 8.0)]


def _stats(e: torch.Tensor) -> str:
    return f"{float(e.median()):5.1f} + {float(e.pow(2).mean().sqrt()):5.1f}"


def _config(name: str) -> dict:
    with initialize_config_dir(config_dir=str(Path(__file__).resolve().parents[1] / "conf"), version_base="1.3"):
        c = compose("realdata", overrides=[f"realdata={name}"])
    return resolve_config(OmegaConf.to_container(c.realdata, resolve=True))  # type: ignore[arg-type]


def main() -> None:
    """Print the diagnostics (median + RMS of the horizontal error, m; innovation NLL per step)."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--pilot", type=int, default=0, help="epochs of the v2 validation-only pilot (0: none)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cfg, drives = cached_drives(json.dumps(_config("smartloc"), sort_keys=True))
    n = drives[0].data.num_epochs
    hand, nog = hand_tuned_filter(cfg, drives), _baselines(drives[0], cfg)["ekf-no-gate"]
    blocks = {f: contiguous_blocks(n, {k: tuple(v) for k, v in cfg["folds"][f].items()}) for f in ("A", "B")}
    windows = {"train A": blocks["A"]["train"], "train B": blocks["B"]["train"], "validation": blocks["A"]["val"]}
    sets = {k: block_sets(drives, {0: span}, length=100, stride=25) for k, span in windows.items()}
    print("## 100-epoch windows every 25 epochs (median + RMS, m): all epochs | without the first 25 | without the first 50")
    for k, s in sets.items():
        for name, filt in (("hand-tuned", hand), ("no gate", nog)):
            e = torch.cat([_errors(filt, x) for x in s]).reshape(-1, 100)
            print(f"{k:10s} {name:10s} {_stats(e)} | {_stats(e[:, 25:])} | {_stats(e[:, 50:])}")
    print("## each fold's non-test part run continuously from one snapshot fix")
    for f in ("A", "B"):
        b = blocks[f]
        span = (min(b["train"][0], b["val"][0]), max(b["train"][1], b["val"][1]))
        cont = block_sets(drives, {0: span})
        for name, filt in (("hand-tuned", hand), ("no gate", nog)):
            e = _errors(filt, cont[0])
            tr, va = e[b["train"][0] - span[0] : b["train"][1] - span[0]], e[b["val"][0] - span[0] : b["val"][1] - span[0]]
            print(f"fold {f} {span} {name:10s} train part {_stats(tr)} | validation part {_stats(va)}")
    print("## hard gate (threshold sigma, floor m) at the hand-tuned values: innovation NLL per step, error")
    for thr, floor in GATES:
        c = copy.deepcopy(cfg)
        c["gate"]["threshold"], c["gate"]["floor"] = thr, floor
        filt = hand_tuned_filter(c, drives)
        row = []
        for k, s in sets.items():
            with torch.no_grad():
                res = filt(s[0].measurements, s[0].initial_mean, s[0].initial_cov, mask=s[0].mask, controls=s[0].controls)
            e = (res.mean[..., :2] - s[0].truth[..., :2]).norm(dim=-1)
            row.append(f"{k}: NLL {float(nll_per_step(res).mean()):6.2f}, {_stats(e)}")
        print(f"gate {thr:g} / {floor:g}: " + " | ".join(row))
    print("## what the innovation NLL of the hand-tuned filter is made of (windows)")
    meas = hand.model.measurement
    for k, s in sets.items():
        print(f"{k}: " + _nll_shares(hand, meas, s[0]))
    if args.pilot:
        v2 = resolve_config(_config("smartloc_v2"))
        v2, drives2 = cached_drives(json.dumps(v2, sort_keys=True))
        jobs = [
            {"cfg": v2, "fold": f, "variant": v, "seed": 0, "epochs": args.pilot, "log_dir": "/tmp/realdata_pilot"}
            | {"coefficients": fold_coefficients(v2, drives2, f, v).tolist()}
            for f in ("A", "B")
            for v in v2["variants"]
        ]
        print("## v2 pilot (seed 0): validation score (median + RMS) per epoch")
        for r in train_jobs(jobs, workers=2):
            print(r["fold"], r["variant"], " ".join(f"{s:.1f}" for s in r["scores"]))


def _nll_shares(filt: torch.nn.Module, meas: torch.nn.Module, s: TrajectorySet) -> str:
    """Rejected ranges (inflated variance at the prior mean), the share of the NLL that their
    constant ``ln(1e6) / 2`` terms make up, and the share held by the worst 10 % of epochs."""
    with torch.no_grad():
        res = filt(s.measurements, s.initial_mean, s.initial_cov, mask=s.mask, controls=s.controls)
        b, t = res.prior_mean.shape[:2]
        u = {k: v.reshape(b * t, *v.shape[2:]) for k, v in s.controls.items()}
        r = torch.diagonal(meas.measurement_noise(res.prior_mean.reshape(b * t, -1), u), dim1=-2, dim2=-1)
        used = s.mask.reshape(b * t, -1)
        rejected = (r > 10.0 * u["pr_var"].to(r.dtype)) & used
    nll = -res.log_likelihood.reshape(-1)
    total, n_rej, n = float(nll.sum()), int(rejected.sum()), int(used.sum())
    worst = float(nll.sort(descending=True).values[: nll.numel() // 10].sum()) / total
    return (
        f"{n} ranges, {n_rej / n:.1%} rejected; their ln(1e6)/2 terms {n_rej * math.log(1e6) / 2 / total:.1%} of the NLL; "
        f"worst 10 % of epochs {worst:.1%} of the NLL"
    )


def _errors(filt: torch.nn.Module, s: TrajectorySet) -> torch.Tensor:
    with torch.no_grad():
        res = filt(s.measurements, s.initial_mean, s.initial_cov, mask=s.mask, controls=s.controls)
    return (res.mean[..., :2] - s.truth[..., :2]).norm(dim=-1).reshape(-1)


if __name__ == "__main__":
    main()
