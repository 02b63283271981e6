"""Issue 27's battery: extreme-scale numerics on both engines against independent references,
and the batch-isolation matrix.

    python experiments/reliability_battery.py            # everything; writes results/reliability_battery.md

Options in conf/reliability_battery.yaml (``engines``, ``dtypes``, ``isolation``, ``out``).

Scenarios (float64 and float32, the eager filters and ``FusedFilter(engine="generated")``):

* a measurement 1e10 away from the prediction on the 2-D constant-velocity model;
* ``P0 = Q = 1e-30``, ``R = 1e-20 I`` (float32: ``1e-12``), ``P0 = 1e24 I``, ``Q = R = 1e12``;
* a nearly singular innovation covariance (two sensors of one position, ``R`` 1e-14 / 1e-6 of
  ``P``);
* float32 pseudoranges of an ECEF position (~6e6 m, clock bias and drift; float32 only).

References, none of them the filter under test: the Kalman filter, the IMM and the AR(1)-noise
posteriors in mpmath at 80 digits (:mod:`experiments.benchmarks.exact`) on the same
dtype-rounded inputs; for the nonlinear ECEF case the same filter run in float64 on the same
rounded inputs (the question there is float32 rounding).

A step is *wrong* when a mean component is off the reference by more than ``64 eps s_i +
1e-2 sigma*_i`` (``s_i`` the largest of ``|x*_i|``, the reference prediction ``|x-*_i|`` and the
terms it adds, ``(|F| |x*_(t-1)|)_i``: the rounding of the numbers the step works with) or its
log-likelihood by more than ``2e-2 + 2e-4 |l*|`` nats; a wrong step is
*flagged* when ``extras["untrusted"]`` marks it or an earlier step of its trajectory, else
*silent*.  Each case (scenario x filter x dtype x engine) counts once: within tolerance, flagged
(some wrong step, all flagged) or SILENT (some wrong step unflagged); a case whose run raises
counts as an error.  Isolation: the cases of ``experiments/benchmarks/isolation.py``, which
``tests/test_reliability_isolation_matrix.py`` also runs (corrupted trajectory flagged or refused by
name, the others' values and gradients equal to a run without it to 1e-12).
"""

from __future__ import annotations

import functools
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from difffilter.engines import FusedFilter  # noqa: E402
from difffilter.filters import EKF, UKF, ColoredNoiseUKF, KalmanFilter, SimplifiedUKF, SquareRootUKF  # noqa: E402
from difffilter.mixers import IMM  # noqa: E402
from difffilter.models import FunctionalModel, LinearModel  # noqa: E402
from experiments.benchmarks.exact import exact_colored_posteriors, exact_imm, exact_kalman  # noqa: E402
from experiments.benchmarks.isolation import COMPILED, EAGER, check_isolated, make_filter  # noqa: E402

F64 = torch.float64
PI = np.array([[0.9, 0.1], [0.1, 0.9]])
PSI = np.array([0.7, -0.4])
Reference = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # means [B, T, n], covs, logliks [B, T], sizes [B, T, n]


def cv(q: float = 0.3, r: float = 0.8) -> dict[str, np.ndarray]:
    """2-D constant velocity ``[px, vx, py, vy]``, ``dt = 0.5``, both positions measured."""
    dt = 0.5
    f1 = np.array([[1.0, dt], [0.0, 1.0]])
    q1 = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    return {"F": np.kron(np.eye(2), f1), "Q": np.kron(np.eye(2), q1), "H": np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]]), "R": r * np.eye(2)}


