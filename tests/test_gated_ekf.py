"""GatedEKF (difffilter.filters.gated): the gate acts on the normalised innovation
``|e_j| / sqrt((H P- H^T + R)_jj + floor^2)``.  One update against a numpy re-implementation of
the equations; a filter unsure of its state accepts a residual that a confident one rejects (the
lock-out the ``R``-only gate has); gradients against finite differences in float64 (through the
inputs with ``gradcheck``, through the gate's raw parameters by central differences); a NaN
under a False mask reaches neither values nor gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difffilter.filters import EKF, GatedEKF
from difffilter.filters.gated import innovation_gate_factor
from difffilter.models.heteroscedastic import RobustGate
from difffilter.models.navigation import make_ranging_model

D = torch.float64
ANCHORS = torch.tensor([[0.0, 0.0], [20.0, 0.0], [20.0, 15.0], [-5.0, 12.0]], dtype=D)


def _filter(threshold: float = 3.0, floor: float = 0.3, softness: float | None = 0.4) -> GatedEKF:
    model = make_ranging_model(num_anchors=4, bias=None, noise=None, gate=None)
    gate = RobustGate(kind="reject", threshold=threshold, floor=floor, softness=softness, learnable=softness is not None)
    return GatedEKF(model, gate=gate)


def _u(z: torch.Tensor, b: int = 1, t: int | None = None) -> dict[str, torch.Tensor]:
    lead = (b,) if t is None else (b, t)
    return {
        "odom": torch.zeros(*lead, 3, dtype=D),
        "odom_cov": 0.01 * torch.eye(3, dtype=D).expand(*lead, 3, 3).clone(),
        "dt": torch.ones(*lead, 1, dtype=D),
        "anchors": ANCHORS.expand(*lead, 4, 2).clone(),
        "range_var": torch.tensor([0.25, 0.25, 1.0, 0.5], dtype=D).expand(*lead, 4).clone(),
        "z_obs": z,
    }


def _reference_update(m, p, z, rvar, thr, floor, soft):  # numpy, from the equations
    d = m[:2] - ANCHORS.numpy()
    r = np.linalg.norm(d, axis=1)
    h = np.concatenate([d / r[:, None], np.zeros((4, 1))], 1)
    e = z - r
    s0 = h @ p @ h.T + np.diag(rvar)
    n = np.abs(e) / np.sqrt(np.diag(s0) + floor**2)
    f = 1e6 ** (1.0 / (1.0 + np.exp(-(n - thr) / soft)))
    rg = np.diag(np.sqrt(f)) @ np.diag(rvar) @ np.diag(np.sqrt(f))
    s = h @ p @ h.T + rg
    k = p @ h.T @ np.linalg.inv(s)
    a = np.eye(3) - k @ h
    return m + k @ e, a @ p @ a.T + k @ rg @ k.T, f


def test_one_update_matches_the_equations() -> None:
    filt = _filter()
    m = torch.tensor([[6.0, 4.0, 0.3]], dtype=D)
    p = torch.tensor([[[2.0, 0.3, 0.0], [0.3, 1.5, 0.1], [0.0, 0.1, 0.05]]], dtype=D)
    truth = (m[0, :2] - ANCHORS).norm(dim=-1)
    z = (truth + torch.tensor([0.4, -0.3, 9.0, 0.2], dtype=D))[None]  # anchor 3 an outlier
    u = _u(z)
    post, _info = filt.update({"mean": m, "cov": p}, z, None, u)
    mean, cov, f = _reference_update(m[0].numpy(), p[0].numpy(), z[0].numpy(), u["range_var"][0].numpy(), 3.0, 0.3, 0.4)
    np.testing.assert_allclose(post["mean"][0].detach().numpy(), mean, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(post["cov"][0].detach().numpy(), cov, rtol=1e-9, atol=1e-12)
    assert f[2] > 1e5 and f[[0, 1, 3]].max() < 2.0  # the outlier is gated out, the others are not
    s0 = torch.tensor([[[4.0, 1.0], [1.0, 9.0]]], dtype=D)
    got = innovation_gate_factor(filt.gate, torch.tensor([[1.0, -6.0]], dtype=D), s0)
    n = torch.tensor([1.0 / (4.0 + 0.09) ** 0.5, 6.0 / (9.0 + 0.09) ** 0.5], dtype=D)
    torch.testing.assert_close(got[0], 1e6 ** torch.sigmoid((n - 3.0) / 0.4))


def test_a_large_prior_covariance_accepts_what_a_small_one_rejects() -> None:
    # the same 5 m residual on every range: an outlier for a confident filter, not for an unsure one
    m = torch.tensor([[6.0, 4.0, 0.3]], dtype=D)
    z = ((m[0, :2] - ANCHORS).norm(dim=-1) + 5.0)[None]
    hard = _filter(floor=0.0, softness=None)
    for var, gated in ((0.05, True), (60.0, False)):
        p = torch.diag(torch.tensor([var, var, 0.01], dtype=D))[None]
        post, _ = hard.update({"mean": m, "cov": p}, z, None, _u(z))
        moved = float((post["mean"][0, :2] - m[0, :2]).norm())
        assert (moved < 1e-3) == gated, (var, moved)
    # a gate on |e| / sqrt(R + floor^2) ignores P: it rejects the residual whatever the filter's doubt
    old = EKF(make_ranging_model(num_anchors=4, bias=None, noise=None, gate="hard", gate_threshold=3.0, gate_floor=0.0))
    post, _ = old.update({"mean": m, "cov": torch.diag(torch.tensor([60.0, 60.0, 0.01], dtype=D))[None]}, z, None, _u(z))
    assert float((post["mean"][0, :2] - m[0, :2]).norm()) < 1e-3


def _run(filt: GatedEKF, z: torch.Tensor, m0: torch.Tensor, l0: torch.Tensor, mask: torch.Tensor | None = None):
    p0 = l0 @ l0.mT + 0.1 * torch.eye(3, dtype=D)
    return filt(z, m0, p0, mask=mask, controls=_u(z, z.shape[0], z.shape[1]))


def _data(t: int = 4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    pos = torch.tensor([6.0, 4.0], dtype=D)
    z = (pos - ANCHORS).norm(dim=-1).expand(1, t, 4) + 0.5 * torch.randn(1, t, 4, generator=g, dtype=D)
    z[0, 1, 2] += 4.0  # an outlier inside the smooth gate's transition
    m0 = torch.tensor([[6.5, 3.5, 0.1]], dtype=D)
    l0 = torch.tensor([[[1.2, 0.0, 0.0], [0.3, 0.9, 0.0], [0.0, 0.1, 0.2]]], dtype=D)
    return z, m0, l0


def test_gradients_through_the_gate_match_finite_differences() -> None:
    filt = _filter(softness=0.8)
    z, m0, l0 = _data()

    def fn(z_, m0_, l0_):
        r = _run(filt, z_, m0_, l0_)
        return r.mean[:, -1], r.log_likelihood.sum()

    assert torch.autograd.gradcheck(fn, (z.requires_grad_(), m0.requires_grad_(), l0.requires_grad_()), eps=1e-6, atol=1e-5)
    z, m0, l0 = z.detach(), m0.detach(), l0.detach()
    loss = lambda: _run(filt, z, m0, l0).mean[:, 1:, :2].pow(2).sum() + _run(filt, z, m0, l0).log_likelihood.sum()  # noqa: E731
    params = dict(filt.gate.named_parameters())
    assert len(params) == 3  # threshold, floor, softness (raw)
    filt.zero_grad()
    loss().backward()
    for name, p in params.items():
        with torch.no_grad():
            p += 1e-6
            up = float(loss())
            p -= 2e-6
            down = float(loss())
            p += 1e-6
        fd = (up - down) / 2e-6
        assert float(p.grad) == pytest.approx(fd, rel=1e-4, abs=1e-7), name
        assert abs(fd) > 1e-6, name  # the gate's parameters do move the loss here


def test_nan_under_a_false_mask_reaches_neither_values_nor_gradients() -> None:
    filt = _filter()
    z, m0, l0 = _data()
    mask = torch.ones(1, 4, 4, dtype=torch.bool)
    mask[0, 2, 1] = False
    outs = []
    for fill in (float("nan"), 123.0):
        zz = z.clone()
        zz[0, 2, 1] = fill
        zz.requires_grad_(True)
        r = _run(filt, zz, m0, l0, mask)
        (r.mean.sum() + r.log_likelihood.sum()).backward()
        assert torch.isfinite(r.mean).all() and torch.isfinite(zz.grad).all() and float(zz.grad[0, 2, 1]) == 0.0
        outs.append(r.mean.detach())
    torch.testing.assert_close(outs[0], outs[1])


def test_bad_gate_argument() -> None:
    with pytest.raises(TypeError, match="gate must be a RobustGate"):
        GatedEKF(make_ranging_model(num_anchors=4, gate=None), gate=3.0)  # type: ignore[arg-type]
