"""Plain-numpy references of the adaptive noise-estimating filters, one trajectory at a time,
written from the papers' equations (Sage–Husa; Särkkä & Nummenmaa 2009; Huang et al. 2018;
Mehra 1972 / Mohamed & Schwarz 1999) and the partial-mask rule of the library's docs.

Every reference uses linear dynamics ``x- = F x``, ``P- = F P F^T + Q`` and takes the measurement
through ``mom(x, P) -> (z^, P_xz, spread)``, its moments at ``N(x, P)``: :func:`ekf_moments`
(``h(x)``, ``P H^T``, ``H P H^T``) or :func:`unscented_moments` (scaled sigma points).
Each returns a dict of arrays ``mean [T, n]``, ``cov [T, n, n]``, ``ll [T]``, ``R [T, m, m]``
(and ``Q [T, n, n]`` where estimated).
"""

from __future__ import annotations

import math

import numpy as np


def _obs(mask, t, m):
    return np.ones(m, bool) if mask is None else np.asarray(mask[t], bool)


def _loglik(e, s):
    return -0.5 * (e @ np.linalg.solve(s, e) + np.linalg.slogdet(s)[1] + len(e) * math.log(2 * math.pi))


def ekf_moments(h, hj):
    """``mom(x, P)`` of the extended filter: ``(h(x), P H^T, H P H^T)``, ``H = hj(x)``."""

    def mom(x, p):
        H = hj(x)
        return h(x), p @ H.T, H @ p @ H.T

    return mom


def unscented_moments(h, alpha=1.0, beta=2.0, kappa=0.0):
    """``mom(x, P)`` of the scaled unscented transform: points ``x``, ``x +- gamma L_i``
    (``L`` the lower Cholesky factor of ``P``, ``gamma^2 = n + lambda``,
    ``lambda = alpha^2 (n + kappa) - n``), weights ``Wm0 = lambda / (n + lambda)``,
    ``Wc0 = Wm0 + 1 - alpha^2 + beta``, ``Wi = 1 / (2 (n + lambda))``."""

    def mom(x, p):
        n = len(x)
        lam = alpha**2 * (n + kappa) - n
        L = np.linalg.cholesky(p)
        pts = np.concatenate([x[None], x + np.sqrt(n + lam) * L.T, x - np.sqrt(n + lam) * L.T])
        wm = np.full(2 * n + 1, 0.5 / (n + lam))
        wc = wm.copy()
        wm[0] = lam / (n + lam)
        wc[0] = wm[0] + 1 - alpha**2 + beta
        zs = np.array([h(pt) for pt in pts])
        zhat = wm @ zs
        dz, dx = zs - zhat, pts - x
        return zhat, (wc[:, None] * dx).T @ dz, (wc[:, None] * dz).T @ dz

    return mom


def _kf_update(xp, pp, z, mom, r, o):
    """Gaussian update of ``N(xp, pp)`` on the observed components ``o``:
    ``K = P_xz S^-1``, ``S = spread + R``, ``P = P - K S K^T``."""
    zhat, pxz, spread = mom(xp, pp)
    e = z[o] - zhat[o]
    s = spread[np.ix_(o, o)] + r[np.ix_(o, o)]
    k = pxz[:, o] @ np.linalg.inv(s)
    p = pp - k @ s @ k.T
    return xp + k @ e, 0.5 * (p + p.T), k


def _pd(a, floor):
    level = abs(np.mean(np.diag(a)))
    try:
        np.linalg.cholesky(0.5 * (a + a.T) - floor * level * np.eye(len(a)))
        return True
    except np.linalg.LinAlgError:
        return False


def _blockdiag(sample, current, o):
    out = np.zeros_like(sample)
    out[np.ix_(o, o)] = sample[np.ix_(o, o)]
    u = ~o
    out[np.ix_(u, u)] = current[np.ix_(u, u)]
    return out


