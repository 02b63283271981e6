"""High-precision reference filters for linear-Gaussian models (mpmath, optional dependency).

Independent of the filters under test: plain textbook recursions written with ``mpmath``
matrices at a chosen number of decimal digits (80 by default), so that rounding plays no part
at any dynamic range float64 can hold (a prior covariance of ``1e24`` against a measurement
noise of ``1e-8`` spans 32 orders of magnitude).  Used by the reliability tests and
``experiments/reliability_sweep.py``.

* :func:`exact_kalman`: the Kalman filter (predict, then update; the covariance update in the
  form ``P - K S K^T``, exact at this precision).
* :func:`exact_fading_kalman`: p002's residual-constrained fading factor (scalar) on top of it,
  the linear-Gaussian case of :class:`~difffilter.filters.RCUKF`.
* :func:`exact_imm`: the textbook IMM (Bar-Shalom) of linear Kalman modes.
* :func:`exact_colored_posteriors`: filtering posteriors of a linear model with AR(1)
  measurement noise (stationary start), by conditioning the dense joint Gaussian.

Every function takes float64 numpy arrays and returns float64 numpy arrays ``means [T, n]``,
``covs [T, n, n]``, ``log_likelihoods [T]`` (rounded once, at the end).
"""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence

import numpy as np

__all__ = [
    "exact_colored_posteriors",
    "exact_fading_kalman",
    "exact_imm",
    "exact_kalman",
    "mpmath_available",
    "cv_scenario",
    "relative_errors",
    "simulate_linear",
]


def mpmath_available() -> str | None:
    """``None`` if mpmath imports, else why not."""
    return None if importlib.util.find_spec("mpmath") is not None else "mpmath is not installed (pip install mpmath)"


def _mp():  # type: ignore[no-untyped-def]
    import mpmath  # optional dependency: imported where used

    return mpmath


def _m(a: np.ndarray):  # type: ignore[no-untyped-def]
    mp = _mp()
    a = np.atleast_2d(np.asarray(a, dtype=np.float64))
    return mp.matrix([[mp.mpf(float(v)) for v in row] for row in a])


def _v(a: np.ndarray):  # type: ignore[no-untyped-def]
    mp = _mp()
    return mp.matrix([mp.mpf(float(v)) for v in np.asarray(a, dtype=np.float64).ravel()])


def _np(a) -> np.ndarray:  # type: ignore[no-untyped-def]
    return np.array([[float(a[i, j]) for j in range(a.cols)] for i in range(a.rows)])


def _np_vec(a) -> np.ndarray:  # type: ignore[no-untyped-def]
    return np.array([float(a[i]) for i in range(a.rows)])


def _logpdf(e, s):  # type: ignore[no-untyped-def]
    """``log N(e; 0, S)`` at full precision."""
    mp = _mp()
    m = e.rows
    sol = mp.lu_solve(s, e)
    maha = sum(e[i] * sol[i] for i in range(m))
    return -(maha + mp.log(mp.det(s)) + m * mp.log(2 * mp.pi)) / 2


def _sym(a):  # type: ignore[no-untyped-def]
    return (a + a.T) / 2


def _kf_update(x, p, z, h, r):  # type: ignore[no-untyped-def]
    mp = _mp()
    s = h * p * h.T + r
    pht = p * h.T
    gain = pht * mp.inverse(s)
    e = z - h * x
    return x + gain * e, _sym(p - gain * s * gain.T), _logpdf(e, s), s, pht, e


def _kalman_run(F, H, Q, R, m0, P0, z, *, rho: float | None, dps: int):  # type: ignore[no-untyped-def]  # noqa: N803
    mp = _mp()
    with mp.workdps(dps):
        f, h, q, r = _m(F), _m(H), _m(Q), _m(R)
        x, p = _v(m0), _m(P0)
        m = h.rows
        c0 = mp.zeros(m, m)
        means, covs, lls = [], [], []
        for t in range(z.shape[0]):
            x = f * x
            spread = _sym(f * p * f.T)
            p = spread + q
            if rho is not None:
                eps = _v(z[t]) - h * x
                c0 = (mp.mpf(rho) * c0 + eps * eps.T) / (1 + mp.mpf(rho))
                num = sum((c0 - r)[i, i] for i in range(m))
                den = sum((h * p * h.T)[i, i] for i in range(m))
                p = _sym(p + (max(mp.mpf(1), num / den) - 1) * spread)
            x, p, ll, *_ = _kf_update(x, p, _v(z[t]), h, r)
            means.append(_np_vec(x))
            covs.append(_np(p))
            lls.append(float(ll))
    return np.array(means), np.array(covs), np.array(lls)


