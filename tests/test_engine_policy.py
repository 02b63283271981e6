"""The engine switch of plain filter calls (difffilter.engines.policy, DIFFFILTER_ENGINE)."""

from __future__ import annotations

import warnings

import pytest
import torch

from difffilter.engines import build, policy
from difffilter.filters import UKF
from difffilter.models import FunctionalModel

D = torch.float64


@pytest.fixture(autouse=True)
def fresh_policy(monkeypatch):
    monkeypatch.delenv("DIFFFILTER_ENGINE", raising=False)
    monkeypatch.delenv("DIFFFILTER_AUTO_MIN_WORK", raising=False)
    monkeypatch.delenv("DIFFFILTER_AUTO_MIN_TOTAL", raising=False)
    policy.set_engine(None)
    policy._runners.clear()
    policy._failed.clear()
    policy._warned.clear()
    policy._work.clear()
    yield
    policy.set_engine(None)
    policy._runners.clear()


def _ukf(f=None) -> UKF:  # type: ignore[no-untyped-def]
    model = FunctionalModel(
        f=f or (lambda x: 0.95 * x),
        h=lambda x: torch.stack([torch.hypot(x[..., 0], x[..., 1] + 2.0), x[..., 1]], -1),
        Q=0.1 * torch.eye(2, dtype=D),
        R=0.2 * torch.eye(2, dtype=D),
    )
    return UKF(model)


def _data(bsz: int = 4, steps: int = 6):
    g = torch.Generator().manual_seed(0)
    return torch.randn(bsz, steps, 2, dtype=D, generator=g) + 2.0, torch.zeros(2, dtype=D), torch.eye(2, dtype=D)


def _run(ukf: UKF, z, m0, p0):  # type: ignore[no-untyped-def]
    out = ukf(z, m0, p0)
    grads = torch.autograd.grad(out.log_likelihood.sum(), [p for p in ukf.parameters() if p.requires_grad])
    return out, grads


def test_default_is_auto_and_small_calls_build_nothing():
    assert policy.DEFAULT_ENGINE == "auto" and policy.chosen_engine() == "auto"
    _run(_ukf(), *_data(4, 6))  # B * T = 24 < 10_000
    assert not policy._runners


class _Recording:
    """Stands in for the compiled runner: records each call, returns the eager result."""

    calls: list[tuple[int, ...]] = []

    def __init__(self, filt, engine):  # type: ignore[no-untyped-def]
        self.filter = filt

    def _run(self, z, m0, p0, mask, controls, belief=None):  # type: ignore[no-untyped-def]
        _Recording.calls.append(tuple(z.shape))
        return self.filter._run(z, m0, p0, mask, controls, belief=belief)


def test_auto_compiles_large_calls_and_a_filter_whose_small_calls_add_up(monkeypatch):
    monkeypatch.setattr(policy, "FusedFilter", _Recording)
    _Recording.calls = []
    monkeypatch.setenv("DIFFFILTER_AUTO_MIN_WORK", "100")
    monkeypatch.setenv("DIFFFILTER_AUTO_MIN_TOTAL", "576")
    ukf, other = _ukf(), _ukf()
    _run(ukf, *_data(4, 6))  # B * T = 24; counts max(B, 32) * T = 192 towards the total: eager
    _run(other, *_data(4, 6))  # another filter's work does not count
    _run(ukf, *_data(4, 6))  # total 384: eager
    assert _Recording.calls == [] and policy.last_engine(ukf) == "eager"
    _run(ukf, *_data(2, 6))  # total 576: the repeated calls pay for a build
    _run(ukf, *_data(1, 2))
    assert _Recording.calls == [(2, 6, 2), (1, 2, 2)] and policy.last_engine(ukf) == "generated"
    _run(other, *_data(10, 10))  # one call of B * T = 100
    assert _Recording.calls[-1] == (10, 10, 2) and len(_Recording.calls) == 3


