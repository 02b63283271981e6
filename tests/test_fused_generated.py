"""The generated-kernel engine of FusedFilter against the reference filters and independent references.

* the whole :class:`FilterContract` battery (closed-form KF, dense joint Gaussian, masks,
  gradcheck by finite differences, bad inputs...) with ``FusedFilter(engine="generated")``;
* every output field and every gradient (parameters, initial belief, measurements) equal to the
  reference filter's on a nonlinear model with controls, masks and a wrapped angle, for every
  filter and mixer kind;
* the lowering itself against torch on random inputs (evaluated by a Python interpreter).
"""

from __future__ import annotations

import copy
import warnings
from concurrent.futures import Future

import numpy as np
import pytest
import torch
from torch import Tensor
from torch.fx.experimental.proxy_tensor import make_fx

from difffilter.engines import FusedFilter, build
from difffilter.engines.graph import ScalarGraph, UnsupportedOp, evaluate
from difffilter.engines.lower import lower
from difffilter.filters import EKF, RCUKF, UKF, Julier, KalmanFilter, MerweScaled, SimplifiedUKF, SquareRootUKF
from difffilter.filters.colored import ColoredNoiseUKF
from difffilter.linalg import chol_rank1_update, tria
from difffilter.mixers import IMM
from difffilter.mixers.blend import Blend
from difffilter.smoothers import make_smoother
from tests.filter_contract import FilterContract
from tests.test_fused import FIELDS, _range_bearing_data
from tests.test_nonadditive import linear_noise_models

F64 = torch.float64


def generated(filt):  # type: ignore[no-untyped-def]
    return FusedFilter(filt, engine="generated")


# -- the contract battery ---------------------------------------------------------------------
class TestGeneratedKalmanFilter(FilterContract):
    def make_filter(self, model):  # type: ignore[no-untyped-def]
        return generated(KalmanFilter(model))


class TestGeneratedEKF(FilterContract):
    def make_filter(self, model):  # type: ignore[no-untyped-def]
        return generated(EKF(model))


class TestGeneratedUKFMerweRedraw(FilterContract):
    def make_filter(self, model):  # type: ignore[no-untyped-def]
        return generated(UKF(model, sigma_points=MerweScaled(alpha=1.0, beta=2.0, kappa=0.0)))


class TestGeneratedUKFJulierAugmentedReuse(FilterContract):
    def make_filter(self, model):  # type: ignore[no-untyped-def]
        return generated(UKF(model, sigma_points=Julier(kappa=1.0), noise="augmented", redraw_after_predict=False))


class TestGeneratedSimplifiedUKF(FilterContract):
    def make_filter(self, model):  # type: ignore[no-untyped-def]
        return generated(SimplifiedUKF(model))


class TestGeneratedSquareRootUKF(FilterContract):
    def make_filter(self, model):  # type: ignore[no-untyped-def]
        return generated(SquareRootUKF(model))


class TestGeneratedIMMOfEqualModes(FilterContract):
    """An IMM whose two modes are the same linear model is that model's Kalman filter."""

    def make_filter(self, model):  # type: ignore[no-untyped-def]
        other = copy.deepcopy(model)
        with torch.no_grad():
            other.load_state_dict(model.state_dict())
        pi = torch.tensor([[0.9, 0.1], [0.3, 0.7]], dtype=next(model.parameters()).dtype)
        return generated(IMM([KalmanFilter(model), EKF(other)], transition=pi, initial_probs=torch.tensor([0.4, 0.6], dtype=pi.dtype)))


# -- every filter kind against its reference --------------------------------------------------
def _separate_model():  # type: ignore[no-untyped-def]
    # separately built (not deep-copied) models: deep copies of one parametrized module share
    # torch's parametrization cache key, which changes the reference filter's results
    return _range_bearing_data(batch=5, steps=12)[0]


