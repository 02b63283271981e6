"""The inductor engine of FusedFilter runs the filter's own step: checks against the reference filters.

* the whole :class:`FilterContract` battery with ``FusedFilter(engine="eager")`` (the inductor
  engine's step uncompiled: the filter's own ``predict``/``update`` with the element-wise
  linear algebra and branch-free helpers that the compiled graph runs, on CPU or CUDA) for KF,
  EKF, UKF, SimplifiedUKF, SquareRootUKF and IMM; with ``engine="inductor"`` (compiled) under
  ``-m slow`` (minutes of compilation per class);
* every filter and mixer kind of the generated engine's tests: outputs, extras, final belief
  and gradients (parameters, initial belief, measurements) equal to the reference's at float64
  ``1e-9`` (gradients ``1e-8``), with masks, controls and a wrapped bearing;
* dynamo captures each step as one graph with no graph break and no LAPACK call left (cheap:
  no inductor compilation); a compiled SquareRootUKF (the QR path) equals its reference
  (``-m slow``; a compiled UKF, forward and backward, runs in ``tests/test_fused.py``);
* the element-wise primitives against torch's LAPACK-backed ones, values and gradients.
"""

from __future__ import annotations

import copy
import re

import pytest
import torch
from torch.nn.utils import parametrize

from difffilter.engines import FusedFilter
from difffilter.engines.branchfree import branch_free
from difffilter.engines.step import SmallLinalg, cholesky_lower, householder_qr, solve_triangular
from difffilter.filters import EKF, UKF, KalmanFilter, MerweScaled, SimplifiedUKF, SquareRootUKF
from difffilter.mixers import IMM
from difffilter.models import LinearModel
from tests.filter_contract import FilterContract, cv_matrices, make_data
from tests.test_fused import FIELDS, _range_bearing_data
from tests.test_fused_generated import KINDS, assert_same_run

F64 = torch.float64


def _imm(model):  # type: ignore[no-untyped-def]
    other = copy.deepcopy(model)
    with torch.no_grad():
        other.load_state_dict(model.state_dict())
    pi = torch.tensor([[0.9, 0.1], [0.3, 0.7]], dtype=next(model.parameters()).dtype)
    return IMM([KalmanFilter(model), EKF(other)], transition=pi, initial_probs=torch.tensor([0.4, 0.6], dtype=pi.dtype))


# -- the contract battery ---------------------------------------------------------------------
class _Eager(FilterContract):
    engine = "eager"

    def fused(self, filt):  # type: ignore[no-untyped-def]
        return FusedFilter(filt, engine=self.engine)


class TestEagerKalmanFilter(_Eager):
    def make_filter(self, model):  # type: ignore[no-untyped-def]
        return self.fused(KalmanFilter(model))


class TestEagerEKF(_Eager):
    def make_filter(self, model):  # type: ignore[no-untyped-def]
        return self.fused(EKF(model))


class TestEagerUKF(_Eager):
    def make_filter(self, model):  # type: ignore[no-untyped-def]
        return self.fused(UKF(model, sigma_points=MerweScaled(alpha=1.0, beta=2.0, kappa=0.0)))


class TestEagerSimplifiedUKF(_Eager):
    def make_filter(self, model):  # type: ignore[no-untyped-def]
        return self.fused(SimplifiedUKF(model))


class TestEagerSquareRootUKF(_Eager):
    def make_filter(self, model):  # type: ignore[no-untyped-def]
        return self.fused(SquareRootUKF(model))


class TestEagerIMMOfEqualModes(_Eager):
    """An IMM whose two modes are the same linear model is that model's Kalman filter."""

    def make_filter(self, model):  # type: ignore[no-untyped-def]
        return self.fused(_imm(model))


_NO_FALLBACK = pytest.mark.filterwarnings("error:FusedFilter")  # a compiler failure must not pass as the eager step


# the same battery compiled (minutes of compilation per class): TestInductorKalmanFilter, ...
for _eager in (TestEagerKalmanFilter, TestEagerEKF, TestEagerUKF, TestEagerSimplifiedUKF, TestEagerSquareRootUKF, TestEagerIMMOfEqualModes):
    _name = _eager.__name__.replace("Eager", "Inductor")
    globals()[_name] = pytest.mark.slow(_NO_FALLBACK(type(_name, (_eager,), {"engine": "inductor"})))


