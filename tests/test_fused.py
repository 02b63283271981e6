"""FusedFilter's inductor engine (the filter's own step, element-wise linear algebra) against the reference filters.

Most tests run the step eagerly (``compile=False``): the same code ``torch.compile`` fuses,
with the same element-wise primitives, so equality with the reference filters checks what the
compiled graph computes; one small model is also compiled (forward and backward) in the default
run, the benchmark model under ``-m slow``.  More in ``tests/test_fused_inductor.py``.
"""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from difffilter.engines import FusedFilter, fuse
from difffilter.engines.step import cholesky_lower as _chol
from difffilter.filters import (
    EKF,
    RCUKF,
    UKF,
    Cubature,
    Julier,
    KalmanFilter,
    MerweScaled,
    SimplifiedUKF,
    SquareRootUKF,
)
from difffilter.models import tracking_model
from difffilter.models.base import DynamicsModel, MeasurementModel, StateSpaceModel, wrap_angle
from difffilter.models.motion import Singer
from difffilter.params import register_covariance
from experiments.benchmarks.cases import builtin_case
from experiments.benchmarks.gpsdr import make_gpsdr_model, simulate_gpsdr
from experiments.benchmarks.runner import BenchSettings

F64 = torch.float64
FIELDS = ("mean", "cov", "prior_mean", "prior_cov", "log_likelihood", "nis", "num_observed")