def sage_husa(z, m0, p0, F, Q, R, mom, b, mask=None, adapt_r=True, adapt_q=False, floor=1e-9):
    x, p, r, q, k = m0.copy(), p0.copy(), R.copy(), Q.copy(), 0
    out = {key: [] for key in ("mean", "cov", "ll", "R", "Q")}
    T, m = z.shape
    for t in range(T):
        xp = F @ x
        spread_f = F @ p @ F.T
        pp = spread_f + q
        o = _obs(mask, t, m)
        ll = 0.0
        if o.any():
            k += 1
            d = (1 - b) / (1 - b ** (k + 1))
            zhat, _, hph = mom(xp, pp)
            e = np.where(o, z[t] - zhat, 0.0)
            ll = _loglik(e[o], (hph + r)[np.ix_(o, o)])
            if adapt_r:
                cand = (1 - d) * r + d * _blockdiag(np.outer(e, e) - hph, r, o)
                if not _pd(cand, floor):
                    cand = (1 - d) * r + d * _blockdiag(np.outer(e, e), r, o)
                r = 0.5 * (cand + cand.T)
            x, p, _ = _kf_update(xp, pp, z[t], mom, r, o)
            if adapt_q:
                dx = x - xp
                cand = (1 - d) * q + d * (np.outer(dx, dx) + p - spread_f)
                if not _pd(cand, floor):
                    cand = (1 - d) * q + d * np.outer(dx, dx)
                q = 0.5 * (cand + cand.T)
        else:
            x, p = xp, pp
        for key, val in (("mean", x), ("cov", p), ("ll", ll), ("R", r), ("Q", q)):
            out[key].append(np.copy(val))
    return {key: np.array(v) for key, v in out.items()}


def vb_r(z, m0, p0, F, Q, R, mom, rho, iterations, prior_shape, mask=None):
    """Särkkä & Nummenmaa (2009), Algorithm 1, diagonal R ~ prod IG(alpha_i, beta_i)."""
    x, p = m0.copy(), p0.copy()
    T, m = z.shape
    alpha = np.full(m, prior_shape)
    beta = prior_shape * np.diag(R).copy()
    out = {key: [] for key in ("mean", "cov", "ll", "R")}
    for t in range(T):
        xp, pp = F @ x, F @ p @ F.T + Q
        o = _obs(mask, t, m)
        ll = 0.0
        x, p = xp, pp
        if o.any():
            zhat, _, hph = mom(xp, pp)
            ll = _loglik((z[t] - zhat)[o], (hph + np.diag(beta / alpha))[np.ix_(o, o)])
            alpha_new, beta_pred = alpha.copy(), beta.copy()
            alpha_new[o] = rho * alpha[o] + 0.5
            beta_pred[o] = rho * beta[o]
            beta_n = beta_pred.copy()
            for _ in range(iterations):
                x, p, _ = _kf_update(xp, pp, z[t], mom, np.diag(beta_n / alpha_new), o)
                zpost, _, spread = mom(x, p)
                res = z[t] - zpost
                beta_n = beta_pred.copy()
                beta_n[o] = beta_pred[o] + 0.5 * res[o] ** 2 + 0.5 * np.diag(spread)[o]
            alpha, beta = alpha_new, beta_n
        for key, val in (("mean", x), ("cov", p), ("ll", ll), ("R", np.diag(beta / alpha))):
            out[key].append(np.copy(val))
    return {key: np.array(v) for key, v in out.items()}