class Scenario:
    """A linear-Gaussian case: model matrices, data, prior and the filters that run on it."""

    def __init__(
        self, name: str, mats: dict[str, np.ndarray], z: np.ndarray, p0: np.ndarray, filters: tuple[str, ...], psi: np.ndarray | None = None
    ) -> None:
        self.name, self.mats, self.z, self.p0, self.filters, self.psi = name, mats, z, p0, filters, psi
        # a mean away from zero: sigma points x +- gamma L_i then lose digits to |x| (the case)
        self.m0 = np.array([0.5, 1.0, -1.0, 0.2])[: mats["F"].shape[0]]

    def inputs(self, dtype: torch.dtype) -> dict[str, torch.Tensor]:
        t = {k: torch.tensor(v, dtype=dtype) for k, v in self.mats.items()}
        data = {"z": torch.tensor(self.z, dtype=dtype), "m0": torch.tensor(self.m0, dtype=dtype), "p0": torch.tensor(self.p0, dtype=dtype)}
        return {**t, **data}

    def reference(self, name: str, dtype: torch.dtype) -> Reference:
        """The 80-digit reference on the dtype-rounded inputs."""
        d = {k: v.double().numpy() for k, v in self.inputs(dtype).items()}
        fhqr = (d["F"], d["H"], d["Q"], d["R"])
        runs = []
        for b in range(d["z"].shape[0]):
            if name == "IMM(KF, UKF)":
                runs.append(exact_imm([fhqr, fhqr], PI, np.array([0.5, 0.5]), d["m0"], d["p0"], d["z"][b])[:3])
            elif name == "ColoredNoiseUKF" and self.psi is not None:
                runs.append(exact_colored_posteriors(*fhqr, self.psi, d["m0"], d["p0"], d["z"][b]))
            else:  # ColoredNoiseUKF without psi is the UKF, exact for a linear model
                runs.append(exact_kalman(*fhqr, d["m0"], d["p0"], d["z"][b]))
        means, covs, lls = (np.stack([r[i] for r in runs]) for i in range(3))
        before = np.concatenate([np.broadcast_to(d["m0"], (means.shape[0], 1, means.shape[-1])), means[:, :-1]], 1)
        # the sizes of the numbers a step adds: the prediction's terms F_ij x_j and its result
        return means, covs, lls, np.maximum(np.abs(before) @ np.abs(d["F"]).T, np.abs(before @ d["F"].T))

    def build(self, name: str, dtype: torch.dtype) -> torch.nn.Module:
        t = self.inputs(dtype)
        model = LinearModel(F=t["F"], H=t["H"], Q=t["Q"], R=t["R"])
        if name == "IMM(KF, UKF)":
            modes = [KalmanFilter(model), UKF(LinearModel(F=t["F"], H=t["H"], Q=t["Q"], R=t["R"]))]
            return IMM(modes, torch.tensor(PI, dtype=dtype), torch.tensor([0.5, 0.5], dtype=dtype))
        if name == "ColoredNoiseUKF":
            return ColoredNoiseUKF(model, psi=0.0 if self.psi is None else torch.tensor(self.psi, dtype=dtype))
        return {"KalmanFilter": KalmanFilter, "EKF": EKF, "UKF": UKF, "SquareRootUKF": SquareRootUKF, "SimplifiedUKF": SimplifiedUKF}[name](
            model
        )


ALL = ("KalmanFilter", "EKF", "UKF", "SquareRootUKF", "SimplifiedUKF", "IMM(KF, UKF)", "ColoredNoiseUKF")


def scenarios(dtype: torch.dtype) -> list[Scenario]:
    rng = np.random.default_rng(0)
    z = rng.normal(size=(2, 10, 2))
    outlier = z.copy()
    outlier[0, 4, 0] = 1e10
    tiny = cv(q=0.0)
    tiny["Q"] = 1e-30 * np.eye(4)
    tiny_r = cv(r=1e-20 if dtype == F64 else 1e-12)
    huge = cv(q=1e12, r=1e12)
    r = 1e-14 if dtype == F64 else 1e-6
    twin = {
        "F": np.array([[1.0, 1.0], [0.0, 1.0]]),
        "Q": np.array([[1 / 3, 0.5], [0.5, 1.0]]),
        "H": np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]]),
        "R": np.diag([r, r, 1.0]),
    }
    zt = rng.normal(size=(2, 6, 3))
    zt[..., 1] = zt[..., 0] + np.sqrt(r) * rng.normal(size=(2, 6))
    eye = np.eye(4)
    return [
        Scenario("outlier 1e10", cv(), outlier, eye, ALL),
        Scenario("P0 = Q = 1e-30", tiny, z, 1e-30 * eye, ALL, psi=PSI),
        Scenario("tiny R", tiny_r, z, eye, ALL),
        Scenario("P0 = 1e24", cv(), z, 1e24 * eye, ALL),
        Scenario("Q = R = 1e12", huge, 1e6 * z, eye, ALL),
        Scenario("near-singular S", twin, zt, np.eye(2), ("KalmanFilter", "EKF", "UKF", "SquareRootUKF", "SimplifiedUKF")),
    ]