# -- every filter and mixer kind against its reference ----------------------------------------
def _outputs_and_gradients(filt, run_filter, z, u, m0, p0):  # type: ignore[no-untyped-def]
    mask = torch.ones(z.shape, dtype=torch.bool)
    mask[0, 4] = False
    mask[2, 6, 1] = False
    zz = z.masked_fill(~mask, float("nan")).requires_grad_(True)
    mm, pp = m0.clone().requires_grad_(True), p0.clone().requires_grad_(True)
    out = run_filter(zz, mm, pp, mask=mask, controls=u)
    loss = out.log_likelihood.sum() + 0.01 * out.mean.sum()
    params = [p for p in filt.parameters() if p.requires_grad]
    return out, torch.autograd.grad(loss, [zz, mm, pp, *params], allow_unused=True)


@pytest.mark.parametrize("kind", list(KINDS))
def test_eager_engine_equals_reference_outputs_and_gradients(kind: str) -> None:
    """Every kind the generated engine runs (UKF variants, EKF, SquareRootUKF, RCUKF,
    ColoredNoiseUKF, IMM, Blend), B = 5, masks with NaN underneath, controls, a wrapped bearing."""
    model, z, u, m0, p0 = _range_bearing_data(batch=5, steps=12)
    filt = KINDS[kind](model)
    ref, g_ref = _outputs_and_gradients(filt, filt, z, u, m0, p0)
    fused = FusedFilter(filt, engine="eager")
    out, g_out = _outputs_and_gradients(filt, fused, z, u, m0, p0)
    assert fused.last_engine == "eager"
    assert_same_run(out, ref, g_out, g_ref)
    assert set(out.final_belief) == set(ref.final_belief)
    assert float(out.extras["cholesky_clamps"].sum()) == 0.0


class _JointPrediction:
    """Mixed into a linear model's dynamics: ``linear_prediction`` returns ``(f(x), F, Q)`` from
    one call (counted), the form SimplifiedUKF prefers."""

    calls: list[int] = []

    def linear_prediction(self, x, u=None):  # type: ignore[no-untyped-def]
        _JointPrediction.calls.append(1)
        return self(x, u), self.matrix(u), self.process_noise(x, u)


def test_simplified_ukf_linear_prediction_runs_on_the_eager_engine() -> None:
    model = LinearModel(**cv_matrices())
    dyn = model.dynamics
    dyn.__class__ = type("JointLinearDynamics", (_JointPrediction, type(dyn)), {})
    filt = SimplifiedUKF(model)
    z = make_data(3, 10, 2, seed=2)
    m0, p0 = torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
    ref = filt(z, m0, p0)
    before = len(_JointPrediction.calls)
    out = FusedFilter(filt, engine="eager")(z, m0, p0)
    assert len(_JointPrediction.calls) - before == 10  # the joint prediction is what ran
    plain = KalmanFilter(LinearModel(**cv_matrices()))(z, m0, p0)  # an independent reference
    for name in FIELDS:
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=1e-9, atol=1e-10, msg=name)
        torch.testing.assert_close(getattr(out, name), getattr(plain, name), rtol=1e-8, atol=1e-9, msg=name)


# -- what the compiler sees -------------------------------------------------------------------
_LAPACK = re.compile(r"cholesky|solve|matmul|bmm|linalg|(^|_)qr$|^mm$")


@pytest.mark.parametrize("kind", ["kf", "ekf-autodiff", "ukf-reuse", "square-root", "imm"])
def test_dynamo_captures_each_step_as_one_graph_without_lapack(kind: str) -> None:
    model, z, u, m0, p0 = _range_bearing_data(batch=4, steps=3)
    if kind == "kf":
        model, z, u = LinearModel(**cv_matrices()), make_data(4, 3, 2), None
        m0, p0 = torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
    filt = KalmanFilter(model) if kind == "kf" else KINDS[kind](model)
    engine = FusedFilter(filt, engine="eager")._inductor
    belief = filt.initial_belief(m0, p0, batch_size=4)
    ctrl = [None if u is None else u[:, t] for t in range(3)]
    with parametrize.cached(), branch_free():
        belief = engine.step(belief, z[:, 0], None, ctrl[0])[0]  # the steady layout
        explained = torch._dynamo.explain(engine.step)(belief, z[:, 1], None, ctrl[1])
    assert explained.graph_count == 1 and explained.graph_break_count == 0, explained.break_reasons
    nodes = [node for g in explained.graphs for node in g.graph.nodes if node.op in ("call_function", "call_method")]
    called = {getattr(node.target, "__name__", str(node.target)) for node in nodes}
    assert "sqrt" in called and "stack" in called  # the names are read
    assert not [t for t in called if _LAPACK.search(t)], called


