"""gaussian_update's covariance forms as one typed option (JosephForm): each form against a numpy
re-implementation of the textbook equations, and the fallback applied only where P - K S K^T cancels."""

from __future__ import annotations

import numpy as np
import torch

from difffilter.filters.update import JosephForm, gaussian_update, square_root_deviations

f64 = torch.float64


def _system(prior_scale: list[float], r: float | list[float], seed: int = 0, m: int = 2):
    gen = torch.Generator().manual_seed(seed)
    b, n = len(prior_scale), 3
    a = torch.randn(b, n, n, generator=gen, dtype=f64)
    cov = (a @ a.mT + n * torch.eye(n, dtype=f64)) * torch.tensor(prior_scale, dtype=f64)[:, None, None]
    h = torch.randn(b, m, n, generator=gen, dtype=f64)
    rr = torch.as_tensor(r, dtype=f64).reshape(-1, 1, 1) * torch.eye(m, dtype=f64).expand(b, m, m)
    mean = torch.randn(b, n, generator=gen, dtype=f64)
    e = torch.randn(b, m, generator=gen, dtype=f64)
    return mean, cov, h, rr, e


def _numpy_forms(cov, h, r):
    p, hh, rr = cov.numpy(), h.numpy(), r.numpy()
    s = hh @ p @ hh.swapaxes(-1, -2) + rr
    k = np.linalg.solve(s, hh @ p).swapaxes(-1, -2)  # K = P H^T S^{-1} (S symmetric)
    ikh = np.eye(p.shape[-1]) - k @ hh
    joseph = ikh @ p @ ikh.swapaxes(-1, -2) + k @ rr @ k.swapaxes(-1, -2)
    standard = p - k @ s @ k.swapaxes(-1, -2)
    return standard, joseph


def _update(mean, cov, h, r, e, joseph):
    pht = cov @ h.mT
    return gaussian_update(mean, cov, e, h @ pht + r, pht, None, joseph=joseph)[1]


def test_each_form_matches_the_textbook_equations():
    mean, cov, h, r, e = _system([1.0, 2.0], r=0.5)
    standard, joseph = _numpy_forms(cov, h, r)
    np.testing.assert_allclose(_update(mean, cov, h, r, e, None).numpy(), standard, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(_update(mean, cov, h, r, e, JosephForm.linear(h, r, always=True)).numpy(), joseph, rtol=1e-10, atol=1e-12)
    # sigma-point form with the columns of a square root of P (unit weights) is the linear Joseph form
    dx, dz, wc = square_root_deviations(cov, h)
    np.testing.assert_allclose(_update(mean, cov, h, r, e, JosephForm.sigma_points(dx, dz, wc, r)).numpy(), joseph, rtol=1e-9, atol=1e-11)


def test_fallback_replaces_only_the_elements_whose_reduction_cancels():
    # element 0: a benign reduction; element 1: the measurement pins the state (posterior/prior
    # variance ratio below the 64 sqrt(eps) switch), where P - K S K^T loses its digits
    mean, cov, h, r, e = _system([1.0, 1e6], r=[1.0, 1e-6], m=3)
    ratio = torch.diagonal(_update(mean, cov, h, r, e, None), dim1=-2, dim2=-1) / torch.diagonal(cov, dim1=-2, dim2=-1)
    switch = 64 * torch.finfo(f64).eps ** 0.5
    assert bool((ratio[1] < switch).any()) and bool((ratio[0] > switch).all())
    plain = _update(mean, cov, h, r, e, None)
    always = _update(mean, cov, h, r, e, JosephForm.linear(h, r, always=True))
    fallback = _update(mean, cov, h, r, e, JosephForm.linear(h, r))
    assert torch.equal(fallback[1], always[1])
    assert torch.equal(fallback[0], plain[0])
    sigma = _update(mean, cov, h, r, e, JosephForm.sigma_points(*square_root_deviations(cov, h), r))
    assert torch.equal(sigma[0], plain[0])
    torch.testing.assert_close(sigma[1], always[1], rtol=1e-6, atol=1e-9)