KINDS = {
    "ukf-reuse": lambda m: UKF(m, redraw_after_predict=False),
    "ukf-augmented": lambda m: UKF(m, noise="augmented"),
    "ekf-autodiff": lambda m: EKF(m),
    "kf-linearised": lambda m: EKF(m, joseph=False),
    "square-root": lambda m: SquareRootUKF(m),
    "rcukf": lambda m: RCUKF(m),
    "colored": lambda m: ColoredNoiseUKF(m, psi=0.3),
    "imm": lambda m: IMM(
        [UKF(m), EKF(_separate_model())],
        transition=torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=F64),
        initial_probs=torch.tensor([0.5, 0.5], dtype=F64),
    ),
    "blend": lambda m: Blend(EKF(m), UKF(_separate_model())),
}


@pytest.mark.parametrize("kind", list(KINDS))
def test_generated_equals_reference_outputs_and_gradients(kind: str) -> None:
    """Masks (NaN underneath), controls, a wrapped bearing, B = 5 (not a multiple of the SIMD
    width); gradients w.r.t. the parameters, the initial belief and the measurements."""
    model, z, u, m0, p0 = _range_bearing_data(batch=5, steps=12)
    filt = KINDS[kind](model)
    mask = torch.ones(z.shape, dtype=torch.bool)
    mask[0, 4] = False
    mask[2, 6, 1] = False
    zn = z.masked_fill(~mask, float("nan"))

    def run(f):  # type: ignore[no-untyped-def]
        zz = zn.clone().requires_grad_(True)
        mm, pp = m0.clone().requires_grad_(True), p0.clone().requires_grad_(True)
        out = f(zz, mm, pp, mask=mask, controls=u)
        loss = out.log_likelihood.sum() + 0.01 * out.mean.sum()
        params = [p for p in filt.parameters() if p.requires_grad]
        grads = torch.autograd.grad(loss, [zz, mm, pp, *params], allow_unused=True)
        return out, list(grads)

    ref, g_ref = run(filt)
    out, g_out = run(generated(filt))
    assert_same_run(out, ref, g_out, g_ref)


def assert_same_run(out, ref, g_out, g_ref) -> None:  # type: ignore[no-untyped-def]
    """Every field, extra and final-belief entry at ``1e-9``, every gradient at ``1e-8``."""
    for name in FIELDS:
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=1e-9, atol=1e-10, msg=name)
    for name, val in ref.extras.items():
        torch.testing.assert_close(out.extras[name], val, rtol=1e-9, atol=1e-10, msg=name)
    for key, val in ref.final_belief.items():
        torch.testing.assert_close(out.final_belief[key], val, rtol=1e-9, atol=1e-10, msg=key)
    for a, b in zip(g_out, g_ref, strict=True):
        if b is None:  # unused by the reference (e.g. a blend's second R): no gradient or zeros
            assert a is None or not bool(a.any())
        else:
            assert a is not None
            torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10)


def test_float32_and_threads() -> None:
    model, z, u, m0, p0 = _range_bearing_data(batch=20, steps=10)
    filt = UKF(model)
    one = FusedFilter(filt, engine="generated", threads=1)(z, m0, p0, controls=u)
    two = FusedFilter(filt, engine="generated", threads=3)(z, m0, p0, controls=u)
    for name in FIELDS:
        assert torch.equal(getattr(one, name), getattr(two, name)), name
    ref = filt(z, m0, p0, controls=u)
    filt32 = UKF(copy.deepcopy(model).float())
    out32 = generated(filt32)(z.float(), m0.float(), p0.float(), controls=u.float())
    assert out32.mean.dtype == torch.float32
    assert float((out32.mean.double() - ref.mean).abs().max() / ref.mean.abs().max()) < 1e-4


def test_frozen_values_are_not_stale() -> None:
    """Buffers and frozen parameters are compiled in as constants: changing one changes the kernel."""
    model, z, u, m0, p0 = _range_bearing_data()
    filt = UKF(model)
    fused = generated(filt)
    first = fused(z, m0, p0, controls=u)
    with torch.no_grad():
        model.measurement.R = model.measurement.R * 4.0  # through the constraint
    model.requires_grad_(False)
    second = fused(z, m0, p0, controls=u)
    ref = filt(z, m0, p0, controls=u)
    torch.testing.assert_close(second.log_likelihood, ref.log_likelihood, rtol=1e-10, atol=1e-10)
    assert not torch.allclose(first.log_likelihood, second.log_likelihood)


