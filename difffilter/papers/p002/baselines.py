"""Experiment support for p002 (GPS + PDR, RC-UKF): model builder, non-filter baselines, sweep table.

* :func:`pdr_model` builds p002's :class:`~difffilter.models.pdr.PDRModel` from standard
  deviations a config can write (metres and degrees).
* :class:`EstimatorBaseline` is the generic hook that lets an estimator which is *not* a Gaussian
  filter (a function of the whole measurement record) appear as a baseline row of
  :func:`difffilter.learn.experiment.run_experiment`: it is a :class:`GaussianFilter` whose
  ``forward`` calls ``estimator(measurements=, mask=, controls=, initial_mean=, initial_cov=)
  -> (mean [B, T, n], variance [B, T, n])``.  The result's ``log_likelihood`` and ``nis`` are
  NaN (such estimators have no innovation model), so the ``nll``/``nis`` columns read ``nan``;
  ``rmse`` columns are exact, and ``anees`` refers to the estimator's own *nominal* variance.
* :func:`gps_only_estimate` / :func:`pdr_only_estimate` wrap p002's "GPS only" and "PDR only" rows
  (:func:`~difffilter.sim.p002_pdr.gps_only_positions`, :func:`~difffilter.sim.p002_pdr.pdr_only_positions`).
* :func:`sweep_table` collects a ``-m scenario.blockage_prob=...`` multirun into one markdown table
  next to p002's published numbers (``python -m difffilter.learn.support_p002 <multirun dir>``).
"""

from __future__ import annotations

import csv
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from types import SimpleNamespace

import torch
from torch import Tensor

from ..filters.base import Belief, FilterResult, GaussianFilter
from ..models.base import Controls, StateSpaceModel
from ..models.pdr import PDRModel
from ..sim.p002_pdr import gps_only_positions, pdr_only_positions
from ..sim.sampling import as_dtype

__all__ = ["PAPER_RMSE", "EstimatorBaseline", "gps_only_estimate", "pdr_model", "pdr_only_estimate", "sweep_table"]

#: p002's position RMSE table (m), by row and outage probability P.
PAPER_RMSE: dict[str, dict[float, float]] = {
    "GPS only": {0.8: 12.17, 0.6: 9.42, 0.4: 5.83, 0.2: 2.88, 0.05: 2.67},
    "PDR only": {0.8: 8.31, 0.6: 7.98, 0.4: 8.16, 0.2: 8.23, 0.05: 7.96},
    "UKF": {0.8: 7.38, 0.6: 7.19, 0.4: 4.46, 0.2: 3.97, 0.05: 2.41},
    "RC-UKF": {0.8: 6.78, 0.6: 6.42, 0.4: 3.12, 0.2: 2.60, 0.05: 1.94},
}

Estimator = Callable[..., tuple[Tensor, Tensor]]


def pdr_model(
    *,
    Q_std: Sequence[float],
    R_std: Sequence[float],
    Q_structure: str = "diagonal",
    R_structure: str = "diagonal",
    dtype: torch.dtype | str = "float64",
) -> PDRModel:
    """p002's PDR model from standard deviations.

    Args:
        Q_std: per-step process noise ``[E m, N m, L m, theta deg]``.
        R_std: ``[GPS east m, GPS north m, compass deg]``.
        Q_structure, R_structure: learnable structure (``"diagonal"``...).
        dtype: ``"float64"`` or a torch dtype.
    """
    dt = as_dtype(dtype)
    q = torch.as_tensor(list(Q_std), dtype=dt).clone()
    r = torch.as_tensor(list(R_std), dtype=dt).clone()
    if q.shape != (4,) or r.shape != (3,):
        raise ValueError(f"Q_std needs 4 and R_std 3 entries, got {tuple(q.shape)}, {tuple(r.shape)}")
    q[3], r[2] = math.radians(float(q[3])), math.radians(float(r[2]))
    return PDRModel(Q=torch.diag(q * q), R=torch.diag(r * r), Q_structure=Q_structure, R_structure=R_structure, dtype=dt)


