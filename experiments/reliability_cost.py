"""Cost of the reliability checks in the ordinary regime.

Forward and forward+backward time of the Kalman filter, EKF and UKF on a 2-D constant-velocity
target (B=64, T=200, float64, one thread, best of 5 after one warm-up call).  Run it on two
checkouts and compare: ``PYTHONPATH=<checkout> python experiments/reliability_cost.py`` prints one
JSON line of seconds per filter and mode (options ``batch=``, ``steps=``: conf/reliability_cost.yaml).
"""

from __future__ import annotations

import json

import hydra
import torch
from omegaconf import DictConfig

from difffilter.filters import EKF, UKF, KalmanFilter
from difffilter.models import LinearModel
from experiments.benchmarks.timing import best_of


def _model(dt: float = 0.1) -> LinearModel:
    f1 = torch.tensor([[1.0, dt], [0.0, 1.0]], dtype=torch.float64)
    g1 = torch.tensor([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]], dtype=torch.float64)
    h = torch.zeros(2, 4, dtype=torch.float64)
    h[0, 0] = 1.0
    h[1, 2] = 1.0
    return LinearModel(F=torch.block_diag(f1, f1), H=h, Q=torch.block_diag(g1, g1), R=torch.eye(2, dtype=torch.float64))


def main(batch: int = 64, steps: int = 200) -> dict[str, float]:
    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = _model()
    z = torch.randn(batch, steps, 2, dtype=torch.float64)
    m0 = torch.zeros(batch, 4, dtype=torch.float64)
    p0 = torch.eye(4, dtype=torch.float64).expand(batch, 4, 4)
    out: dict[str, float] = {}
    for name, cls in (("KF", KalmanFilter), ("EKF", EKF), ("UKF", UKF)):
        flt = cls(model)

        def forward(flt: torch.nn.Module = flt) -> None:
            with torch.no_grad():
                flt(z, m0, p0)

        def train(flt: torch.nn.Module = flt) -> None:
            flt(z, m0, p0).log_likelihood.sum().backward()

        out[f"{name}_forward"] = best_of(forward, 5)
        out[f"{name}_train"] = best_of(train, 5)
    return out


@hydra.main(version_base="1.3", config_path="../conf", config_name="reliability_cost")
def cli(cfg: DictConfig) -> None:
    """Print :func:`main`'s timings for ``cfg.batch`` and ``cfg.steps`` as one JSON line."""
    print(json.dumps(main(batch=int(cfg.batch), steps=int(cfg.steps))))


if __name__ == "__main__":
    cli()