class _Pushed(DynamicsModel):
    """Constant velocity in 2-D pushed by an acceleration control ``u [.., 2]``."""

    def __init__(self, dt: float = 0.5) -> None:
        super().__init__()
        self.state_dim, self.dt = 4, dt
        register_covariance(self, "Q", torch.diag(torch.tensor([0.01, 0.01, 0.1, 0.1], dtype=F64)), "diagonal")

    def forward(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        px, py, vx, vy = x.unbind(-1)
        ax, ay = (torch.zeros_like(px), torch.zeros_like(px)) if u is None else u.unbind(-1)
        dt = self.dt
        return torch.stack([px + dt * vx + 0.5 * dt * dt * ax, py + dt * vy + 0.5 * dt * dt * ay, vx + dt * ax, vy + dt * ay], -1)


class _RangeBearing(MeasurementModel):
    """Range and bearing from the origin; the bearing residual is wrapped to (-pi, pi]."""

    def __init__(self) -> None:
        super().__init__()
        self.measurement_dim = 2
        self.angular = (1,)  # the bearing wraps (residual); undeclared, the unscented filters refuse it
        register_covariance(self, "R", torch.diag(torch.tensor([0.25, 0.01], dtype=F64)), "diagonal")

    def forward(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        px, py = x[..., 0], x[..., 1]
        return torch.stack([torch.sqrt(px * px + py * py), torch.atan2(py, px)], -1)

    def residual(self, z: Tensor, z_ref: Tensor) -> Tensor:
        r = z - z_ref
        return torch.cat([r[..., :1], wrap_angle(r[..., 1:])], -1)


def _range_bearing_data(batch: int = 3, steps: int = 15, seed: int = 0) -> tuple[StateSpaceModel, Tensor, Tensor, Tensor, Tensor]:
    g = torch.Generator().manual_seed(seed)
    model = StateSpaceModel(_Pushed(), _RangeBearing())
    x = torch.tensor([-20.0, 0.5, 2.0, 0.1], dtype=F64).repeat(batch, 1) + torch.randn(batch, 4, generator=g, dtype=F64)
    u = 0.3 * torch.randn(batch, steps, 2, generator=g, dtype=F64)
    zs = []
    with torch.no_grad():
        for t in range(steps):
            x = model.dynamics(x, u[:, t])
            zs.append(model.measurement(x) + torch.randn(batch, 2, generator=g, dtype=F64) * torch.tensor([0.5, 0.1], dtype=F64))
    m0 = torch.tensor([-20.0, 0.5, 2.0, 0.1], dtype=F64)
    return model, torch.stack(zs, 1), u, m0, torch.eye(4, dtype=F64) * 2.0


def _singer_data(batch: int = 3, steps: int = 20) -> tuple[StateSpaceModel, Tensor, Tensor, Tensor]:
    model = tracking_model(dynamics=Singer(axes=2, dt=1.0, tau=8.0, sigma_a=0.7, dtype=F64), R=[4.0, 9.0])
    g = torch.Generator().manual_seed(3)
    z = torch.cumsum(torch.randn(batch, steps, 2, generator=g, dtype=F64), 1) * 3.0
    return model, z, torch.zeros(6, dtype=F64), torch.eye(6, dtype=F64) * 10.0


def _assert_same(out, ref, rtol: float = 1e-10) -> None:  # type: ignore[no-untyped-def]
    for name in FIELDS:
        a, b = getattr(out, name), getattr(ref, name)
        scale = b.abs().max().clamp_min(1.0)
        assert float((a - b).abs().max() / scale) < rtol, name


@pytest.mark.parametrize(
    "make",
    [
        pytest.param(lambda m: UKF(m), id="ukf-merwe-redraw"),
        pytest.param(lambda m: UKF(m, sigma_points=Julier(kappa=0.0), redraw_after_predict=False), id="ukf-julier-reuse"),
        pytest.param(lambda m: UKF(m, sigma_points=Cubature()), id="ukf-cubature"),
        pytest.param(
            lambda m: UKF(m, sigma_points=MerweScaled(alpha=0.5, beta=2.0, kappa=1.0), redraw_after_predict=False), id="ukf-merwe-reuse"
        ),
        pytest.param(lambda m: EKF(m), id="ekf-autodiff-joseph"),
        pytest.param(lambda m: EKF(m, joseph=False, jacobian_mode="rev"), id="ekf-rev-plain"),
    ],
)
def test_fused_equals_reference_with_controls_masks_and_angles(make) -> None:  # type: ignore[no-untyped-def]
    model, z, u, m0, p0 = _range_bearing_data()
    filt = make(model)
    mask = torch.ones(z.shape, dtype=torch.bool)
    mask[0, 3] = False  # a whole step missing
    mask[1, 5, 1] = False  # one component missing
    mask[2, 7:10, 0] = False
    z = z.masked_fill(~mask, float("nan"))  # values under a False mask never matter
    ref = filt(z, m0, p0, mask=mask, controls=u)
    fused = FusedFilter(filt, compile=False)
    out = fused(z, m0, p0, mask=mask, controls=u)
    _assert_same(out, ref)
    assert out.log_likelihood[0, 3] == 0 and float(out.num_observed[1, 5]) == 1.0
    assert float(out.cholesky_clamps.sum()) == 0.0
    with torch.no_grad():  # without autograd the outputs are written into preallocated buffers
        out_ng = fused(z, m0, p0, mask=mask, controls=u)
    _assert_same(out_ng, ref)
    assert torch.equal(out_ng.final_belief["cov"], out.final_belief["cov"].detach())


def test_output_buffers_are_reused_only_when_no_result_holds_them() -> None:
    model, z, u, m0, p0 = _range_bearing_data()
    filt = UKF(model)
    fused = FusedFilter(filt, compile=False)
    with torch.no_grad():
        ref = filt(z, m0, p0, controls=u)
        first = fused(z, m0, p0, controls=u)
        kept = first.cov.clone()
        second = fused(z * 1.01, m0, p0, controls=u)  # `first` is alive: new memory
        assert second.cov.data_ptr() != first.cov.data_ptr()
        assert torch.equal(first.cov, kept)
        ptr = second.cov.data_ptr()
        cov_np = second.cov.numpy()  # a NumPy view keeps the memory in use
        third = fused(z, m0, p0, controls=u)
        assert third.cov.data_ptr() != ptr
        del second, cov_np, first
        ptr = third.cov.data_ptr()
        kept = {name: getattr(third, name).clone() for name in FIELDS}
        del third
        fourth = fused(z, m0, p0, controls=u)  # nothing holds the last buffers: reused, results unchanged
        assert fourth.cov.data_ptr() == ptr
        _assert_same(fourth, ref)
        for name in FIELDS:
            assert torch.equal(getattr(fourth, name), kept[name]), name
        fresh = FusedFilter(filt, compile=False, reuse_buffers=False)
        fresh(z, m0, p0, controls=u)
        assert fresh._inductor.buffers.kept == []
        _assert_same(fresh(z, m0, p0, controls=u), ref)


@pytest.mark.parametrize("kind", ["kf", "ekf", "ukf", "sukf"])
def test_fused_equals_reference_on_learnable_singer_with_gradients(kind: str) -> None:
    """Singer's Q depends on learnable tau and sigma_a (computed inside the step); gradients of
    the total log-likelihood agree with the reference filter's."""
    model, z, m0, p0 = _singer_data()
    filt = {"kf": KalmanFilter, "ekf": EKF, "ukf": UKF, "sukf": SimplifiedUKF}[kind](model)
    fused = fuse(filt, compile=False)
    params = [p for p in filt.parameters() if p.requires_grad]
    assert len(params) >= 3
    ref = filt(z, m0, p0)
    g_ref = torch.autograd.grad(ref.log_likelihood.sum(), params)
    out = fused(z, m0, p0)
    g_out = torch.autograd.grad(out.log_likelihood.sum(), params)
    _assert_same(out, ref)
    for a, b in zip(g_out, g_ref, strict=False):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)


def test_fused_float32_tracks_float64() -> None:
    model, z, u, m0, p0 = _range_bearing_data(batch=4, steps=30)
    out64 = fuse(UKF(model), compile=False)(z, m0, p0, controls=u)
    model32 = model.to(torch.float32)
    out32 = fuse(UKF(model32), compile=False)(z.float(), m0.float(), p0.float(), controls=u.float())
    assert out32.mean.dtype == torch.float32
    rel = (out32.mean.double() - out64.mean).abs().max() / out64.mean.abs().max()
    assert float(rel) < 1e-4
    assert float((out32.log_likelihood.double() - out64.log_likelihood).abs().max()) < 1e-3


def test_one_absurd_trajectory_leaves_the_others_unchanged() -> None:
    model, z, u, m0, p0 = _range_bearing_data(batch=3)
    fused = fuse(UKF(model), compile=False)
    clean = fused(z, m0, p0, controls=u)
    bad = z.clone()
    bad[1] *= 1e150
    out = fused(bad, m0, p0, controls=u)
    for name in FIELDS:
        a, b = getattr(out, name), getattr(clean, name)
        assert torch.equal(a[[0, 2]], b[[0, 2]]), name


def test_belief_carry_over_equals_the_full_run() -> None:
    model, z, u, m0, p0 = _range_bearing_data(steps=20)
    fused = fuse(EKF(model), compile=False)
    full = fused(z, m0, p0, controls=u)
    first = fused(z[:, :8], m0, p0, controls=u[:, :8])
    second = fused(z[:, 8:], controls=u[:, 8:], belief=first.final_belief)
    torch.testing.assert_close(torch.cat([first.mean, second.mean], 1), full.mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(second.cov[:, -1], full.cov[:, -1], rtol=0, atol=1e-12)


def test_branch_free_cholesky_clamps_only_the_bad_element() -> None:
    g = torch.Generator().manual_seed(0)
    a = torch.randn(5, 7, 4, generator=g, dtype=F64)
    mats = torch.einsum("ikb,jkb->ijb", a, a) + torch.eye(5, dtype=F64)[..., None]
    mats[:, :, 2] = torch.ones(5, 5, dtype=F64)  # rank one: pivots 2..5 vanish
    mats[0, 0, 3] = float("nan")
    lf, clamps = _chol(mats.permute(2, 0, 1))  # batch-first, the reference filters' layout
    assert clamps.tolist()[0] == 0 and clamps.tolist()[1] == 0 and clamps[2] >= 4 and clamps[3] >= 1
    for b in (0, 1):
        torch.testing.assert_close(lf[b], torch.linalg.cholesky(mats[..., b]), rtol=1e-12, atol=1e-12)
    assert bool(torch.isfinite(lf[2]).all())
    recon = lf[2] @ lf[2].T
    assert float((recon - mats[..., 2]).abs().max()) < 1e-6


def test_unsupported_filters_and_bad_inputs_are_rejected() -> None:
    """Every engine accepts any filter (each runs the filter's own step; equality with the
    reference in tests/test_fused_inductor.py); bad filters and inputs are refused."""
    model, z, u, m0, p0 = _range_bearing_data()
    for engine in ("inductor", "eager", "generated"):
        for filt in (SquareRootUKF(model), RCUKF(model), UKF(model, noise="augmented")):
            assert FusedFilter(filt, engine=engine).engine == engine
    with pytest.raises(TypeError, match="RecursiveFilter"):
        FusedFilter(torch.nn.Linear(2, 2))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="engine must be one of"):
        FusedFilter(UKF(model), engine="fast")
    assert FusedFilter(RCUKF(model)).engine == "auto"
    fused = fuse(UKF(model), compile=False)
    with pytest.raises(ValueError, match=r"measurements must have shape \[B, T, 2\]"):
        fused(z[..., :1], m0, p0, controls=u)
    with pytest.raises(ValueError, match="initial_cov must be positive definite"):
        fused(z, m0, -p0, controls=u)
    with pytest.raises(ValueError, match="controls"):
        fused(z, m0, p0, controls=u[:, :3])
    with pytest.raises(ValueError, match="not masked"):
        fused(z.masked_fill(torch.zeros_like(z, dtype=torch.bool).index_fill(1, torch.tensor([2]), True), math.nan), m0, p0, controls=u)


def test_compiled_step_matches_reference_forward_and_backward() -> None:
    """The compiled path itself, on a small model (compiles in seconds)."""
    model, z, u, m0, p0 = _range_bearing_data(batch=5, steps=12)
    filt = UKF(model)
    params = [p for p in filt.parameters() if p.requires_grad]
    ref = filt(z, m0, p0, controls=u)
    g_ref = torch.autograd.grad(ref.log_likelihood.sum(), params)
    fused = FusedFilter(filt)
    with _no_fallback_warning():
        out = fused(z, m0, p0, controls=u)
        g_out = torch.autograd.grad(out.log_likelihood.sum(), params)
    _assert_same(out, ref, rtol=1e-9)
    for a, b in zip(g_out, g_ref, strict=False):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-12)
    assert not fused._compile_failed


