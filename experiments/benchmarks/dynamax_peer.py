"""dynamax (JAX) twins of the benchmark filters: ``jax.jit(jax.vmap(...))`` over trajectories.

dynamax conditions on ``y_0`` *before* its first prediction, and its ``initial_mean`` is the
prior of the first state; difffilter predicts first.  The benchmark dynamics are linear, so the
exact first prior ``(F m0, F P0 F^T + Q)`` is handed to dynamax and both libraries compute the
same log-likelihood (dynamax's UKF ``alpha, beta, kappa`` follow the same scaled-set rule
``lambda = alpha^2 (n + kappa) - n`` as :class:`~difffilter.filters.MerweScaled`).

Forward calls return dynamax's default posterior (filtered and predicted means/covariances plus
the marginal log-likelihood), the counterpart of difffilter's ``FilterResult``;
training calls are ``jax.value_and_grad`` of the summed marginal log-likelihood w.r.t.
``log diag R`` (``Q`` fixed), difffilter's training step.  float64 runs enable
``jax_enable_x64``; float32 runs disable it so that no constant silently promotes the
computation to float64.
"""

from __future__ import annotations

import importlib.util
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from .gpsdr import BenchData, cv_matrices, gpsdr_constants, gpsdr_matrices

__all__ = ["DynamaxRun", "dynamax_available", "prepare_dynamax"]

_RAD2DEG = 180.0 / math.pi


def dynamax_available() -> str | None:
    """``None`` if dynamax and jax import, else the reason they do not."""
    for mod in ("jax", "dynamax"):
        if importlib.util.find_spec(mod) is None:
            return f"{mod} is not installed (pip install dynamax jax)"
    return None


@dataclass
class DynamaxRun:
    """A compiled dynamax computation: ``run()`` executes it once and blocks until done."""

    run: Callable[[], Any]
    compile_s: float
    loglik: Callable[[], np.ndarray]


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