def test_compiled_kernels_are_found_in_the_cache(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    # a cache directory of its own, and no library loaded earlier in this process (another test may have
    # loaded the same kernel from a directory that is gone): the first call must build into tmp_path
    monkeypatch.setenv("DIFFFILTER_CACHE_DIR", str(tmp_path))
    build._loaded.clear()
    model, z, u, m0, p0 = _range_bearing_data()
    first = generated(UKF(model))
    first(z, m0, p0, controls=u)
    for program in first.generated_engine()._programs.values():  # the reverse kernel built in the background
        for built in program._backward.values():
            if isinstance(built, Future):
                built.result()
    build._loaded.clear()

    def no_compiler(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise AssertionError("compiled again")

    monkeypatch.setattr(build.subprocess, "run", no_compiler)
    out = generated(UKF(model))(z, m0, p0, controls=u)
    assert bool(torch.isfinite(out.log_likelihood).all())


class _DataDependent(UKF):
    """A filter whose update makes a Python decision on data values."""

    def update(self, belief, z, mask, u):  # type: ignore[no-untyped-def]
        if bool((z.abs() > 1e9).any()):
            z = z.clamp(-1e9, 1e9)
        return super().update(belief, z, mask, u)


def test_untraceable_filter_falls_back_with_a_warning() -> None:
    model, z, u, m0, p0 = _range_bearing_data()
    filt = _DataDependent(model)
    with pytest.raises(UnsupportedOp, match="cannot be traced"):
        FusedFilter(filt, engine="generated")(z, m0, p0, controls=u)
    with warnings.catch_warnings(record=True) as log:
        warnings.simplefilter("always")
        out = FusedFilter(filt)(z, m0, p0, controls=u)
    assert any("generated engine cannot run" in str(w.message) for w in log)
    torch.testing.assert_close(out.mean, filt(z, m0, p0, controls=u).mean)


# -- the lowering against torch -----------------------------------------------------------------
def lowered_graph(fn, *examples: Tensor):  # type: ignore[no-untyped-def]
    """``fn`` traced and lowered to a scalar graph with one input node per element of each example:
    ``(graph, input node arrays, {input node: example value}, lowered outputs)``."""
    gm = make_fx(torch.func.functionalize(fn), tracing_mode="fake", _allow_non_fake_inputs=True)(*examples)
    g = ScalarGraph()
    arrays, values = [], {}
    for k, ex in enumerate(examples):
        arr = np.array([g.input(f"x{k}", i) for i in range(ex.numel())], dtype=object).reshape(ex.shape)
        arrays.append(arr)
        values.update(zip(arr.reshape(-1).tolist(), ex.reshape(-1).tolist(), strict=True))
    return g, arrays, values, lower(gm, g, F64, arrays)


def _lowered(fn, *examples: Tensor) -> list[np.ndarray]:  # type: ignore[no-untyped-def]
    g, _, values, outs = lowered_graph(fn, *examples)
    outs = [outs] if isinstance(outs, np.ndarray) else list(outs)
    return [np.array(evaluate(g, [int(x) for x in np.asarray(o).reshape(-1)], values), dtype=float).reshape(np.shape(o)) for o in outs]


def test_lowered_linear_algebra_matches_torch() -> None:
    g = torch.Generator().manual_seed(0)
    a = torch.randn(2, 4, 4, dtype=F64, generator=g)
    spd = a @ a.mT + torch.eye(4, dtype=F64)
    low = torch.linalg.cholesky(spd)
    b = torch.randn(2, 4, 3, dtype=F64, generator=g)
    wide = torch.randn(2, 3, 7, dtype=F64, generator=g)
    cases = [
        (lambda x: torch.linalg.cholesky_ex(x)[0], (spd,)),
        (lambda l_, y: torch.linalg.solve_triangular(l_, y, upper=False), (low, b)),
        (lambda l_, y: torch.linalg.solve_triangular(l_.mT, y, upper=True), (low, b)),
        (lambda l_, y: torch.cholesky_solve(y, l_), (low, b)),
        (lambda x: torch.linalg.qr(x.mT)[1], (wide,)),
        (lambda x: torch.linalg.qr(x.mT)[0], (wide,)),
        (tria, (wide,)),
        (lambda l_, y: chol_rank1_update(l_, 0.3 * y[..., 0], -1.0), (low, b)),
        (lambda x: torch.logsumexp(x, -1), (b,)),
        (lambda x: torch.log_softmax(x, -2), (b,)),
        (lambda x: torch.nn.functional.softplus(x * 30.0), (b,)),
        (lambda x, y: torch.atan2(x, y) + torch.where(x > y, x.exp(), y.sin()), (b, b.flip(-1))),
    ]
    for fn, ex in cases:
        want = fn(*ex)
        (got,) = _lowered(fn, *ex)
        np.testing.assert_allclose(got, want.numpy(), rtol=1e-12, atol=1e-12)


def test_lowered_cholesky_clamps_only_bad_pivots() -> None:
    good = torch.tensor([[4.0, 1.0], [1.0, 3.0]], dtype=F64)
    bad = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=F64)  # indefinite: second pivot negative
    mats = torch.stack([good, bad])
    chol, clamps = _lowered(lambda x: torch.linalg.cholesky_ex(x), mats)
    np.testing.assert_allclose(chol[0], torch.linalg.cholesky(good).numpy(), rtol=1e-14)
    assert clamps.tolist() == [0.0, 1.0]
    assert np.isfinite(chol[1]).all()


@pytest.mark.parametrize("kind", ["ekf", "ukf-augmented"])
def test_non_additive_noise_runs_on_the_generated_and_eager_engines(kind: str) -> None:
    """Noise entering linearly through G w / D v: the filter equals the additive Kalman filter with
    G Q G^T and D R D^T (an independent reference), on the generated engine and on the inductor
    engine's step (eager), both of which run the filter's own equations."""
    noisy, additive = linear_noise_models()
    filt = EKF(noisy) if kind == "ekf" else UKF(noisy, noise="augmented")
    g = torch.Generator().manual_seed(1)
    z = torch.randn(3, 12, 2, generator=g, dtype=F64).cumsum(1)
    mask = torch.rand(3, 12, 2, generator=g) > 0.25
    m0, p0 = torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
    ref = KalmanFilter(additive)(z, m0, p0, mask=mask)
    for out in (generated(filt)(z, m0, p0, mask=mask), FusedFilter(filt, engine="eager")(z, m0, p0, mask=mask)):
        for name in FIELDS:
            torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=0, atol=1e-10, msg=name)


def test_a_smoother_runs_on_the_generated_engines_result() -> None:
    """``Smoother.smooth`` of FusedFilter's result (non-contiguous views) equals the smoother run
    end to end on the reference filter, gradients included."""
    model, z, u, m0, p0 = _range_bearing_data()
    filt = UKF(model)
    smoother = make_smoother(filt)
    initial = filt.initial_belief(m0, p0, batch_size=z.shape[0])
    ref = smoother(z, m0, p0, controls=u)
    out = smoother.smooth(generated(filt)(z, m0, p0, controls=u), initial, controls=u)
    torch.testing.assert_close(out.mean, ref.mean, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(out.cov, ref.cov, rtol=1e-9, atol=1e-10)
    params = [p for p in filt.parameters() if p.requires_grad]
    g_out = torch.autograd.grad(out.mean.square().sum(), params)
    g_ref = torch.autograd.grad(ref.mean.square().sum(), params)
    for a, b in zip(g_out, g_ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10)
