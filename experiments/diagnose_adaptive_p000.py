"""Why Sage-Husa and VB-AKF diverge on p000 (issue 25): a per-step trace on p000_nominal's test drives.

Builds the test set of ``experiment=p000_nominal_practitioners`` (seed 0: p000's scripted drive, 30
runs x 5000 steps) as the experiment does, runs the overlay's wrapped filter (p000's UKF, Julier
kappa -5, update points redrawn) with fixed R (also on the compiled engine, with p000's own UKF
beside it), under Sage-Husa (b) and under VB-AKF (rho), and
prints for each diverging run: the first step where the state covariance P stops being positive
definite, where the adapted R does, where the position error passes 50 m; the smallest eigenvalue
of R and of the unscented measurement spread before that; the gyro variance R[2,2] against the
model's; the estimated and true speed; and how often Sage-Husa's safeguard took its biased form.

    PYTHONPATH=$PWD OMP_NUM_THREADS=1 python experiments/diagnose_adaptive_p000.py [--b 0.98] [--rho 0.98] [--kappa 0]

About 37 s of CPU (1 thread); about 62 s with --kappa.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

# the repository root first, so that `experiments.*` imports when run as a script
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# eager: the trace hooks below must see real tensors, not the compiled engine's traced ones
os.environ["DIFFFILTER_ENGINE"] = "eager"

import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from hydra.utils import instantiate  # noqa: E402

from difffilter import as_dtype  # noqa: E402
from difffilter.filters.adaptive_noise import sage_husa as sage_husa_module  # noqa: E402
from experiments.runner.experiment import _plain, build_filter  # noqa: E402

__all__ = ["main"]

CONF = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "conf")


def _record_moments(filt: Any, log: list[torch.Tensor]) -> None:
    """Record, at every call, the smallest eigenvalue of the unscented spread (H P H^T's analogue),
    its diagonal and the predicted measurement: ``[B, 1 + 2 m]`` per call."""
    orig = filt.measurement_moments

    def wrapped(mean: torch.Tensor, cov: torch.Tensor, u: Any) -> Any:
        mo = orig(mean, cov, u)
        diag = torch.diagonal(mo.spread, dim1=-2, dim2=-1)
        log.append(torch.cat([torch.linalg.eigvalsh(mo.spread)[..., :1], diag, mo.zhat], -1).detach())
        return mo

    filt.measurement_moments = wrapped


def _first(flags: torch.Tensor) -> int | None:
    idx = flags.nonzero().flatten()
    return int(idx[0]) if idx.numel() else None


def trace(name: str, filt: Any, test: Any, model_r: torch.Tensor, calls_per_step: int) -> None:
    spread_log: list[torch.Tensor] = []
    if hasattr(filt, "measurement_moments"):
        _record_moments(filt, spread_log)
    with torch.no_grad():
        res = filt(test.measurements, test.initial_mean, test.initial_cov, mask=test.mask)
    truth = test.truth
    err = (res.mean[..., [0, 3]] - truth[..., [0, 3]]).norm(dim=-1)  # [B, T]
    rmse = err.pow(2).mean(-1).sqrt()
    bad = [int(i) for i in (~torch.isfinite(rmse) | (rmse > 100)).nonzero().flatten()]
    good = rmse[torch.isfinite(rmse) & (rmse <= 100)]
    print(f"\n== {name}: {len(bad)} of {len(rmse)} runs diverge (RMSE > 100 m): {bad}; median RMSE of the others {good.median():.3f} m")
    if not bad:
        return
    p_min = torch.linalg.eigvalsh(torch.nan_to_num(res.cov, nan=0.0, posinf=1e300, neginf=-1e300))[..., 0]
    p_min = torch.where(torch.isfinite(res.cov).all(-1).all(-1), p_min, torch.full_like(p_min, -torch.inf))
    r = getattr(res, "noise_R", None)
    moments = torch.stack(spread_log, 1)[:, ::calls_per_step] if spread_log else None  # [B, T, 1 + 2 m]: at the prior
    spread = None if moments is None else moments[..., 0]
    for i in bad:
        t_p = _first(p_min[i] <= 0)
        t_e = _first(err[i] > 50)
        line = f"run {i:2d}: first P not PD at step {t_p}, first |pos err| > 50 m at step {t_e}"
        t0 = min(t for t in (t_p, t_e) if t is not None)
        if r is not None:
            r_min = torch.linalg.eigvalsh(torch.nan_to_num(r[i], nan=0.0, posinf=1e300, neginf=-1e300))[:, 0]
            line += f", first R not PD at step {_first(r_min <= 0)}"
            line += f"; before step {t0}: min eig R {r_min[:t0].min():.3e}, R[2,2] (gyro) min {r[i, :t0, 2, 2].min():.3e} "
            line += f"(model {model_r[2, 2]:.3e}), at step {t0 - 1} {r[i, t0 - 1, 2, 2]:.3e}, at step {t0} {r[i, t0, 2, 2]:.3e}"
        if spread is not None:
            line += f"; min eig of the spread before step {t0}: {spread[i, :t0].min():.3e} (at step {t0}: {spread[i, t0]:.3e})"
        v_est = res.mean[i, t0 - 1, [1, 4]].norm()
        v_true = truth[i, t0 - 1, [1, 4]].norm()
        line += f"; speed at step {t0 - 1}: estimate {v_est:.2f} m/s, truth {v_true:.2f} m/s; P min eig at {t0 - 1}: {p_min[i, t0 - 1]:.2e}"
        print(line)
        if r is not None and moments is not None and i == bad[0]:
            _window(res, test, r, moments, p_min, i, t0)
    if r is not None and moments is not None:
        m = r.shape[-1]
        ratio = (moments[..., 1 : 1 + m] / torch.diagonal(r, dim1=-2, dim2=-1).roll(1, dims=1)).nan_to_num(nan=0.0)
        med = ratio[:, 1:].median(0).values.median(0).values
        print(f"median over runs and steps of spread_ii / R_ii (held before the step), per component: {[f'{v:.3g}' for v in med.tolist()]}")


def _window(res: Any, test: Any, r: torch.Tensor, moments: torch.Tensor, p_min: torch.Tensor, i: int, t0: int) -> None:
    """Step by step before the failure of run ``i``: speeds, the gyro's innovation and variances."""
    m = r.shape[-1]
    print("   step | speed est (after t-1) / true (m/s) | gyro z - zhat (rad/s) | gyro spread | gyro R held | min eig spread | min eig P")
    for t in range(t0 - 8, t0 + 1):
        v_est, v_true = res.mean[i, t - 1, [1, 4]].norm(), test.truth[i, t, [1, 4]].norm()
        innov = test.measurements[i, t, 2] - moments[i, t, 1 + m + 2]
        print(
            f"   {t:5d} | {v_est:6.2f} / {v_true:5.2f} | {innov: .3e} | {moments[i, t, 3]:.3e} | {r[i, t - 1, 2, 2]:.3e}"
            f" | {moments[i, t, 0]: .3e} | {p_min[i, t]: .2e}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--b", type=float, default=0.98, help="Sage-Husa forgetting factor")
    ap.add_argument("--rho", type=float, default=0.98, help="VB-AKF forgetting factor")
    ap.add_argument("--split", default="test", choices=["test", "train", "val"], help="which drives (train/val: 150 s random drives)")
    ap.add_argument(
        "--kappa",
        type=float,
        default=None,
        help="also run Sage-Husa and VB-AKF around the same UKF with this Julier kappa (0: no negative weight)",
    )
    args = ap.parse_args()
    torch.set_num_threads(1)
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("train", overrides=["experiment=p000_nominal_practitioners", "seed=0"])
    dtype = as_dtype(cfg.dtype)
    test = instantiate(cfg.data, _convert_="all").dataset(args.split)
    params = _plain(cfg.experiment.hand_tuned)
    specs = _plain(cfg.experiment.baselines)
    sh = build_filter(specs["sage-husa"]["filter"], dtype=dtype, params=params, b=args.b)
    vb = build_filter(specs["vb-akf"]["filter"], dtype=dtype, params=params, rho=args.rho)
    model_r = sh.model_r(test.initial_mean, None)[0]
    print(f"p000_nominal {args.split} drives: {tuple(test.measurements.shape)}; model R diag {torch.diagonal(model_r).tolist()}")
    fallbacks: list[torch.Tensor] = []
    orig_pd = sage_husa_module.is_positive_definite

    def counting_pd(a: torch.Tensor, floor: float) -> torch.Tensor:
        ok = orig_pd(a, floor)
        fallbacks.append(~ok)
        return ok

    trace("p000's UKF redrawn, fixed R (the wrapped filter alone)", sh.inner, test, model_r, 1)
    # the same fixed-R filters on the compiled engine (rounding differs): how narrowly they survive
    own = build_filter(cfg.filter, dtype=dtype, params=params)
    os.environ["DIFFFILTER_ENGINE"] = "compiled"
    try:
        trace("compiled engine: p000's UKF redrawn, fixed R", sh.inner, test, model_r, 1)
        trace("compiled engine: p000's own UKF (points not redrawn), fixed R: the hand-tuned row", own, test, model_r, 1)
    finally:
        os.environ["DIFFFILTER_ENGINE"] = "eager"
    sage_husa_module.is_positive_definite = counting_pd  # type: ignore[assignment]
    try:
        trace(f"Sage-Husa b={args.b}", sh, test, model_r, 1)
    finally:
        sage_husa_module.is_positive_definite = orig_pd  # type: ignore[assignment]
    fb = torch.stack(fallbacks, 1)
    print(f"Sage-Husa safeguard: unbiased candidate not PD (biased form used) at {int(fb.sum())} of {fb.numel()} trajectory-steps")
    trace(f"VB-AKF rho={args.rho}", vb, test, model_r, 1 + vb.iterations)
    if args.kappa is not None:
        for name, knob in (("sage-husa", {"b": args.b}), ("vb-akf", {"rho": args.rho})):
            spec = specs[name]["filter"]
            spec["inner"]["sigma_points"]["kappa"] = args.kappa
            filt = build_filter(spec, dtype=dtype, params=params, **knob)
            calls = 1 + getattr(filt, "iterations", 0)
            trace(f"{name} {knob} around the redrawn UKF with Julier kappa {args.kappa}", filt, test, model_r, calls)


if __name__ == "__main__":
    main()