def prepare_dynamax(
    kind: str,
    data: BenchData,
    dtype: torch.dtype,
    mode: str,
    *,
    ukf_alpha: float,
    ukf_beta: float,
    ukf_kappa: float,
    smoother: bool = False,
) -> DynamaxRun:
    """Build and compile the dynamax ``kind`` (``kf``, ``ekf``, ``ukf``) run on ``data``.

    ``mode`` is ``"forward"`` or ``"train"`` (value and gradient w.r.t. ``log diag R``).
    ``smoother``: dynamax's smoother of the filter (``lgssm_smoother``,
    ``extended_kalman_smoother``, ``unscented_kalman_smoother``), the twin of the smoother
    benchmark (:mod:`.smoothers`): its training loss is the position mean squared error of the
    smoothed means against the truth.
    """
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", dtype == torch.float64)
    jdt = jnp.float64 if dtype == torch.float64 else jnp.float32
    c = gpsdr_constants()

    if kind == "kf":
        from dynamax.linear_gaussian_ssm.inference import (
            ParamsLGSSM,
            ParamsLGSSMDynamics,
            ParamsLGSSMEmissions,
            ParamsLGSSMInitial,
            lgssm_filter,
            lgssm_smoother,
        )

        f_t, h_t, q_t, r_t = cv_matrices(c, torch.float64)
        F, H = jnp.asarray(_np(f_t), jdt), jnp.asarray(_np(h_t), jdt)
        Q0, R0 = jnp.asarray(_np(q_t), jdt), jnp.asarray(_np(r_t), jdt)
        n, m = 4, 2
        m0s = jnp.asarray(_np(data.cv_initial_mean), jdt)
        P0 = jnp.asarray(_np(data.cv_initial_cov), jdt)
        zs = jnp.asarray(_np(data.cv_measurements), jdt)

        def single(Q, R, m0, z):  # noqa: N803
            params = ParamsLGSSM(
                initial=ParamsLGSSMInitial(mean=F @ m0, cov=F @ P0 @ F.T + Q),
                dynamics=ParamsLGSSMDynamics(weights=F, bias=jnp.zeros(n, jdt), input_weights=jnp.zeros((n, 0), jdt), cov=Q),
                emissions=ParamsLGSSMEmissions(weights=H, bias=jnp.zeros(m, jdt), input_weights=jnp.zeros((m, 0), jdt), cov=R),
            )
            return (lgssm_smoother if smoother else lgssm_filter)(params, z)

    else:
        from dynamax.nonlinear_gaussian_ssm import (
            ParamsNLGSSM,
            UKFHyperParams,
            extended_kalman_filter,
            extended_kalman_smoother,
            unscented_kalman_filter,
            unscented_kalman_smoother,
        )

        f_t, q_t, r_t = gpsdr_matrices(c, torch.float64)
        F = jnp.asarray(_np(f_t), jdt)
        Q0, R0 = jnp.asarray(_np(q_t), jdt), jnp.asarray(_np(r_t), jdt)
        m0s = jnp.asarray(_np(data.initial_mean), jdt)
        P0 = jnp.asarray(_np(data.initial_cov), jdt)
        zs = jnp.asarray(_np(data.measurements), jdt)
        dt = c.dt

        def f(x):
            return F @ x

        def h(x):
            ve, ae, vn, an = x[1], x[2], x[4], x[5]
            sp2 = ve * ve + vn * vn
            return jnp.stack([x[0], x[3], _RAD2DEG * (vn * ae - ve * an) / sp2 + x[6], x[7] * dt * jnp.sqrt(sp2)])

        hyper = UKFHyperParams(alpha=ukf_alpha, beta=ukf_beta, kappa=ukf_kappa)

        def single(Q, R, m0, z):  # noqa: N803
            params = ParamsNLGSSM(
                initial_mean=F @ m0,
                initial_covariance=F @ P0 @ F.T + Q,
                dynamics_function=f,
                dynamics_covariance=Q,
                emission_function=h,
                emission_covariance=R,
            )
            if kind == "ekf":
                return (extended_kalman_smoother if smoother else extended_kalman_filter)(params, z)
            return (unscented_kalman_smoother if smoother else unscented_kalman_filter)(params, z, hyper)

    batched = jax.vmap(single, in_axes=(None, None, 0, 0))
    if mode == "forward":
        fn = jax.jit(batched)
        args = (Q0, R0, m0s, zs)
    elif mode == "train" and smoother:
        # the smoother benchmark's loss: position mean squared error of the smoothed means
        pos = [0, 2] if kind == "kf" else [0, 3]
        truth = jnp.asarray(_np(data.truth[:, 1:, [0, 3]]), jdt)

        def loss(log_r, m0, z):  # type: ignore[no-untyped-def]
            return jnp.mean((batched(Q0, jnp.diag(jnp.exp(log_r)), m0, z).smoothed_means[..., pos] - truth) ** 2)

        fn = jax.jit(jax.value_and_grad(loss))
        args = (jnp.log(jnp.diag(R0)), m0s, zs)
    elif mode == "train":

        def loss(log_r, m0, z):  # type: ignore[no-untyped-def]
            return batched(Q0, jnp.diag(jnp.exp(log_r)), m0, z).marginal_loglik.sum()

        fn = jax.jit(jax.value_and_grad(loss))
        args = (jnp.log(jnp.diag(R0)), m0s, zs)
    else:
        raise ValueError(f"mode must be 'forward' or 'train', got {mode!r}")
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    compile_s = time.perf_counter() - t0

    def run() -> Any:
        return jax.block_until_ready(compiled(*args))

    ll_fn = jax.jit(lambda Q, R, m0, z: batched(Q, R, m0, z).marginal_loglik)  # noqa: N803

    def loglik() -> np.ndarray:
        return np.asarray(ll_fn(Q0, R0, m0s, zs), dtype=np.float64)

    return DynamaxRun(run=run, compile_s=compile_s, loglik=loglik)