class _no_fallback_warning:  # noqa: N801 - used as a context manager
    """Fails the test if FusedFilter falls back to the eager step."""

    def __enter__(self) -> None:
        import warnings

        self._ctx = warnings.catch_warnings(record=True)
        self._log = self._ctx.__enter__()
        warnings.simplefilter("always")

    def __exit__(self, *exc: object) -> None:
        self._ctx.__exit__(*exc)
        msgs = [str(w.message) for w in self._log if "FusedFilter" in str(w.message)]
        assert not msgs, msgs


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["kf", "ekf", "ukf"])
def test_compiled_benchmark_model_matches_reference(kind: str) -> None:
    """The inductor and generated engines on the benchmark model (the inductor build takes minutes)."""
    case = builtin_case(kind, F64, simulate_gpsdr(batch_size=16, steps=40, seed=2), BenchSettings())
    filt, z, m0, p0 = case.filter, case.measurements, case.initial_mean, case.initial_cov
    with torch.no_grad():
        ref = filt(z, m0, p0)
        for engine in ("inductor", "generated"):
            _assert_same(FusedFilter(filt, engine=engine)(z, m0, p0), ref, rtol=1e-9)


def test_gpsdr_model_fused_eager_equals_reference() -> None:
    data = simulate_gpsdr(batch_size=3, steps=25, seed=1)
    for filt in (UKF(make_gpsdr_model()), EKF(make_gpsdr_model(analytic_jacobian=False))):
        ref = filt(data.measurements, data.initial_mean, data.initial_cov)
        out = fuse(filt, compile=False)(data.measurements, data.initial_mean, data.initial_cov)
        _assert_same(out, ref)


