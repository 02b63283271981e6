"""Accuracy of every filter against an 80-digit reference over the prior's dynamic range.

    python experiments/reliability_sweep.py                            # the README table (P0 = s I sweep)
    python experiments/reliability_sweep.py 'scales=[1e24]' all=true  # every filter at one scale

Options in conf/reliability_sweep.yaml (a Hydra app like every entry point).

Model: 2-D constant velocity ``[px, vx, py, vy]``, ``dt = 1``, white-noise-acceleration
``Q`` with intensity ``q``, both positions measured with ``R = r I`` (default ``r = 1e-8``,
``sigma_z = 1e-4``), ``T`` steps of one simulated trajectory (seeded), prior ``N(0, s I)``.
The reference is :mod:`experiments.benchmarks.exact` (mpmath, 80 digits) on the same rounded
inputs (float32 runs: the float32-rounded model and data).

Printed per filter, dtype and ``s``: the maximum absolute error of the posterior mean (the
issue's measure), and the scale-aware relative errors of the mean, the covariance and the step
log-likelihood (:func:`experiments.benchmarks.exact.relative_errors`); ``nan`` when the filter's
output is not finite.
"""

from __future__ import annotations

import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from difffilter.filters import EKF, RCUKF, UKF, ColoredNoiseUKF, KalmanFilter, SimplifiedUKF, SquareRootUKF  # noqa: E402
from difffilter.mixers import IMM, Blend  # noqa: E402
from difffilter.models import LinearModel  # noqa: E402
from experiments.benchmarks.exact import (  # noqa: E402
    cv_scenario,
    exact_colored_posteriors,
    exact_fading_kalman,
    exact_imm,
    exact_kalman,
    relative_errors,
    simulate_linear,
)

FILTERS = ("kf", "kf_nojoseph", "ekf", "ukf", "sukf", "srukf", "rcukf", "colored0", "colored", "imm", "blend")


def build(name: str, mats: dict[str, torch.Tensor]):  # type: ignore[no-untyped-def]
    model = LinearModel(**mats)
    if name == "kf":
        return KalmanFilter(model)
    if name == "kf_nojoseph":
        return KalmanFilter(model, joseph=False)
    if name == "ekf":
        return EKF(model)
    if name == "ukf":
        return UKF(model)
    if name == "sukf":
        return SimplifiedUKF(model)
    if name == "srukf":
        return SquareRootUKF(model)
    if name == "rcukf":
        return RCUKF(model, rho=0.95)
    if name == "colored0":
        return ColoredNoiseUKF(model, psi=0.0)
    if name == "colored":
        return ColoredNoiseUKF(model, psi=0.5)
    if name == "imm":
        other = LinearModel(**{**mats, "Q": 10.0 * mats["Q"]})
        pi = torch.tensor([[0.95, 0.05], [0.1, 0.9]], dtype=mats["F"].dtype)
        return IMM([KalmanFilter(model), KalmanFilter(other)], transition=pi, initial_probs=torch.tensor([0.5, 0.5], dtype=pi.dtype))
    if name == "blend":
        return Blend(EKF(model), UKF(LinearModel(**mats)), delta=0.85)
    raise ValueError(name)


def reference(name: str, mats: dict[str, np.ndarray], m0: np.ndarray, P0: np.ndarray, z: np.ndarray):  # type: ignore[no-untyped-def]
    F, H, Q, R = mats["F"], mats["H"], mats["Q"], mats["R"]
    if name == "rcukf":
        return exact_fading_kalman(F, H, Q, R, m0, P0, z, rho=0.95)
    if name == "colored":
        return exact_colored_posteriors(F, H, Q, R, np.full(2, 0.5), m0, P0, z)
    if name == "imm":
        pi = np.array([[0.95, 0.05], [0.1, 0.9]])
        return exact_imm([(F, H, Q, R), (F, H, 10.0 * Q, R)], pi, np.array([0.5, 0.5]), m0, P0, z)[:3]
    return exact_kalman(F, H, Q, R, m0, P0, z)


def run_case(name: str, scale: float, dtype: torch.dtype, *, q: float, r: float, steps: int, seed: int) -> dict[str, float]:
    mats64 = cv_scenario(q, r)
    z64 = simulate_linear(mats64, steps, seed)
    # the reference sees exactly the inputs the filter sees (rounded to its dtype)
    tmats = {k: torch.tensor(v, dtype=dtype) for k, v in mats64.items()}
    mats = {k: v.double().numpy() for k, v in tmats.items()}
    zt = torch.tensor(z64, dtype=dtype)[None]
    z = zt[0].double().numpy()
    m0 = np.zeros(4)
    P0 = scale * np.eye(4)
    P0t = torch.tensor(P0, dtype=dtype)
    ref_mean, ref_cov, ref_ll = reference(name, mats, m0, P0t.double().numpy(), z)
    flt = build(name, tmats)
    with torch.no_grad():
        try:
            res = flt(zt, torch.zeros(4, dtype=dtype), P0t)
        except Exception as exc:  # noqa: BLE001 - the sweep reports failures, it does not stop on them
            return {"error": f"{type(exc).__name__}: {exc}"[:80]}  # type: ignore[dict-item]
    out = relative_errors(
        res.mean[0].double().numpy(), res.cov[0].double().numpy(), res.log_likelihood[0].double().numpy(), ref_mean, ref_cov, ref_ll
    )
    flags = {k: int(v.sum()) for k, v in res.extras.items() if k in ("untrusted", "diffuse")}
    out.update(flags)
    return out


@hydra.main(version_base="1.3", config_path="../conf", config_name="reliability_sweep")
def main(args: DictConfig) -> None:
    """Print the table for the options in ``args`` (conf/reliability_sweep.yaml)."""
    unknown = sorted(set(args.filters) - set(FILTERS))
    if unknown:
        raise ValueError(f"filters: unknown {unknown}; expected names from {list(FILTERS)}")
    torch.set_num_threads(int(args.threads))
    names = FILTERS if args.all else args.filters
    print(f"CV 2-D, q = {args.q:g}, R = {args.r:g} I, T = {args.steps}, seed {args.seed}; errors against the 80-digit reference")
    print("| filter | dtype | P0 = s I | max abs mean error | mean rel | cov rel | loglik rel | loglik abs | flags |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in names:
        for dt in args.dtypes:
            for s in (float(x) for x in args.scales):
                out = run_case(name, s, getattr(torch, dt), q=float(args.q), r=float(args.r), steps=int(args.steps), seed=int(args.seed))
                if "error" in out:
                    print(f"| {name} | {dt} | {s:g} | {out['error']} | | | | | |")
                    continue
                flags = ", ".join(f"{k} {v}" for k, v in out.items() if k in ("untrusted", "diffuse"))
                print(
                    f"| {name} | {dt} | {s:g} | {out['mean_abs']:.2g} | {out['mean']:.2g} | {out['cov']:.2g} | "
                    f"{out['loglik']:.2g} | {out['loglik_abs']:.2g} | {flags} |"
                )


if __name__ == "__main__":
    main()