class EstimatorBaseline(GaussianFilter):
    """A whole-trajectory estimator presented as a filter, for baseline rows (see the module docstring).

    ``model`` only fixes the state/measurement dimensions and the dtype check; ``estimator`` gets
    the validated inputs (masked measurements zeroed, ``mask [B, T, m]`` or ``None``,
    ``initial_mean [B, n]``, ``initial_cov [B, n, n]``) and returns ``mean [B, T, n]`` and the
    nominal per-component ``variance [B, T, n]``.  Prior = posterior.  No ``belief=`` carry-over
    (it is not a recursive filter).
    """

    def __init__(self, model: StateSpaceModel, *, estimator: Estimator) -> None:
        super().__init__(model)
        if not callable(estimator):
            raise TypeError(f"estimator must be callable, got {type(estimator).__name__}")
        self.estimator = estimator

    def forward(  # type: ignore[override]
        self,
        measurements: Tensor,
        initial_mean: Tensor | None = None,
        initial_cov: Tensor | None = None,
        mask: Tensor | None = None,
        controls: Controls = None,
        *,
        belief: Belief | None = None,
    ) -> FilterResult:
        if belief is not None:
            raise ValueError("EstimatorBaseline works on whole trajectories: belief= is not supported")
        z, mask3, mean0, cov0 = self.check_inputs(measurements, initial_mean, initial_cov, mask, controls)
        if mean0 is None or cov0 is None:
            raise ValueError("initial_mean and initial_cov are required")
        mean, var = self.estimator(measurements=z, mask=mask3, controls=controls, initial_mean=mean0, initial_cov=cov0)
        cov = torch.diag_embed(var)
        bsz, steps = z.shape[:2]
        nan = torch.full((bsz, steps), math.nan, dtype=z.dtype, device=z.device)
        observed = torch.full((bsz, steps), z.shape[-1], device=z.device) if mask3 is None else mask3.sum(-1)
        return FilterResult(
            mean=mean,
            cov=cov,
            prior_mean=mean,
            prior_cov=cov,
            log_likelihood=nan,
            nis=nan,
            num_observed=observed,
            final_belief={"mean": mean[:, -1], "cov": cov[:, -1]},
        )


def _observed_gps(measurements: Tensor, mask: Tensor | None) -> Tensor:
    if mask is None:
        return torch.ones(measurements.shape[:2], dtype=torch.bool, device=measurements.device)
    return mask[..., 0] & mask[..., 1]


def _steps_since_fix(ok: Tensor) -> Tensor:
    """``[B, T]`` steps since the last fix (counted from step -1 before the first one)."""
    steps = ok.shape[1]
    idx = torch.arange(1, steps + 1, device=ok.device).expand_as(ok)
    last = torch.where(ok, idx, torch.zeros_like(idx)).cummax(1).values
    return idx - last


def gps_only_estimate(
    *,
    measurements: Tensor,
    mask: Tensor | None,
    controls: Controls,
    initial_mean: Tensor,
    initial_cov: Tensor,
    gps_std: float = 2.67,
    compass_std_deg: float = 11.4,
) -> tuple[Tensor, Tensor]:
    """p002's "GPS only": the last fix held between fixes (:func:`gps_only_positions`); step length
    held at its initial value, heading = compass.  Nominal variance per axis: ``gps_std^2 +
    (L0 k)^2 / 2`` ``k`` steps after a fix (a walk of unknown direction), the initial variance
    instead of ``gps_std^2`` before the first fix."""
    ok = _observed_gps(measurements, mask)
    initial_cov = initial_cov.expand(ok.shape[0], 4, 4)
    scen = SimpleNamespace(mask=ok[..., None], measurements=measurements, initial_mean=initial_mean)
    pos = gps_only_positions(scen)  # type: ignore[arg-type]
    bsz, steps = ok.shape
    step0 = initial_mean[:, None, 2].expand(bsz, steps)
    k = _steps_since_fix(ok).to(measurements.dtype)
    ever = ok.cummax(1).values
    base = torch.where(ever, torch.full_like(k, gps_std**2), initial_cov[:, None, 0, 0].expand(bsz, steps))
    pvar = base + 0.5 * (step0 * k) ** 2
    heading_var = torch.full_like(k, math.radians(compass_std_deg) ** 2)
    var = torch.stack([pvar, pvar, initial_cov[:, None, 2, 2].expand(bsz, steps), heading_var], -1)
    mean = torch.cat([pos, step0[..., None], measurements[..., 2:3]], -1)
    return mean, var