def test_learner_trains_through_the_fused_step() -> None:
    """``FilterLearner(FusedFilter(filter))`` runs the same filter through FusedFilter: same
    outputs, same gradients, same parameter names (checkpoints stay interchangeable)."""
    import copy

    from difffilter.engines import FusedFilter
    from difffilter.learn.learner import FilterLearner, LearnerOptions

    model, z, m0, p0 = _singer_data()
    opts = LearnerOptions(initial_mean=m0, initial_cov=p0)
    plain = FilterLearner(UKF(model), "nll", options=opts)
    fused = FilterLearner(FusedFilter(UKF(copy.deepcopy(model)), compile=False), "nll", options=opts)
    assert isinstance(fused.engine, FusedFilter) and fused.filter is fused.engine.filter
    assert [n for n, _ in plain.named_parameters()] == [n for n, _ in fused.named_parameters()]
    assert plain.state_dict().keys() == fused.state_dict().keys()
    a, b = plain({"measurements": z}), fused({"measurements": z})
    _assert_same(b, a)
    pa = [p for p in plain.parameters() if p.requires_grad]
    pb = [p for p in fused.parameters() if p.requires_grad]
    for ga, gb in zip(torch.autograd.grad(a.log_likelihood.sum(), pa), torch.autograd.grad(b.log_likelihood.sum(), pb), strict=True):
        torch.testing.assert_close(gb, ga, rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="FusedFilter wrapping this learner's filter"):
        plain.set_engine(FusedFilter(UKF(model), compile=False))
    # any filter runs fused (its own step): a square-root UKF too
    sr = FilterLearner(SquareRootUKF(model), "nll", options=opts)
    sr.set_engine(FusedFilter(sr.filter, compile=False))
    _assert_same(sr({"measurements": z}), FilterLearner(SquareRootUKF(model), "nll", options=opts)({"measurements": z}))


