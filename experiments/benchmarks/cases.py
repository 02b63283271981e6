"""The benchmark's difffilter cases: filters, their inputs, and the timed calls.

A case is a filter and its inputs for one ``(kind, dtype, batch, steps)``.  Built in: ``kf``
(linear constant-velocity model), ``ekf``, ``ukf`` and ``imm`` (two UKFs whose ``Q`` differ)
on the p000 GPS/DR model of :mod:`.gpsdr`.  Other kinds (e.g. a paper's filter bank) are passed
in as :data:`CaseFactory` functions by the entry point, so this package never imports paper
code.

What trains: the measurement noise ``R`` as a diagonal (softplus-parametrised standard
deviations), nothing else: ``Q`` is fixed and the IMM's transition and initial probabilities are
frozen, so every library differentiates w.r.t. the same few numbers (dynamax: ``log diag R``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from difffilter.engines import FusedFilter
from difffilter.filters import EKF, UKF, KalmanFilter, MerweScaled
from difffilter.filters.base import RecursiveFilter
from difffilter.mixers import IMM

from .gpsdr import BenchData, make_cv_model, make_gpsdr_model

__all__ = ["BUILT_IN", "BenchCase", "CaseFactory", "builtin_case", "make_difffilter", "torch_runner"]

BUILT_IN = ("kf", "ekf", "ukf", "imm")


@dataclass
class BenchCase:
    """A filter and its inputs (batch-first)."""

    filter: RecursiveFilter
    measurements: Tensor
    initial_mean: Tensor
    initial_cov: Tensor
    mask: Tensor | None = None
    controls: Any = None

    def run(self, filt: Any) -> Any:
        return filt(self.measurements, self.initial_mean, self.initial_cov, mask=self.mask, controls=self.controls)


#: ``factory(dtype=, batch=, steps=, seed=) -> BenchCase`` for a kind that is not built in
CaseFactory = Callable[..., BenchCase]


def _train_only_r(filt: RecursiveFilter) -> RecursiveFilter:
    for name, p in filt.named_parameters():
        p.requires_grad_(name.endswith("measurement.parametrizations.R.original"))
    return filt


def make_difffilter(kind: str, dtype: torch.dtype, settings: Any) -> RecursiveFilter:
    """The difffilter filter of built-in case ``kind``; only the (diagonal) ``R`` trains."""
    pts = MerweScaled(alpha=settings.ukf_alpha, beta=settings.ukf_beta, kappa=settings.ukf_kappa)
    noise = {"Q_structure": "fixed", "R_structure": "diagonal"}
    if kind == "kf":
        return _train_only_r(KalmanFilter(make_cv_model(dtype=dtype, **noise)))
    if kind == "ekf":
        return _train_only_r(EKF(make_gpsdr_model(dtype=dtype, analytic_jacobian=settings.ekf_analytic_jacobian, **noise)))
    if kind == "ukf":
        return _train_only_r(UKF(make_gpsdr_model(dtype=dtype, **noise), sigma_points=pts, redraw_after_predict=True))
    if kind != "imm":
        raise ValueError(f"unknown built-in benchmark filter {kind!r}, choose from {list(BUILT_IN)}")
    k = len(settings.imm_q_scales)
    off = (1.0 - settings.imm_stay_prob) / max(k - 1, 1)
    trans = torch.full((k, k), off, dtype=dtype) + torch.eye(k, dtype=dtype) * (settings.imm_stay_prob - off)
    modes = [
        UKF(make_gpsdr_model(dtype=dtype, q_scale=q, **noise), sigma_points=pts, redraw_after_predict=True) for q in settings.imm_q_scales
    ]
    imm = IMM(modes, transition=trans, initial_probs=torch.full((k,), 1.0 / k, dtype=dtype), prob_floor=0.0)
    return _train_only_r(imm)


def builtin_case(kind: str, dtype: torch.dtype, data: BenchData, settings: Any) -> BenchCase:
    """Built-in case ``kind`` on ``data`` (already cut to the batch and steps)."""
    filt = make_difffilter(kind, dtype, settings)
    if kind == "kf":
        return BenchCase(filt, data.cv_measurements, data.cv_initial_mean, data.cv_initial_cov)
    return BenchCase(filt, data.measurements, data.initial_mean, data.initial_cov)


def torch_runner(
    case: BenchCase, mode: str, *, fused: bool = False, threads: int = 1, engine: str = "auto", runner: Any = None
) -> Callable[[], np.ndarray]:
    """The timed call: ``forward`` (no gradient) or ``train`` (total log-likelihood and its
    gradient w.r.t. the trained parameters); returns the per-trajectory log-likelihood.

    ``runner``: the module to call (e.g. the ``.runner`` of an earlier call, so that a warm-up
    builds the kernels of the very wrapper that is timed); default ``case.filter``, or a new
    :class:`FusedFilter` of it when ``fused``."""
    if runner is not None:
        filt: Any = runner
    else:
        filt = FusedFilter(case.filter, engine=engine, threads=threads) if fused else case.filter
    params = [p for p in case.filter.parameters() if p.requires_grad]

    def forward() -> np.ndarray:
        with torch.no_grad():
            return case.run(filt).log_likelihood.sum(-1).double().numpy()

    def train() -> np.ndarray:
        for p in params:
            p.grad = None
        ll = case.run(filt).log_likelihood.sum(-1)
        (-ll.sum()).backward()
        return ll.detach().double().numpy()

    if mode not in ("forward", "train"):
        raise ValueError(f"mode must be 'forward' or 'train', got {mode!r}")
    call = forward if mode == "forward" else train
    call.runner = filt  # type: ignore[attr-defined]  # lets the caller see which engine ran
    return call
