"""Filter calls run with the library's thread count (default 1) in their forward and backward
passes, and give the caller's count back afterwards (difffilter.threads)."""

from __future__ import annotations

import pytest
import torch

from difffilter import threads as th
from difffilter.engines import FusedFilter
from difffilter.filters import UKF
from difffilter.models import FunctionalModel
from difffilter.smoothers import RTSSmoother

D = torch.float64


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(3)  # any count other than the library's 1
    yield 3
    torch.set_num_threads(before)


def _recording_model(seen: dict[str, list[int]]) -> FunctionalModel:
    def f(x):
        seen["forward"].append(torch.get_num_threads())
        if x.requires_grad:
            x.register_hook(lambda g: seen["backward"].append(torch.get_num_threads()))
        return x

    def h(x):
        return torch.stack([torch.sqrt(x[..., 0] ** 2 + 1.0), x[..., 1]], -1)

    return FunctionalModel(f=f, h=h, Q=0.1 * torch.eye(2, dtype=D), R=0.2 * torch.eye(2, dtype=D), Q_structure="diagonal")


def _data(bsz: int = 4, steps: int = 6):
    g = torch.Generator().manual_seed(0)
    return torch.randn(bsz, steps, 2, dtype=D, generator=g), torch.zeros(2, dtype=D), torch.eye(2, dtype=D)


def test_forward_and_backward_run_single_threaded_and_restore(two_threads):
    seen: dict[str, list[int]] = {"forward": [], "backward": []}
    ukf = UKF(_recording_model(seen))
    z, m0, p0 = _data()
    res = ukf(z, m0, p0)
    assert torch.get_num_threads() == two_threads
    res.log_likelihood.sum().backward()
    assert torch.get_num_threads() == two_threads
    assert seen["forward"] and set(seen["forward"]) == {1}
    assert seen["backward"] and set(seen["backward"]) == {1}


def test_upstream_backward_keeps_the_callers_count(two_threads):
    """A network feeding the filter computes its gradient with the caller's count."""
    seen: list[int] = []
    ukf = UKF(_recording_model({"forward": [], "backward": []}))
    z, m0, p0 = _data()
    raw = z.clone().requires_grad_()
    fed = raw * 1.0
    fed.register_hook(lambda g: seen.append(torch.get_num_threads()))
    ukf(fed, m0, p0).log_likelihood.sum().backward()
    assert seen == [two_threads]
    assert raw.grad is not None and torch.isfinite(raw.grad).all()


def test_grad_of_parameters_only_restores(two_threads):
    ukf = UKF(_recording_model({"forward": [], "backward": []}))
    z, m0, p0 = _data()
    params = [p for p in ukf.parameters() if p.requires_grad]
    grads = torch.autograd.grad(ukf(z, m0, p0).log_likelihood.sum(), params)
    assert torch.get_num_threads() == two_threads
    assert all(torch.isfinite(g).all() for g in grads)


def test_backward_that_fails_midway_restores_at_the_next_call(two_threads):
    def boom(g):
        raise RuntimeError("boom")

    def f(x):
        if x.requires_grad:
            x.register_hook(boom)
        return x

    model = FunctionalModel(f=f, h=lambda x: x, Q=0.1 * torch.eye(2, dtype=D), R=0.2 * torch.eye(2, dtype=D))
    z, m0, p0 = _data()
    res = UKF(model)(z, m0, p0)
    with pytest.raises(RuntimeError, match="boom"):
        res.log_likelihood.sum().backward()
    with torch.no_grad():
        UKF(model)(z, m0, p0)
    assert torch.get_num_threads() == two_threads


