"""Independent references for the smoother tests: the dense joint Gaussian of a linear-Gaussian
window (numpy, float64), conditioned on its observed measurements."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def dense_smoother(
    z: np.ndarray,
    m0: np.ndarray,
    P0: np.ndarray,
    F: np.ndarray | Sequence[np.ndarray],
    H: np.ndarray,
    Q: np.ndarray | Sequence[np.ndarray],
    R: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    offsets: np.ndarray | None = None,
    upto: int | None = None,
) -> dict[str, np.ndarray]:
    """Exact posterior of ``[x_{-1}, x_0, ..., x_{T-1}]`` given the observed ``z_0..z_{upto}``.

    ``x_{-1} ~ N(m0, P0)``, ``x_t = F_t x_{t-1} + offsets_t + w_t``, ``w_t ~ N(0, Q_t)``,
    ``z_t = H x_t + v_t``, ``v_t ~ N(0, R)``; ``mask [T, m]`` True = observed (``z`` may hold NaN
    elsewhere).  Returns ``mean [T, n]``, ``cov [T, n, n]``, ``cross [T, n, n]`` (``Cov(x_{t-1},
    x_t | z)``), ``initial_mean``, ``initial_cov`` and the ``log_likelihood`` of the observed z.
    """
    T, m = z.shape
    n = m0.shape[0]
    Fs = [np.asarray(F)] * T if np.ndim(F) == 2 else [np.asarray(f) for f in F]
    Qs = [np.asarray(Q)] * T if np.ndim(Q) == 2 else [np.asarray(q) for q in Q]
    off = np.zeros((T, n)) if offsets is None else offsets
    obs = np.ones((T, m), bool) if mask is None else mask.astype(bool)
    last = T - 1 if upto is None else upto
    # prior moments of X = [x_{-1}, x_0, ..., x_{T-1}]
    mus = [m0]
    for t in range(T):
        mus.append(Fs[t] @ mus[-1] + off[t])
    K = T + 1
    cov = [[None] * K for _ in range(K)]
    cov[0][0] = P0
    for t in range(1, K):
        for s in range(t):
            cov[s][t] = cov[s][t - 1] @ Fs[t - 1].T
            cov[t][s] = cov[s][t].T
        cov[t][t] = Fs[t - 1] @ cov[t - 1][t - 1] @ Fs[t - 1].T + Qs[t - 1]
    Sxx = np.block(cov)
    mux = np.concatenate(mus)
    # observed measurement rows: z_t[i] = H[i] x_t + v
    rows, zs, times = [], [], []
    for t in range(last + 1):
        for i in range(m):
            if obs[t, i]:
                sel = np.zeros((1, K * n))
                sel[0, (t + 1) * n : (t + 2) * n] = H[i]
                rows.append(sel)
                zs.append(z[t, i])
                times.append((t, i))
    if rows:
        A = np.concatenate(rows)
        Rz = np.zeros((len(rows), len(rows)))
        for a, (ta, ia) in enumerate(times):
            for b, (tb, ib) in enumerate(times):
                if ta == tb:
                    Rz[a, b] = R[ia, ib]
        Szz = A @ Sxx @ A.T + Rz
        Sxz = Sxx @ A.T
        d = np.array(zs) - A @ mux
        sol = np.linalg.solve(Szz, d)
        post_mu = mux + Sxz @ sol
        post_S = Sxx - Sxz @ np.linalg.solve(Szz, Sxz.T)
        loglik = -0.5 * (d @ sol + np.linalg.slogdet(Szz)[1] + len(d) * np.log(2 * np.pi))
    else:
        post_mu, post_S, loglik = mux, Sxx, 0.0
    blk = lambda a, b: post_S[a * n : (a + 1) * n, b * n : (b + 1) * n]  # noqa: E731
    return {
        "initial_mean": post_mu[:n],
        "initial_cov": blk(0, 0),
        "mean": post_mu[n:].reshape(T, n),
        "cov": np.stack([blk(t + 1, t + 1) for t in range(T)]),
        "cross": np.stack([blk(t, t + 1) for t in range(T)]),
        "log_likelihood": loglik,
    }