def test_nan_under_the_mask_reaches_no_gradient() -> None:
    model, z, u, m0, p0 = _range_bearing_data()
    filt = UKF(model)
    mask = torch.ones(z.shape, dtype=torch.bool)
    mask[0, 4] = False
    mask[2, 6, 1] = False
    params = [p for p in filt.parameters() if p.requires_grad]
    clean = fuse(filt, compile=False)(z.masked_fill(~mask, 0.0), m0, p0, mask=mask, controls=u)
    g_clean = torch.autograd.grad(clean.log_likelihood.sum(), params)
    out = fuse(filt, compile=False)(z.masked_fill(~mask, float("nan")), m0, p0, mask=mask, controls=u)
    g_out = torch.autograd.grad(out.log_likelihood.sum(), params)
    assert all(bool(torch.isfinite(g).all()) for g in g_out)
    for a, b in zip(g_out, g_clean, strict=True):
        assert torch.equal(a, b)
    assert bool(torch.isfinite(out.mean).all()) and bool(torch.isfinite(out.cov).all())


def test_compile_options_plumbing() -> None:
    """threads / cpp_wrapper become inductor options unless the caller picks a compile mode;
    caller-given options win; bad thread counts are refused."""
    model, _z, _m0, _p0 = _singer_data()
    filt = KalmanFilter(model)
    assert FusedFilter(filt).compile_options == {"options": {"cpp.threads": 1, "cpp_wrapper": True}}
    opts = FusedFilter(filt, threads=None, cpp_wrapper=False).compile_options
    assert opts == {"options": {"cpp_wrapper": False}}
    given = FusedFilter(filt, compile_options={"options": {"cpp_wrapper": False, "cpp.threads": 2}}).compile_options
    assert given == {"options": {"cpp_wrapper": False, "cpp.threads": 2}}
    assert FusedFilter(filt, compile_options={"mode": "max-autotune"}).compile_options == {"mode": "max-autotune"}
    assert fuse(filt, cpp_wrapper=False, reuse_buffers=False).reuse_buffers is False
    with pytest.raises(ValueError, match="threads"):
        FusedFilter(filt, threads=0)
