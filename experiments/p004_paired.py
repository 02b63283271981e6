"""Paired Monte-Carlo comparison of a p004_blend run's learned filter with the hand-tuned one.

    python experiments/p004_paired.py outputs/p004_full_v2
    python experiments/p004_paired.py outputs/p004_full_v2 --no-initial-error \
        --model sigma_accel_bias_walk=1e-5 sigma_gyro_bias_walk=1e-6 sigma_position_step=0.0288675
                                     # the settings before issue 7's fixes (Q_pp = sigma_a^2 T^4/3)

Rebuilds p004's test set (the fixed 400 s drive, ``data.test_size`` runs, the data module's test
seed) and the blend filter with the hand-tuned values and with the learned values of the run's
checkpoint, and prints per filter: RMSE of the position, the paired difference of the per-run
mean squared position error (learned - hand-tuned) with its Monte-Carlo standard error, ANEES
over all 8 states with a 95 % interval over runs (per-run means are independent; the steps of
one run are not, which the chi-square band of results.md assumes), and NEES per state block.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from difffilter.learn.selection import assign_parameters  # noqa: E402
from difffilter.learn.support_p004 import blend_filter, p004_simulator  # noqa: E402
from difffilter.models.gnss_imu import GnssImuModel  # noqa: E402

BLOCKS = {"position": [0, 1], "velocity": [2, 3], "heading": [4], "accel_bias": [5, 6], "gyro_bias": [7]}


def _blend(delta: float, options: dict[str, float]) -> torch.nn.Module:
    model = GnssImuModel(planar=True, dtype=torch.float64, **options)
    return blend_filter(model=model, delta=delta).to(torch.float64)


def _option(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    try:
        return name, float(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{name}: not a number: {value!r}") from exc


def _per_run(filt: torch.nn.Module, data: object) -> dict[str, torch.Tensor]:
    with torch.no_grad():
        res = filt(data.measurements, data.initial_mean, data.initial_cov, mask=data.mask, controls=data.controls)
    err = res.mean - data.truth
    out = {"mse_pos": err[..., :2].pow(2).sum(-1).mean(-1)}
    for name, idx in {**BLOCKS, "all": list(range(8))}.items():
        e = err[..., idx]
        cov = res.cov[..., idx, :][..., :, idx]
        out[f"nees_{name}"] = (e[..., None, :] @ torch.linalg.solve(cov, e[..., None]))[..., 0, 0].mean(-1)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--runs", type=int, default=None, help="test runs (default: the run's data.test_size)")
    parser.add_argument("--model", type=_option, nargs="*", default=[], help="GnssImuModel overrides NAME=VALUE (both filters)")
    parser.add_argument("--no-initial-error", action="store_true", help="initial belief mean = truth (the old simulator)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cfg = OmegaConf.load(args.run_dir / ".hydra" / "config.yaml")
    ckpts = sorted((args.run_dir / "checkpoints").glob("*.ckpt"))
    if not ckpts:
        raise FileNotFoundError(f"no checkpoint under {args.run_dir / 'checkpoints'}")
    runs = int(args.runs or cfg.data.test_size)
    if runs < 2:
        raise ValueError(f"--runs must be at least 2, got {runs}")
    test = cfg.data.test_simulator
    data = p004_simulator(
        batch_size=runs,
        seed=int(cfg.data.seeds.test),
        dtype=torch.float64,
        randomize=bool(test.randomize),
        planar=bool(test.planar),
        gnss_outages=[tuple(w) for w in (test.gnss_outages or [])],
        initial_heading_std_deg=test.initial_heading_std_deg,
        initial_error=not args.no_initial_error,
    )
    options = dict(args.model)
    hand = _blend(float(cfg.filter.delta), options)
    assign_parameters(hand, OmegaConf.to_container(cfg.experiment.hand_tuned, resolve=True))
    learned = _blend(float(cfg.filter.delta), options)
    state = torch.load(ckpts[-1], map_location="cpu", weights_only=False)["state_dict"]
    learned_state = {k.removeprefix("filter."): v for k, v in state.items() if k.startswith("filter.")}
    # values overridden by --model stay as given (they are not learned in p004_blend)
    keep = [n.removeprefix("sigma_") for n in options]
    learned_state = {k: v for k, v in learned_state.items() if not any(n in k for n in keep)}
    learned.load_state_dict({**learned.state_dict(), **learned_state})
    print(f"{args.run_dir}: {runs} runs, checkpoint {ckpts[-1].name}")
    rows = {"hand-tuned": _per_run(hand, data), "learned": _per_run(learned, data)}
    for name, r in rows.items():
        nees = r["nees_all"]
        ci = 1.96 * float(nees.std()) / math.sqrt(runs)
        blocks = " ".join(f"{b} {float(r[f'nees_{b}'].mean()):.3f}/{len(i)}" for b, i in BLOCKS.items())
        rmse = math.sqrt(float(r["mse_pos"].mean()))
        print(f"{name:10s} rmse_pos {rmse:.5f} m  ANEES {float(nees.mean()):.3f} +- {ci:.3f} (95 % over runs)  {blocks}")
    d = rows["learned"]["mse_pos"] - rows["hand-tuned"]["mse_pos"]
    base = float(rows["hand-tuned"]["mse_pos"].mean())
    rel, se = 50.0 * float(d.mean()) / base, 50.0 * float(d.std()) / math.sqrt(runs) / base
    print(f"paired: learned - hand-tuned RMSE {rel:+.4f} % +- {se:.4f} % (1 s.e.; {int((d < 0).sum())}/{runs} runs better)")


if __name__ == "__main__":
    main()