def exact_kalman(
    F: np.ndarray, H: np.ndarray, Q: np.ndarray, R: np.ndarray, m0: np.ndarray, P0: np.ndarray, z: np.ndarray, *, dps: int = 80
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kalman filter of one trajectory ``z [T, m]`` from the belief ``(m0, P0)`` before the first
    measurement; returns posterior ``means [T, n]``, ``covs [T, n, n]`` and ``log_likelihoods [T]``."""
    return _kalman_run(F, H, Q, R, m0, P0, z, rho=None, dps=dps)


def exact_fading_kalman(
    F: np.ndarray,
    H: np.ndarray,
    Q: np.ndarray,
    R: np.ndarray,
    m0: np.ndarray,
    P0: np.ndarray,
    z: np.ndarray,
    *,
    rho: float,
    dps: int = 80,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """p002's fading Kalman filter (scalar factor, no cap) on a linear model, at full precision.

    ``S = F P F^T``, ``P- = S + Q``; ``eps = z - H x-``; ``C0 = (rho C0 + eps eps^T)/(1 + rho)``
    (``C0 = 0`` before the first step); ``eta = max(1, tr(C0 - R) / tr(H P- H^T))``;
    ``P-_faded = P- + (eta - 1) S``; then the Kalman update from ``(x-, P-_faded)``.
    """
    return _kalman_run(F, H, Q, R, m0, P0, z, rho=rho, dps=dps)


def cv_scenario(q: float = 1.0, r: float = 1e-8) -> dict[str, np.ndarray]:
    """The reliability scenario's model: 2-D constant velocity ``[px, vx, py, vy]``, ``dt = 1``,
    white-noise-acceleration ``Q`` of intensity ``q``, both positions measured with ``R = r I``."""
    f1 = np.array([[1.0, 1.0], [0.0, 1.0]])
    q1 = q * np.array([[1.0 / 3.0, 0.5], [0.5, 1.0]])
    return {"F": np.kron(np.eye(2), f1), "Q": np.kron(np.eye(2), q1), "H": np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]]), "R": r * np.eye(2)}


def simulate_linear(mats: dict[str, np.ndarray], steps: int, seed: int = 0) -> np.ndarray:
    """Measurements ``[T, m]`` of one seeded trajectory of a linear model (start ``[10, 1, -5, 0.5]``)."""
    rng = np.random.default_rng(seed)
    x = np.array([10.0, 1.0, -5.0, 0.5])
    lq = np.linalg.cholesky(mats["Q"])
    lr = np.linalg.cholesky(mats["R"])
    zs = []
    for _ in range(steps):
        x = mats["F"] @ x + lq @ rng.standard_normal(x.shape[0])
        zs.append(mats["H"] @ x + lr @ rng.standard_normal(mats["H"].shape[0]))
    return np.array(zs)


def exact_imm(
    modes: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    transition: np.ndarray,
    initial_probs: np.ndarray,
    m0: np.ndarray,
    P0: np.ndarray,
    z: np.ndarray,
    *,
    dps: int = 80,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Textbook IMM of linear Kalman modes ``(F, H, Q, R)`` sharing the state, at full precision.

    Mixing with ``Pi[i, j] = P(j | i)``, per-mode predict and update, mode probabilities
    ``w_j ∝ Lambda_j c_j``, combined moments.  Returns combined ``means [T, n]``, ``covs``, the
    log-likelihoods ``log sum_j c_j Lambda_j [T]`` and the mode probabilities ``[T, M]``.
    """
    mp = _mp()
    with mp.workdps(dps):
        mats = [tuple(_m(a) for a in mode) for mode in modes]
        num = len(mats)
        pi = [[mp.mpf(float(transition[i, j])) for j in range(num)] for i in range(num)]
        w = [mp.mpf(float(v)) for v in initial_probs]
        xs = [_v(m0) for _ in range(num)]
        ps = [_m(P0) for _ in range(num)]
        means, covs, lls, probs = [], [], [], []
        for t in range(z.shape[0]):
            c = [sum(pi[i][j] * w[i] for i in range(num)) for j in range(num)]
            new_x, new_p, loglik = [], [], []
            for j, (f, h, q, r) in enumerate(mats):
                mix = [pi[i][j] * w[i] / c[j] for i in range(num)]
                x0 = sum((mix[i] * xs[i] for i in range(1, num)), mix[0] * xs[0])
                p0 = mp.zeros(len(m0), len(m0))
                for i in range(num):
                    d = xs[i] - x0
                    p0 += mix[i] * (ps[i] + d * d.T)
                x, p = f * x0, _sym(f * p0 * f.T + q)
                x, p, ll, *_ = _kf_update(x, p, _v(z[t]), h, r)
                new_x.append(x)
                new_p.append(p)
                loglik.append(ll)
            top = max(loglik)
            lik = [mp.exp(ll - top) * c[j] for j, ll in enumerate(loglik)]
            total = sum(lik)
            w = [v / total for v in lik]
            xs, ps = new_x, new_p
            x = sum((w[j] * xs[j] for j in range(1, num)), w[0] * xs[0])
            p = mp.zeros(len(m0), len(m0))
            for j in range(num):
                d = xs[j] - x
                p += w[j] * (ps[j] + d * d.T)
            means.append(_np_vec(x))
            covs.append(_np(_sym(p)))
            lls.append(float(top + mp.log(total)))
            probs.append([float(v) for v in w])
    return np.array(means), np.array(covs), np.array(lls), np.array(probs)


def exact_colored_posteriors(
    F: np.ndarray,
    H: np.ndarray,
    Q: np.ndarray,
    R: np.ndarray,
    psi: np.ndarray,
    m0: np.ndarray,
    P0: np.ndarray,
    z: np.ndarray,
    *,
    dps: int = 80,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Filtering posteriors ``p(x_t | z_1..z_t)`` of ``x_t = F x_{t-1} + w_t``,
    ``z_t = H x_t + v_t``, ``v_t = diag(psi) v_{t-1} + eta_t`` (``eta ~ N(0, R)``, ``v_1``
    stationary: ``Cov(v_1)_ij = R_ij / (1 - psi_i psi_j)``), by conditioning the dense joint
    Gaussian of ``(x_0, w_1.., v_1, eta_2..)``; the log-likelihoods are the one-step predictive
    log-densities ``log p(z_t | z_1..z_{t-1})``."""
    mp = _mp()
    with mp.workdps(dps):
        f, h, q, r = _m(F), _m(H), _m(Q), _m(R)
        n, m, steps = f.rows, h.rows, z.shape[0]
        ps = [mp.mpf(float(v)) for v in np.broadcast_to(psi, (m,))]
        # Linear maps from the base vector u = [x0 (n), w_1..w_T (n each), v_1 (m), eta_2..eta_T (m each)].
        dim = n + steps * n + steps * m
        base_mean = mp.zeros(dim, 1)
        for i in range(n):
            base_mean[i] = mp.mpf(float(m0[i]))
        base_cov = mp.zeros(dim, dim)
        p0 = _m(P0)
        for i in range(n):
            for j in range(n):
                base_cov[i, j] = p0[i, j]
        for t in range(steps):
            o = n + t * n
            for i in range(n):
                for j in range(n):
                    base_cov[o + i, o + j] = q[i, j]
        ov = n + steps * n
        for i in range(m):
            for j in range(m):
                base_cov[ov + i, ov + j] = r[i, j] / (1 - ps[i] * ps[j])
        for t in range(1, steps):
            o = ov + t * m
            for i in range(m):
                for j in range(m):
                    base_cov[o + i, o + j] = r[i, j]
        x_map = mp.zeros(n, dim)  # x_t as a linear map of u
        v_map = mp.zeros(m, dim)
        for i in range(n):
            x_map[i, i] = 1
        x_rows, z_rows = [], []
        for t in range(steps):
            nxt = f * x_map
            for i in range(n):
                nxt[i, n + t * n + i] += 1
            x_map = nxt
            if t == 0:
                v_map = mp.zeros(m, dim)
                for i in range(m):
                    v_map[i, ov + i] = 1
            else:
                nv = mp.zeros(m, dim)
                for i in range(m):
                    for k in range(dim):
                        nv[i, k] = ps[i] * v_map[i, k]
                    nv[i, ov + t * m + i] += 1
                v_map = nv
            x_rows.append(x_map)
            z_rows.append(h * x_map + v_map)
        means, covs, lls = [], [], []
        for t in range(steps):
            zm = mp.zeros((t + 1) * m, dim)
            for s in range(t + 1):
                for i in range(m):
                    for k in range(dim):
                        zm[s * m + i, k] = z_rows[s][i, k]
            xm = x_rows[t]
            szz = zm * base_cov * zm.T
            sxz = xm * base_cov * zm.T
            zvec = mp.matrix([mp.mpf(float(z[s, i])) for s in range(t + 1) for i in range(m)])
            d = zvec - zm * base_mean
            gain = sxz * mp.inverse(szz)
            mean = xm * base_mean + gain * d
            cov = _sym(xm * base_cov * xm.T - gain * sxz.T)
            # one-step predictive density of z_t given z_1..z_{t-1}
            zt = mp.zeros(m, dim)
            for i in range(m):
                for k in range(dim):
                    zt[i, k] = z_rows[t][i, k]
            if t == 0:
                pm, pc = zt * base_mean, zt * base_cov * zt.T
            else:
                zp = mp.zeros(t * m, dim)
                for s in range(t):
                    for i in range(m):
                        for k in range(dim):
                            zp[s * m + i, k] = z_rows[s][i, k]
                spp = zp * base_cov * zp.T
                stp = zt * base_cov * zp.T
                g2 = stp * mp.inverse(spp)
                dp = mp.matrix([mp.mpf(float(z[s, i])) for s in range(t) for i in range(m)]) - zp * base_mean
                pm = zt * base_mean + g2 * dp
                pc = _sym(zt * base_cov * zt.T - g2 * stp.T)
            e = mp.matrix([mp.mpf(float(z[t, i])) for i in range(m)]) - pm
            means.append(_np_vec(mean))
            covs.append(_np(cov))
            lls.append(float(_logpdf(e, pc)))
    return np.array(means), np.array(covs), np.array(lls)


def relative_errors(
    mean: np.ndarray, cov: np.ndarray, loglik: np.ndarray, ref_mean: np.ndarray, ref_cov: np.ndarray, ref_loglik: np.ndarray
) -> dict[str, float]:
    """Scale-aware relative errors against a reference run (all ``[T, ...]`` float64 arrays).

    ``mean``: ``max |x_i - x*_i| / max(|x*_i|, sd*_i)`` (relative to the value, or to the
    posterior standard deviation where that is larger); ``cov``: ``max |P_ij - P*_ij| /
    sqrt(P*_ii P*_jj)`` (correlation units); ``loglik``: ``max |l - l*| / max(1, |l*|)``;
    ``mean_abs``: the plain maximum absolute mean error.
    """
    sd = np.sqrt(np.clip(np.diagonal(ref_cov, axis1=-2, axis2=-1), 0.0, None))
    mean_rel = np.abs(mean - ref_mean) / np.maximum(np.abs(ref_mean), sd)
    scale = np.sqrt(sd[..., :, None] ** 2 * sd[..., None, :] ** 2)
    cov_rel = np.abs(cov - ref_cov) / scale
    ll_rel = np.abs(loglik - ref_loglik) / np.maximum(1.0, np.abs(ref_loglik))
    return {
        "mean": float(np.nanmax(np.where(np.isfinite(mean_rel), mean_rel, np.inf))),
        "cov": float(np.nanmax(np.where(np.isfinite(cov_rel), cov_rel, np.inf))),
        "loglik": float(np.nanmax(np.where(np.isfinite(ll_rel), ll_rel, np.inf))),
        "mean_abs": float(np.nanmax(np.where(np.isfinite(mean), np.abs(mean - ref_mean), np.inf))),
        "loglik_abs": float(np.nanmax(np.where(np.isfinite(loglik), np.abs(loglik - ref_loglik), np.inf))),
    }