def ecef_case(dtype: torch.dtype, steps: int = 8, seed: int = 0) -> tuple[FunctionalModel, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A receiver at ~6.3e6 m, 8 satellites 2e7 m away, state ``[x, y, z, clock bias, drift]``,
    pseudoranges with sigma 5 m (the model of tests/test_reliability_extremes.py)."""
    rng = np.random.default_rng(seed)
    pos = np.array([4.0e6, 3.0e5, 4.9e6])
    dirs = rng.normal(size=(8, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs[:, 2] = np.abs(dirs[:, 2])
    sats_np = pos + 2.0e7 * dirs
    sats = torch.tensor(sats_np, dtype=dtype)

    def f(x: torch.Tensor) -> torch.Tensor:
        return torch.cat([x[..., :3], (x[..., 3] + x[..., 4])[..., None], x[..., 4:5]], -1)

    def h(x: torch.Tensor) -> torch.Tensor:
        return (sats - x[..., None, :3]).norm(dim=-1) + x[..., 3:4]

    q = torch.diag(torch.tensor([1.0, 1.0, 1.0, 0.1, 0.01], dtype=F64)).to(dtype)
    model = FunctionalModel(f=f, h=h, Q=q, R=25.0 * torch.eye(8, dtype=dtype))
    bias = 100.0 + 0.5 * np.arange(1, steps + 1)
    z = np.stack([np.linalg.norm(sats_np - pos, axis=1) + bias[t] + 5 * rng.normal(size=8) for t in range(steps)])
    m0 = np.concatenate([pos + 10 * rng.normal(size=3), [100.0, 0.5]])
    p0 = torch.diag(torch.tensor([100.0, 100.0, 100.0, 100.0, 1.0], dtype=dtype))
    return model, torch.tensor(z, dtype=dtype)[None], torch.tensor(m0, dtype=dtype), p0


def classify(res: Any, ref: Reference, dtype: torch.dtype) -> str:
    """``"ok"``, ``"flagged"`` or ``"SILENT"`` (module docstring)."""
    mean, ll = res.mean.detach().double().numpy(), res.log_likelihood.detach().double().numpy()
    ref_mean, ref_cov, ref_ll, ref_size = ref
    eps = torch.finfo(dtype).eps
    sigma = np.sqrt(np.clip(np.diagonal(ref_cov, axis1=-2, axis2=-1), 0.0, None))
    with np.errstate(invalid="ignore", over="ignore"):
        size = np.maximum(np.abs(ref_mean), ref_size)
        bad_mean = ~(np.abs(mean - ref_mean) <= 64 * eps * size + 1e-2 * sigma)
        bad_ll = ~(np.abs(ll - ref_ll) <= 2e-2 + 2e-4 * np.abs(ref_ll))
    wrong = bad_mean.any(-1) | bad_ll
    flagged = np.cumsum(res.extras["untrusted"].numpy(), 1) > 0
    if (wrong & ~flagged).any():
        return "SILENT"
    return "flagged" if wrong.any() else "ok"


def run(filt: torch.nn.Module, engine: str, *args: torch.Tensor) -> tuple[Any, str]:
    """The filter's result on ``engine`` and the engine that ran it."""
    if engine == "eager":
        with torch.no_grad():
            return filt(*args), "eager"
    fused = FusedFilter(filt, engine=engine)
    with torch.no_grad():
        out = fused(*args)
    return out, str(fused.last_engine)


Case = tuple[str, str, Callable[[], torch.nn.Module], tuple[torch.Tensor, ...], Callable[[], Reference]]


def linear_cases(dtype: torch.dtype) -> list[Case]:
    """(scenario, filter, build, inputs, reference) of the linear-Gaussian scenarios."""
    cases: list[Case] = []
    for sc in scenarios(dtype):
        t = sc.inputs(dtype)
        for name in sc.filters:
            build = functools.partial(sc.build, name, dtype)
            cases.append((sc.name, name, build, (t["z"], t["m0"], t["p0"]), functools.partial(sc.reference, name, dtype)))
    return cases


def ecef_reference(cls: type, z: torch.Tensor, m0: torch.Tensor, p0: torch.Tensor) -> Reference:
    """The same filter in float64 on the same (float32-rounded) inputs."""
    with torch.no_grad():
        r64 = cls(ecef_case(F64)[0])(z.double(), m0.double(), p0.double())
    before = np.concatenate([m0.double().numpy()[None, None], r64.mean.numpy()[:, :-1]], 1)
    return r64.mean.numpy(), r64.cov.numpy(), r64.log_likelihood.numpy(), np.maximum(np.abs(before), np.abs(r64.prior_mean.numpy()))


def ecef_cases(dtype: torch.dtype) -> list[Case]:
    model, z, m0, p0 = ecef_case(dtype)
    return [
        ("ECEF pseudoranges", cls.__name__, functools.partial(cls, model), (z, m0, p0), functools.partial(ecef_reference, cls, z, m0, p0))
        for cls in (EKF, UKF)
    ]


def numerics(engines: list[str], dtypes: list[torch.dtype], log: Callable[[str], None]) -> list[dict[str, str]]:
    rows = []
    for dtype in dtypes:
        cases = linear_cases(dtype) + (ecef_cases(dtype) if dtype != F64 else [])
        for scenario, name, build, args, reference in cases:
            ref = reference()
            for engine in engines:
                row = {"scenario": scenario, "filter": name, "dtype": str(dtype)[6:], "engine": engine}
                try:
                    res, ran = run(build(), engine, *args)
                    row.update(status=classify(res, ref, dtype), ran=ran)
                except Exception as exc:  # noqa: BLE001 - the battery reports failures, it does not stop on them
                    row.update(status="error", ran=f"{type(exc).__name__}: {exc}"[:90])
                rows.append(row)
                log(f"{scenario:20s} {name:16s} {row['dtype']:8s} {engine:9s} -> {row['status']} ({row['ran']})")
    return rows


def isolation(engines: list[str], log: Callable[[str], None]) -> tuple[int, int, list[str]]:
    """Passed and total cases of the isolation matrix, and the failures."""
    cases = [(k, d, c, "eager") for k, d, c in EAGER] if "eager" in engines else []
    cases += [(k, F64, c, e) for k, c in COMPILED for e in engines if e != "eager"]
    failed = []
    for kind, dtype, corruption, engine in cases:
        filt = make_filter(kind, dtype)
        try:
            check_isolated(filt if engine == "eager" else FusedFilter(filt, engine=engine), dtype, corruption)
        except BaseException as exc:  # noqa: BLE001 - pytest's failure is a BaseException; report it
            if isinstance(exc, KeyboardInterrupt):
                raise
            failed.append(f"{kind} / {str(dtype)[6:]} / {corruption} / {engine}: {type(exc).__name__}: {str(exc)[:80]}")
            log("isolation FAILED " + failed[-1])
    return len(cases) - len(failed), len(cases), failed


def render(rows: list[dict[str, str]], iso: tuple[int, int, list[str]] | None, command: str, seconds: float) -> str:
    counts = Counter(r["status"] for r in rows)
    lines = [
        f"<!-- generated file: {command} -->",
        "# Reliability battery (issue 27)",
        "",
        "Extreme-scale numerics against independent references (80-digit mpmath Kalman / IMM /",
        "AR(1)-noise posteriors; float64 runs for the nonlinear ECEF case), both engines, and the",
        "batch-isolation matrix. Definitions: the docstring of `experiments/reliability_battery.py`.",
        "",
        f"**Numerics: {len(rows)} cases: {counts['ok']} within tolerance, {counts['flagged']} flagged, "
        f"{counts['SILENT']} SILENT wrong, {counts['error']} errors.**",
    ]
    if iso is not None:
        lines.append("")
        lines.append(f"**Isolation: {iso[0]} of {iso[1]} cases isolated.**")
    lines += [
        "",
        f"Run time {seconds:.0f} s.",
        "",
        "| scenario | dtype | engine | within tolerance | flagged | SILENT | errors |",
        "|---|---|---|---|---|---|---|",
    ]
    groups: dict[tuple[str, str, str], Counter[str]] = {}
    for r in rows:
        groups.setdefault((r["scenario"], r["dtype"], r["engine"]), Counter())[r["status"]] += 1
    for (sc, dt, en), c in groups.items():
        lines.append(f"| {sc} | {dt} | {en} | {c['ok']} | {c['flagged']} | {c['SILENT']} | {c['error']} |")
    odd = [r for r in rows if r["status"] in ("SILENT", "error") or (r["engine"] != "eager" and r["ran"] != r["engine"])]
    if odd:
        lines += ["", "Cases to look at (SILENT, errors, engine fallbacks):", ""]
        lines += [f"- {r['scenario']} / {r['filter']} / {r['dtype']} / {r['engine']}: {r['status']} ({r['ran']})" for r in odd]
    if iso is not None and iso[2]:
        lines += ["", "Isolation failures:", ""] + [f"- {f}" for f in iso[2]]
    return "\n".join(lines) + "\n"


@hydra.main(version_base="1.3", config_path="../conf", config_name="reliability_battery")
def main(args: DictConfig) -> None:
    """Run the battery for the options in ``args`` (conf/reliability_battery.yaml)."""
    torch.set_num_threads(int(args.threads))
    start = time.perf_counter()
    engines, dtypes = list(args.engines), [getattr(torch, d) for d in args.dtypes]
    rows = numerics(engines, dtypes, print)
    iso = isolation(engines, print) if args.isolation else None
    overrides = " ".join(sys.argv[1:])
    text = render(rows, iso, f"python experiments/reliability_battery.py {overrides}".strip(), time.perf_counter() - start)
    print(text)
    if args.out:
        Path(args.out).write_text(text)


if __name__ == "__main__":
    main()