def test_eager_builds_nothing_even_for_large_calls(monkeypatch):
    monkeypatch.setenv("DIFFFILTER_ENGINE", "eager")
    monkeypatch.setenv("DIFFFILTER_AUTO_MIN_WORK", "1")  # ignored: eager never builds
    _run(_ukf(), *_data(4, 6))
    assert not policy._runners


def test_an_engine_error_on_good_input_falls_back_with_the_reason(monkeypatch):
    """An exception inside the engine that is not a refusal: the eager result, flagged once."""

    def broken(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        raise RuntimeError("engine defect")

    monkeypatch.setattr(policy.FusedFilter, "_run", broken)
    policy.set_engine("compiled")
    ukf = _ukf()
    with pytest.warns(UserWarning, match="cannot run UKF \\(RuntimeError: engine defect\\)") as record:
        out, _ = _run(ukf, *_data())
        _run(ukf, *_data())
    assert len([w for w in record if "cannot run" in str(w.message)]) == 1 and policy.last_engine(ukf) == "eager"
    policy.set_engine("eager")
    assert torch.equal(out.mean, _run(ukf, *_data())[0].mean)


def test_bad_input_on_the_compiled_path_raises_the_eager_error_and_flags_nothing(monkeypatch):
    policy.set_engine("compiled")
    ukf = _ukf()
    z, m0, _ = _data()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match="initial_cov"):
            ukf(z, m0, -torch.eye(2, dtype=D))
    assert not policy._failed


@pytest.mark.slow  # builds a small UKF's kernels when the cache is cold
@pytest.mark.skipif(build.compiler_available() is not None, reason="needs a C++ compiler")
def test_auto_runs_large_calls_compiled_with_the_same_values_and_gradients(monkeypatch):
    ukf = _ukf()
    data = _data(5, 8)
    ref, g_ref = _run(ukf, *data)
    monkeypatch.setenv("DIFFFILTER_ENGINE", "auto")
    monkeypatch.setenv("DIFFFILTER_AUTO_MIN_WORK", "40")  # this call counts as large
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out, g_out = _run(ukf, *data)
    (runner,) = policy._runners.values()
    assert runner.filter is ukf and runner.last_engine == "generated"
    torch.testing.assert_close(out.mean, ref.mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out.log_likelihood, ref.log_likelihood, rtol=1e-12, atol=1e-12)
    for a, b in zip(g_out, g_ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-11, atol=1e-12)


def test_a_filter_the_engine_cannot_run_falls_back_once_with_the_reason(monkeypatch):
    policy.set_engine("compiled")

    def branching(x):  # a Python decision on data: the generated engine refuses it
        return 0.9 * x if bool((x > 100).any()) else 0.95 * x

    ukf = _ukf(branching)
    with pytest.warns(UserWarning, match="cannot run UKF") as record:
        out1, _ = _run(ukf, *_data())
        out2, _ = _run(ukf, *_data())
    assert len([w for w in record if "cannot run" in str(w.message)]) == 1
    policy.set_engine("eager")
    ref, _ = _run(ukf, *_data())
    assert torch.equal(out1.mean, ref.mean) and torch.equal(out2.mean, ref.mean)


def test_no_compiler_falls_back_once(monkeypatch):
    monkeypatch.setattr(build, "_compiler", lambda: None)
    policy.set_engine("compiled")
    with pytest.warns(UserWarning, match="no C\\+\\+ compiler") as record:
        _run(_ukf(), *_data())
        _run(_ukf(), *_data())
    assert len(record) == 1
    assert not policy._runners


def test_bad_settings_are_refused(monkeypatch):
    with pytest.raises(ValueError, match="engine"):
        policy.set_engine("fast")
    monkeypatch.setenv("DIFFFILTER_ENGINE", "fast")
    with pytest.raises(ValueError, match="DIFFFILTER_ENGINE"):
        policy.chosen_engine()
    monkeypatch.setenv("DIFFFILTER_ENGINE", "auto")
    monkeypatch.setenv("DIFFFILTER_AUTO_MIN_WORK", "lots")
    with pytest.raises(ValueError, match="DIFFFILTER_AUTO_MIN_WORK"):
        _run(_ukf(), *_data())