def test_values_and_gradients_equal_to_unscoped_run(two_threads):
    z, m0, p0 = _data(8, 10)
    out = {}
    for setting in (1, None):
        th.set_filter_threads(setting)
        try:
            model = FunctionalModel(
                f=lambda x: x @ torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=D).mT,
                h=lambda x: torch.stack([torch.sqrt(x[..., 0] ** 2 + 1.0), x[..., 1]], -1),
                Q=0.1 * torch.eye(2, dtype=D),
                R=0.2 * torch.eye(2, dtype=D),
            )
            m = m0.clone().requires_grad_()
            res = UKF(model)(z, m, p0)
            res.log_likelihood.sum().backward()
            out[setting] = (res.mean.detach(), res.log_likelihood.detach(), m.grad, [p.grad for p in model.parameters()])
        finally:
            th.set_filter_threads(1)
    (a_mean, a_ll, a_m, a_p), (b_mean, b_ll, b_m, b_p) = out[1], out[None]
    assert torch.equal(a_mean, b_mean) and torch.equal(a_ll, b_ll) and torch.equal(a_m, b_m)
    assert all(torch.equal(x, y) for x, y in zip(a_p, b_p, strict=True))


def test_setting_none_leaves_torch_alone(two_threads):
    seen: dict[str, list[int]] = {"forward": [], "backward": []}
    th.set_filter_threads(None)
    try:
        UKF(_recording_model(seen))(*_data()).log_likelihood.sum().backward()
    finally:
        th.set_filter_threads(1)
    assert set(seen["forward"]) == {two_threads} and set(seen["backward"]) == {two_threads}


def test_smoother_and_fused_filter_are_scoped(two_threads):
    for wrap in (RTSSmoother, lambda f: FusedFilter(f, engine="eager")):
        seen: dict[str, list[int]] = {"forward": [], "backward": []}
        runner = wrap(UKF(_recording_model(seen)))
        res = runner(*_data())
        assert torch.get_num_threads() == two_threads
        res.mean.sum().backward()
        assert torch.get_num_threads() == two_threads
        assert set(seen["forward"]) == {1} and set(seen["backward"]) == {1}


def test_set_filter_threads_refuses_bad_values():
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="threads"):
            th.set_filter_threads(bad)  # type: ignore[arg-type]


def test_environment_variable(monkeypatch):
    for raw, want in (("4", 4), ("torch", None), (" 2 ", 2)):
        monkeypatch.setenv("DIFFFILTER_THREADS", raw)
        assert th._from_env() == want
    for bad in ("0", "two"):
        monkeypatch.setenv("DIFFFILTER_THREADS", bad)
        with pytest.raises(ValueError, match="DIFFFILTER_THREADS"):
            th._from_env()


def test_double_backward_and_torch_func_pass_through(two_threads):
    """The scope's autograd nodes are identities: a Hessian-vector product and ``torch.func.grad``
    over the filter see the filter's own derivatives."""
    model = FunctionalModel(
        f=lambda x: 0.9 * x, h=lambda x: x[..., :1] ** 2 + x[..., 1:], Q=0.1 * torch.eye(2, dtype=D), R=0.2 * torch.eye(1, dtype=D)
    )
    ukf = UKF(model)
    z = torch.randn(3, 5, 1, dtype=D, generator=torch.Generator().manual_seed(0))
    p0 = torch.eye(2, dtype=D)

    def loss(m0):
        return ukf(z, m0, p0).log_likelihood.sum()

    m0 = torch.tensor([0.3, -0.2], dtype=D, requires_grad=True)
    (g,) = torch.autograd.grad(loss(m0), m0, create_graph=True)
    (hv,) = torch.autograd.grad(g.sum(), m0)
    th.set_filter_threads(None)
    try:
        (g_ref,) = torch.autograd.grad(loss(m0), m0, create_graph=True)
        (hv_ref,) = torch.autograd.grad(g_ref.sum(), m0)
        g_func_ref = torch.func.grad(loss)(m0.detach())
    finally:
        th.set_filter_threads(1)
    torch.testing.assert_close(g, g_ref, rtol=0, atol=0)
    torch.testing.assert_close(hv, hv_ref, rtol=0, atol=0)
    torch.testing.assert_close(torch.func.grad(loss)(m0.detach()), g_func_ref, rtol=0, atol=0)
    assert torch.get_num_threads() == two_threads