def vb_qr(z, m0, p0, F, Q, R, mom, rho, tau, iterations, prior_dof, mask=None):
    """Huang, Zhang, Wu, Chambers (2018), Table I, with inverse-Wishart ``(u, U)`` for R and
    ``(t, T)`` for the predicted covariance; ``u_0 = prior_dof + m + 1``, ``U_0 = prior_dof R``."""
    x, p = m0.copy(), p0.copy()
    T_, m = z.shape
    n = len(m0)
    u = prior_dof + m + 1
    U = prior_dof * R
    out = {key: [] for key in ("mean", "cov", "ll", "R", "Q", "P")}
    for t in range(T_):
        xp, pp = F @ x, F @ p @ F.T + Q
        o = _obs(mask, t, m)
        ll = 0.0
        r_prev = U / (u - m - 1)
        x, p, p_hat = xp, pp, pp
        if o.any():
            zhat, _, hph = mom(xp, pp)
            ll = _loglik((z[t] - zhat)[o], (hph + r_prev)[np.ix_(o, o)])
            u_pred = rho * (u - m - 1) + m + 1
            U_pred = rho * U
            t_pred, T_pred = n + tau + 1, tau * pp
            xi, pi = xp, pp
            for _ in range(iterations):
                dx = xi - xp
                t_hat, T_hat = t_pred + 1, np.outer(dx, dx) + pi + T_pred
                zi, _, spread_i = mom(xi, pi)
                res = np.where(o, z[t] - zi, 0.0)
                B = _blockdiag(np.outer(res, res) + spread_i, r_prev, o)
                u_hat, U_hat = u_pred + 1, B + U_pred
                p_hat = T_hat / (t_hat - n - 1)
                r_hat = U_hat / (u_hat - m - 1)
                xi, pi, _ = _kf_update(xp, p_hat, z[t], mom, r_hat, o)
            x, p, u, U = xi, pi, u_hat, U_hat
        for key, val in (("mean", x), ("cov", p), ("ll", ll), ("R", U / (u - m - 1)), ("Q", Q + p_hat - pp), ("P", p_hat)):
            out[key].append(np.copy(val))
    return {key: np.array(v) for key, v in out.items()}


def covariance_matching(z, m0, p0, F, Q, R, mom, window, mask=None, adapt_r=True, adapt_q=False, floor=1e-9):
    """Innovation-based adaptive estimation: ``C = sum lambda^(k-j) e_j e_j^T / sum lambda^(k-j)``
    (observed steps; partial masks by the block rule), ``R = C - H P- H^T`` when positive
    definite, ``Q = K C K^T``.  On fully observed steps ``C`` is also checked in its
    explicit-sum form (``sums``)."""
    lam = 1.0 - 1.0 / window
    x, p, r, q = m0.copy(), p0.copy(), R.copy(), Q.copy()
    T, m = z.shape
    c, w = np.zeros((m, m)), 0.0
    history = []
    out = {key: [] for key in ("mean", "cov", "ll", "R", "Q", "C", "sums")}
    for t in range(T):
        xp, pp = F @ x, F @ p @ F.T + q
        o = _obs(mask, t, m)
        ll = 0.0
        x, p = xp, pp
        if o.any():
            zhat, _, hph = mom(xp, pp)
            e = np.where(o, z[t] - zhat, 0.0)
            ll = _loglik(e[o], (hph + r)[np.ix_(o, o)])
            c = (lam * w * c + _blockdiag(np.outer(e, e), c, o)) / (lam * w + 1)
            w = lam * w + 1
            history.append(np.outer(e, e))
            if adapt_r:
                cand = r.copy()
                cand[np.ix_(o, o)] = (c - hph)[np.ix_(o, o)]
                if _pd(cand, floor):
                    r = 0.5 * (cand + cand.T)
            x, p, k = _kf_update(xp, pp, z[t], mom, r, o)
            if adapt_q:
                q = k @ c[np.ix_(o, o)] @ k.T
        weights = lam ** np.arange(len(history))[::-1]
        sums = sum(wj * hj_ for wj, hj_ in zip(weights, history, strict=True)) / weights.sum() if history else c
        for key, val in (("mean", x), ("cov", p), ("ll", ll), ("R", r), ("Q", q), ("C", c), ("sums", sums)):
            out[key].append(np.copy(val))
    return {key: np.array(v) for key, v in out.items()}
