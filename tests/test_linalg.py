"""Linear-algebra primitives against dense references."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from difffilter.linalg import (
    chol_rank1_update,
    gaussian_log_density,
    joseph_update,
    nonfinite_rows,
    psd_solve,
    safe_cholesky,
    symmetrize,
    tria,
)

VALS = st.floats(-5.0, 5.0, allow_nan=False)


def _spd(vals, n, shift=0.5):
    a = torch.tensor(vals, dtype=torch.float64).reshape(n, n)
    return a @ a.mT + shift * torch.eye(n, dtype=torch.float64)


@settings(max_examples=50, deadline=None)
@given(st.lists(VALS, min_size=16, max_size=16), st.lists(VALS, min_size=4, max_size=4), st.booleans())
def test_rank1_update_and_downdate(vals, v, down):
    P = _spd(vals, 4)
    vv = torch.tensor(v, dtype=torch.float64)
    if down:  # downdate back to P from P + v v^T
        L = torch.linalg.cholesky(P + torch.outer(vv, vv))
        out = chol_rank1_update(L, vv, -1.0)
        target = P
    else:
        out = chol_rank1_update(torch.linalg.cholesky(P), vv, 1.0)
        target = P + torch.outer(vv, vv)
    assert torch.allclose(out @ out.mT, target, atol=1e-8 * float(target.abs().max()))
    assert torch.equal(out, torch.tril(out))


@settings(max_examples=50, deadline=None)
@given(st.lists(VALS, min_size=24, max_size=24))
def test_tria_is_cholesky_of_gram(vals):
    a = torch.tensor(vals, dtype=torch.float64).reshape(3, 8)
    s = tria(a)
    assert torch.equal(s, torch.tril(s))
    assert bool((torch.diagonal(s) >= 0).all())
    assert torch.allclose(s @ s.mT, a @ a.mT, atol=1e-10)


@settings(max_examples=50, deadline=None)
@given(st.lists(VALS, min_size=9, max_size=9), st.lists(VALS, min_size=3, max_size=3))
def test_psd_solve_and_log_density_match_dense(vals, b):
    A = _spd(vals, 3)
    bb = torch.tensor(b, dtype=torch.float64)[:, None]
    x = psd_solve(A, bb)
    assert torch.allclose(A @ x, bb, atol=1e-8 * (1 + float(bb.abs().max())) * float(torch.linalg.cond(A)))
    ld, maha = gaussian_log_density(bb[:, 0], torch.linalg.cholesky(A))
    from scipy.stats import multivariate_normal

    ref = multivariate_normal(mean=np.zeros(3), cov=A.numpy()).logpdf(bb[:, 0].numpy())
    assert abs(float(ld) - ref) < 1e-8 * max(1.0, abs(ref))


def test_log_density_of_a_masked_system_is_that_of_the_observed_components():
    # Component 1 unobserved: the masked system has a zero residual and a unit row/column there;
    # with num_obs = 2 the density is the 2-D one of components 0 and 2 (scipy, dense).
    from scipy.stats import multivariate_normal

    full = _spd(list(np.linspace(-0.9, 0.8, 9)), 3)
    keep = [0, 2]
    sub = full[keep][:, keep]
    masked = torch.eye(3, dtype=torch.float64)
    masked[np.ix_(keep, keep)] = sub
    r = torch.tensor([0.7, 0.0, -1.3], dtype=torch.float64)
    chol = torch.linalg.cholesky(masked)
    ref = multivariate_normal(mean=np.zeros(2), cov=sub.numpy()).logpdf(r[keep].numpy())
    ld, maha = gaussian_log_density(r, chol, torch.tensor(2.0, dtype=torch.float64))
    assert abs(float(ld) - ref) < 1e-12 * max(1.0, abs(ref))
    # the caller's whitened residual and log-determinant give the same numbers
    w = torch.linalg.solve_triangular(chol, r[:, None], upper=False)[:, 0]
    ld2, maha2 = gaussian_log_density(r, chol, 2.0, whitened=w, logdet=torch.logdet(masked))
    assert abs(float(ld2) - ref) < 1e-12 * max(1.0, abs(ref)) and abs(float(maha2 - maha)) < 1e-12


def test_safe_cholesky_repairs_only_failing_elements():
    good = _spd(list(np.linspace(-1, 1, 9)), 3)
    singular = torch.ones(3, 3, dtype=torch.float64)  # PSD, rank 1
    indefinite = torch.diag(torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64))
    with_nan = good.clone()
    with_nan[0, 0] = float("nan")
    batch = torch.stack([good, singular, indefinite, with_nan]).requires_grad_(True)
    res = safe_cholesky(batch)
    assert float(res.jitter[0]) == 0.0
    assert 0 < float(res.jitter[1]) <= 1e-2 * 1.0 + 1e-15  # bounded jitter
    assert torch.isinf(res.jitter[2]) and torch.isinf(res.jitter[3])  # beyond the bound: flagged
    assert torch.allclose(res.factor[0], torch.linalg.cholesky(good))
    assert torch.isfinite(res.factor).all()
    res.factor.sum().backward()
    assert torch.isfinite(batch.grad[:2]).all()


@settings(max_examples=40, deadline=None)
@given(st.lists(VALS, min_size=16, max_size=16), st.lists(VALS, min_size=8, max_size=8))
def test_joseph_equals_standard_update_for_optimal_gain_and_stays_psd(vals, hv):
    P = _spd(vals, 4)
    H = torch.tensor(hv, dtype=torch.float64).reshape(2, 4)
    R = torch.eye(2, dtype=torch.float64) * 0.3
    S = H @ P @ H.mT + R
    K = P @ H.mT @ torch.linalg.inv(S)
    std = symmetrize(P - K @ S @ K.mT)
    jos = joseph_update(P, K, H, R)
    assert torch.allclose(jos, std, atol=1e-8 * float(P.abs().max()))
    # any (suboptimal) gain keeps Joseph PSD
    jos2 = joseph_update(P, 3 * K, H, R)
    assert float(torch.linalg.eigvalsh(jos2).min()) > -1e-9 * float(jos2.abs().max())


def test_jitter_bound_limits_repair_and_failures_are_counted():
    from difffilter.linalg import cholesky_failure_count, jitter_bound

    near_singular = torch.ones(1, 3, 3, dtype=torch.float64) + 1e-9 * torch.eye(3, dtype=torch.float64)
    near_singular[0, 0, 1] = near_singular[0, 1, 0] = 1.0 + 1e-5  # indefinite by ~1e-5
    before = cholesky_failure_count()
    assert torch.isfinite(safe_cholesky(near_singular).jitter).all()  # default bound repairs it
    with jitter_bound(1e-8):
        res = safe_cholesky(near_singular)
    assert torch.isinf(res.jitter).all()
    assert cholesky_failure_count() == before + 1
    assert torch.isfinite(safe_cholesky(near_singular).jitter).all()  # bound restored on exit


def test_nonfinite_rows_equals_the_element_wise_test():
    """The sum's shortcut never changes the answer: NaN, +-inf, a row whose finite values
    overflow their sum (1e308 + 1e308), a strided view, float32, under vmap."""
    gen = torch.Generator().manual_seed(0)
    for dtype, huge in ((torch.float64, 1e308), (torch.float32, 3e38)):
        x = torch.randn(6, 5, 3, generator=gen, dtype=torch.float64).to(dtype)
        x[1, 2, 0] = float("nan")
        x[3, 0, 2] = float("inf")
        x[3, 1, 2] = -float("inf")  # inf - inf: a NaN sum
        x[4, :, :] = huge  # finite, the sum overflows: still a finite row
        x[5, 4, 1] = -float("inf")
        for view in (x, x.transpose(0, 2).contiguous().transpose(0, 2), x[:, ::2]):
            for dims in (0, 1, 2, 3):
                want = ~torch.isfinite(view).reshape(*view.shape[:dims], -1).all(-1)
                assert torch.equal(nonfinite_rows(view, dims), want)
        assert not bool(nonfinite_rows(x[[0, 2, 4]], 0))
        assert nonfinite_rows(x, 1).tolist() == [False, True, False, True, False, True]
    got = torch.func.vmap(lambda r: nonfinite_rows(r, 0))(x.double())
    assert got.tolist() == [False, True, False, True, False, True]
