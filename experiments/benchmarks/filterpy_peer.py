"""filterpy twins of the benchmark filters: one Python loop per trajectory (numpy, float64).

filterpy predicts then updates like difffilter, redraws the UKF's sigma points after the
prediction (``redraw_after_predict=True``) and uses the same scaled sigma-point rule, so the
summed ``log_likelihood`` matches difffilter's total log-likelihood.  It has no batch dimension
and no gradients: the benchmark times a few trajectories and reports trajectory-steps per
second, which does not depend on the batch size.
"""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import torch

from .gpsdr import BenchData, cv_matrices, gpsdr_constants, gpsdr_matrices

__all__ = ["filterpy_available", "run_filterpy"]

_RAD2DEG = 180.0 / math.pi


def filterpy_available() -> str | None:
    """``None`` if filterpy imports, else why not."""
    return None if importlib.util.find_spec("filterpy") is not None else "filterpy is not installed (pip install filterpy)"


def _h(x: np.ndarray, dt: float) -> np.ndarray:
    x = np.asarray(x).ravel()
    ve, ae, vn, an = x[1], x[2], x[4], x[5]
    sp2 = ve * ve + vn * vn
    return np.array([x[0], x[3], _RAD2DEG * (vn * ae - ve * an) / sp2 + x[6], x[7] * dt * math.sqrt(sp2)])


def _h_jac(x: np.ndarray, dt: float) -> np.ndarray:
    x = np.asarray(x).ravel()
    ve, ae, vn, an, psi = x[1], x[2], x[4], x[5], x[7]
    sp2 = ve * ve + vn * vn
    sp = math.sqrt(sp2)
    num = vn * ae - ve * an
    j = np.zeros((4, 8))
    j[0, 0] = j[1, 3] = 1.0
    j[2, 1] = _RAD2DEG * (-an / sp2 - 2.0 * ve * num / sp2**2)
    j[2, 2] = _RAD2DEG * vn / sp2
    j[2, 4] = _RAD2DEG * (ae / sp2 - 2.0 * vn * num / sp2**2)
    j[2, 5] = -_RAD2DEG * ve / sp2
    j[2, 6] = 1.0
    j[3, 1], j[3, 4], j[3, 7] = psi * dt * ve / sp, psi * dt * vn / sp, dt * sp
    return j


def _make_ukf(F, Q, R, m0, P0, dt, alpha, beta, kappa):  # noqa: N803
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    pts = MerweScaledSigmaPoints(8, alpha=alpha, beta=beta, kappa=kappa)
    ukf = UnscentedKalmanFilter(dim_x=8, dim_z=4, dt=dt, fx=lambda x, _dt: F @ x, hx=lambda x: _h(x, dt), points=pts)
    ukf.x, ukf.P, ukf.Q, ukf.R = m0.copy(), P0.copy(), Q.copy(), R.copy()
    return ukf


def run_filterpy(
    kind: str,
    data: BenchData,
    *,
    num_trajectories: int,
    steps: int,
    ukf_alpha: float = 1.0,
    ukf_beta: float = 2.0,
    ukf_kappa: float = 0.0,
    imm_q_scales: tuple[float, ...] = (1.0, 10.0),
    imm_transition: np.ndarray | None = None,
    imm_initial_probs: np.ndarray | None = None,
) -> np.ndarray:
    """Total log-likelihood ``[num_trajectories]`` of the first ``steps`` steps, filterpy ``kind``.

    ``kind``: ``kf`` (CV model), ``ekf``, ``ukf`` or ``imm`` (IMM of UKFs whose ``Q`` is scaled
    by ``imm_q_scales``).
    """
    from filterpy.kalman import ExtendedKalmanFilter, IMMEstimator, KalmanFilter

    c = gpsdr_constants()
    dt = c.dt
    out = np.zeros(num_trajectories)
    if kind == "kf":
        f_t, h_t, q_t, r_t = (t.numpy() for t in cv_matrices(c, torch.float64))
        zs = data.cv_measurements.double().numpy()
        m0s, P0 = data.cv_initial_mean.double().numpy(), data.cv_initial_cov.double().numpy()
    else:
        f_t, q_t, r_t = (t.numpy() for t in gpsdr_matrices(c, torch.float64))
        zs = data.measurements.double().numpy()
        m0s, P0 = data.initial_mean.double().numpy(), data.initial_cov.double().numpy()
    for b in range(num_trajectories):
        ll = 0.0
        z = zs[b]
        if kind == "kf":
            kf = KalmanFilter(dim_x=4, dim_z=2)
            kf.x, kf.P, kf.F, kf.H, kf.Q, kf.R = m0s[b].copy(), P0.copy(), f_t, h_t, q_t, r_t
            for t in range(steps):
                kf.predict()
                kf.update(z[t])
                ll += kf.log_likelihood
        elif kind == "ekf":
            ekf = ExtendedKalmanFilter(dim_x=8, dim_z=4)
            ekf.x, ekf.P, ekf.F, ekf.Q, ekf.R = m0s[b].copy(), P0.copy(), f_t, q_t, r_t
            for t in range(steps):
                ekf.predict()
                ekf.update(z[t], HJacobian=_h_jac, Hx=_h, args=(dt,), hx_args=(dt,))
                ll += ekf.log_likelihood
        elif kind == "ukf":
            ukf = _make_ukf(f_t, q_t, r_t, m0s[b], P0, dt, ukf_alpha, ukf_beta, ukf_kappa)
            for t in range(steps):
                ukf.predict()
                ukf.update(z[t])
                ll += ukf.log_likelihood
        elif kind == "imm":
            filters = [_make_ukf(f_t, s * q_t, r_t, m0s[b], P0, dt, ukf_alpha, ukf_beta, ukf_kappa) for s in imm_q_scales]
            k = len(filters)
            trans = (
                np.full((k, k), 0.05 / max(k - 1, 1)) + np.eye(k) * (0.95 - 0.05 / max(k - 1, 1))
                if imm_transition is None
                else imm_transition
            )
            mu0 = np.full(k, 1.0 / k) if imm_initial_probs is None else imm_initial_probs
            imm = IMMEstimator(filters, mu0.copy(), trans)
            for t in range(steps):
                imm.predict()
                cbar = imm.cbar.copy()
                imm.update(z[t])
                ll += math.log(float(np.sum(cbar * imm.likelihood)))
        else:
            raise ValueError(f"unknown filterpy kind {kind!r}")
        out[b] = ll
    return out