def pdr_only_estimate(
    *,
    measurements: Tensor,
    mask: Tensor | None,
    controls: Controls,
    initial_mean: Tensor,
    initial_cov: Tensor,
    compass_gain: float = 0.05,
    heading_std_deg: float = 5.0,
    step_scale_std: float = 0.03,
) -> tuple[Tensor, Tensor]:
    """p002's "PDR only": dead reckoning with the accelerometer step lengths and a compass-corrected
    gyro heading (:func:`pdr_only_positions`, gain ``compass_gain``).  Nominal variance per axis
    after a walked distance ``d``: initial variance ``+ ((heading_std d)^2 + (step_scale_std d)^2) / 2``."""
    if not isinstance(controls, dict) or not {"dtheta", "step_length"} <= set(controls):
        raise ValueError("pdr_only_estimate needs controls {'dtheta', 'step_length'} [B, T, 1] (the p002 simulator's)")
    initial_cov = initial_cov.expand(measurements.shape[0], 4, 4)
    scen = SimpleNamespace(controls=controls, measurements=measurements, initial_mean=initial_mean)
    pos, heading = pdr_only_positions(scen, compass_gain=compass_gain)  # type: ignore[arg-type]
    steps = controls["step_length"][..., 0]
    dist = steps.cumsum(1)
    pvar = initial_cov[:, None, 0, 0] + 0.5 * ((math.radians(heading_std_deg) * dist) ** 2 + (step_scale_std * dist) ** 2)
    svar = torch.full_like(dist, step_scale_std**2) * steps**2 + 0.03**2
    var = torch.stack([pvar, pvar, svar, torch.full_like(dist, math.radians(heading_std_deg) ** 2)], -1)
    return torch.cat([pos, steps[..., None], heading[..., None]], -1), var


# --- multirun collection ------------------------------------------------------------------------
_ROW_NAMES = {"hand-tuned": "RC-UKF (hand-tuned)", "learned": "RC-UKF (learned)"}
_PAPER_ROW = {"GPS only": "GPS only", "PDR only": "PDR only", "UKF": "UKF", "RC-UKF (hand-tuned)": "RC-UKF"}


def _blockage_prob(run_dir: Path) -> float | None:
    overrides = run_dir / ".hydra" / "overrides.yaml"
    if overrides.exists():
        for line in overrides.read_text().splitlines():
            if "scenario.blockage_prob=" in line:
                return float(line.split("=", 1)[1].strip().strip("'\""))
    config = run_dir / ".hydra" / "config.yaml"
    if config.exists():
        from omegaconf import OmegaConf

        return float(OmegaConf.load(config).scenario.blockage_prob)
    return None


def sweep_table(multirun_dir: str | Path, column: str = "rmse_pos") -> str:
    """Markdown table ``filter x P`` of ``column`` from every ``results.csv`` below
    ``multirun_dir`` (one sweep job per ``P``), with p002's published RMSE in brackets."""
    table: dict[str, dict[float, float]] = {}
    for csv_path in sorted(Path(multirun_dir).rglob("results.csv")):
        prob = _blockage_prob(csv_path.parent)
        if prob is None:
            continue
        with csv_path.open() as fh:
            for row in csv.DictReader(fh):
                name = _ROW_NAMES.get(row["filter"], row["filter"])
                value = row.get(column, "")
                table.setdefault(name, {})[prob] = float(value) if value not in ("", None) else math.nan
    probs = sorted({p for v in table.values() for p in v}, reverse=True)
    head = f"{column} (m) [p002]" if column == "rmse_pos" else column
    lines = [f"| {head} | " + " | ".join(f"P={p:g}" for p in probs) + " |", "|---|" + "---|" * len(probs)]
    for name, vals in table.items():
        paper = PAPER_RMSE.get(_PAPER_ROW.get(name, ""), {})
        cells = []
        for p in probs:
            cell = f"{vals[p]:.3g}" if p in vals else "-"
            if p in paper and column == "rmse_pos":
                cell += f" [{paper[p]:.2f}]"
            cells.append(cell)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":  # pragma: no cover - command-line helper
    for arg in sys.argv[2:] or ["rmse_pos"]:
        print(sweep_table(sys.argv[1], arg))