@pytest.mark.slow
@_NO_FALLBACK
def test_compiled_square_root_ukf_equals_reference() -> None:
    """The compiled QR path (tria), no gradient (about a minute of compilation)."""
    model, z, u, m0, p0 = _range_bearing_data(batch=3, steps=6)
    filt = SquareRootUKF(model)
    fused = FusedFilter(filt, engine="inductor")
    with torch.no_grad():
        out, ref = fused(z, m0, p0, controls=u), filt(z, m0, p0, controls=u)
    assert fused.last_engine == "inductor" and not fused._compile_failed
    for name in FIELDS:
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=1e-9, atol=1e-10, msg=name)
    torch.testing.assert_close(out.final_belief["scale_tril"], ref.final_belief["scale_tril"], rtol=1e-9, atol=1e-10)


# -- the primitives ---------------------------------------------------------------------------
def _spd(*lead: int, n: int = 4, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(*lead, n, n + 2, generator=g, dtype=F64)
    return a @ a.mT + 0.1 * torch.eye(n, dtype=F64)


def test_cholesky_lower_gradient_is_torchs() -> None:
    """Symmetric, as torch's, also for a matrix that is not exactly symmetric (values and clamps:
    ``tests/test_fused.py``)."""
    a = _spd(3, seed=1)
    a = (a + 1e-3 * torch.randn(3, 4, 4, generator=torch.Generator().manual_seed(2), dtype=F64)).requires_grad_(True)
    w = torch.randn(3, 4, 4, generator=torch.Generator().manual_seed(3), dtype=F64)
    (g_ours,) = torch.autograd.grad((cholesky_lower(a)[0] * w).sum(), a)
    sym = 0.5 * (a + a.mT)
    (g_ref,) = torch.autograd.grad((torch.linalg.cholesky(sym) * w).sum(), a)
    torch.testing.assert_close(g_ours, g_ref, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("upper", [False, True])
@pytest.mark.parametrize("left", [True, False])
@pytest.mark.parametrize("unit", [False, True])
def test_solve_triangular_equals_lapack_with_broadcasting(upper: bool, left: bool, unit: bool) -> None:
    g = torch.Generator().manual_seed(5)
    a = torch.randn(2, 1, 4, 4, generator=g, dtype=F64) + 4 * torch.eye(4, dtype=F64)
    b = torch.randn(3, 4, 2, generator=g, dtype=F64) if left else torch.randn(3, 2, 4, generator=g, dtype=F64)
    ours = solve_triangular(a, b, upper=upper, left=left, unitriangular=unit)
    ref = torch.linalg.solve_triangular(a, b, upper=upper, left=left, unitriangular=unit)
    torch.testing.assert_close(ours, ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("shape", [(6, 3), (3, 3), (3, 5)])
def test_householder_qr_equals_lapack(shape: tuple[int, int]) -> None:
    g = torch.Generator().manual_seed(7)
    a = torch.randn(2, *shape, generator=g, dtype=F64)
    a[1, 1:, 0] = 0.0  # nothing below the first pivot: no reflection
    q, r = householder_qr(a)
    q_ref, r_ref = torch.linalg.qr(a)
    torch.testing.assert_close(r, r_ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(q, q_ref, rtol=1e-12, atol=1e-12)
    assert householder_qr(a, "r")[1].shape == r.shape
    with pytest.raises(ValueError, match="mode"):
        householder_qr(a, "complete")


def test_the_mode_replaces_lapack_and_keeps_gradients() -> None:
    """Inside SmallLinalg, cholesky_ex/cholesky/solve_triangular/cholesky_solve/qr/matmul give
    torch's values and gradients (gradcheck), and ``info`` counts clamped pivots."""
    a = _spd(2, n=3, seed=9).requires_grad_(True)
    b = torch.randn(2, 3, 2, generator=torch.Generator().manual_seed(4), dtype=F64, requires_grad=True)

    def chain(a, b):  # type: ignore[no-untyped-def]
        low, info = torch.linalg.cholesky_ex(a)
        x = torch.cholesky_solve(b, low) + torch.linalg.solve_triangular(torch.linalg.cholesky(a).mT, b, upper=True)
        r = torch.linalg.qr(torch.cat([low, b], -1).mT).R
        return (a @ x).sum() + (r.diagonal(dim1=-2, dim2=-1).abs() ** 2).sum() + info.sum()

    with SmallLinalg():
        ours = chain(a, b)
        assert torch.autograd.gradcheck(chain, (a, b))
        assert int(torch.linalg.cholesky_ex(-torch.eye(2, dtype=F64)).info) == 2
    ref = chain(a, b)
    torch.testing.assert_close(ours, ref, rtol=1e-12, atol=1e-12)
    g_ours = torch.autograd.grad(ours, (a, b))
    g_ref = torch.autograd.grad(ref, (a, b))
    for x, y in zip(g_ours, g_ref, strict=True):
        torch.testing.assert_close(x, y, rtol=1e-10, atol=1e-12)
