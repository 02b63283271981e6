"""The inputs-only transition of p003's SINS model, computed once per run (``precompute_controls``).

References: the model's own per-step path (``matrix`` of one step's inputs, which computes
``expm(F dt)`` itself) and the filters' online ``step`` loop, which never precomputes; values and
gradients must agree to rounding.
"""

from __future__ import annotations

import pytest
import torch

from difffilter.engines import FusedFilter
from difffilter.filters import SimplifiedUKF
from difffilter.filters.base import slice_controls
from experiments.papers.p003 import p003_imm, p003_mode_model, simulate
from experiments.papers.p003.sins import SinsErrorDynamics
from experiments.papers.p003.sins_measurement import SinsPseudorangeMeasurement

F64 = torch.float64


@pytest.fixture(scope="module")
def flights():
    return simulate(3, 5, F64, duration=12, profile="random", num_satellites=6, feedback="imm")


def _opts(discretization: str = "expm", metres: bool = True) -> dict:
    return {"num_satellites": 6, "linearized": False, "position_in_metres": metres, "discretization": discretization}


def _run_steps(filt, sc, controls):
    """The online loop (``step``): every step builds its own transition."""
    belief = filt.initial_belief(sc.initial_mean, sc.initial_cov, controls=slice_controls(controls, 0))
    means, covs, lls = [], [], []
    for t in range(sc.measurements.shape[1]):
        belief, _, info = filt.step(belief, sc.measurements[:, t], None if sc.mask is None else sc.mask[:, t], slice_controls(controls, t))
        means.append(belief["mean"])
        covs.append(belief["cov"])
        lls.append(info.log_likelihood)
    return torch.stack(means, 1), torch.stack(covs, 1), torch.stack(lls, 1)


def _grads(filt, loss):
    params = [p for p in filt.parameters() if p.requires_grad]
    return torch.autograd.grad(loss, params)


@pytest.mark.parametrize("discretization", ["expm", "first", "second"])
@pytest.mark.parametrize("metres", [True, False])
def test_precomputed_transition_equals_per_step_matrix(flights, discretization: str, metres: bool) -> None:
    dyn = SinsErrorDynamics(discretization=discretization, position_in_metres=metres)
    u = dict(flights.controls)
    out = dyn.precompute_controls(u)
    key = dyn.transition_key
    assert key in out and key not in u  # the caller's dict is left alone
    steps = u["llh"].shape[1]
    ref = torch.stack([dyn.matrix(slice_controls(u, t)) for t in range(steps)], 1)
    phi = out[key]
    assert phi.shape == (3, steps, 20, 20)
    scale = ref.abs().amax(dim=(-2, -1), keepdim=True)
    assert torch.allclose(phi, ref, rtol=0, atol=1e-12 * float(scale.max()))
    # matrix() of a step reads the entry: the same tensor values as the per-step computation
    assert torch.equal(dyn.matrix(slice_controls(out, 4)), phi[:, 4])
    # a second call finds the key and adds nothing
    assert dyn.precompute_controls(out) is out


def test_keys_differ_between_configurations() -> None:
    keys = {
        SinsErrorDynamics(discretization=d, position_in_metres=m, gyro_markov_time=g).transition_key
        for d in ("expm", "first", "second")
        for m in (True, False)
        for g in (3600.0, 1800.0)
    }
    assert len(keys) == 12
    assert SinsErrorDynamics().transition_key == SinsErrorDynamics(Q_structure="diagonal").transition_key


@pytest.mark.parametrize("discretizations", [("expm", "expm"), ("expm", "first")])
def test_imm_forward_equals_step_loop_values_and_gradients(flights, discretizations) -> None:
    imm = p003_imm(model=_opts(), q_scales=(1.0, 1.0e4), r_scales=(1.0, 100.0), transition=((0.95, 0.05), (0.1, 0.9)))
    if discretizations[1] != "expm":
        imm.filters[1].model.dynamics.discretization = discretizations[1]
    u = dict(flights.controls)
    res = imm(flights.measurements, flights.initial_mean, flights.initial_cov, mask=flights.mask, controls=u)
    means, covs, lls = _run_steps(imm, flights, u)
    assert torch.allclose(res.mean, means, rtol=1e-12, atol=1e-12)
    assert torch.allclose(res.cov, covs, rtol=1e-10, atol=1e-14)
    assert torch.allclose(res.log_likelihood, lls, rtol=1e-12, atol=1e-10)
    g_fast = _grads(imm, res.log_likelihood.sum())
    g_ref = _grads(imm, lls.sum())
    assert len(g_fast) >= 5  # Q and R of both modes, transition, initial probabilities
    for a, b in zip(g_fast, g_ref, strict=True):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-12 * (1.0 + float(b.abs().max())))


def test_imm_modes_of_one_configuration_share_one_transition(flights, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    original = SinsErrorDynamics._transition

    def counting(self, u):
        calls.append(u["llh"].shape[:-1])
        return original(self, u)

    monkeypatch.setattr(SinsErrorDynamics, "_transition", counting)
    imm = p003_imm(model=_opts(), transition=((0.95, 0.05), (0.1, 0.9)))
    steps = flights.measurements.shape[1]
    imm(flights.measurements, flights.initial_mean, flights.initial_cov, mask=flights.mask, controls=dict(flights.controls))
    assert calls == [torch.Size([3, steps])]  # one batched call for both modes and every step
    calls.clear()
    imm.filters[1].model.dynamics.discretization = "second"
    imm(flights.measurements, flights.initial_mean, flights.initial_cov, mask=flights.mask, controls=dict(flights.controls))
    assert calls == [torch.Size([3, steps])] * 2  # different settings: one each


def test_float32_forward_equals_step_loop(flights) -> None:
    model = p003_mode_model(dtype="float32", **_opts())
    filt = SimplifiedUKF(model)
    u = {k: v.float() for k, v in flights.controls.items()}
    z = flights.measurements.float()
    sc = type("S", (), {"measurements": z, "mask": flights.mask, "initial_mean": flights.initial_mean.float(),
                        "initial_cov": flights.initial_cov.float()})  # fmt: skip
    res = filt(z, sc.initial_mean, sc.initial_cov, mask=flights.mask, controls=u)
    means, _, lls = _run_steps(filt, sc, u)
    assert res.mean.dtype == torch.float32
    assert torch.allclose(res.mean, means, rtol=1e-4, atol=1e-3)
    assert torch.allclose(res.log_likelihood, lls, rtol=1e-4, atol=1e-2)


def test_fused_eager_engine_uses_the_precomputed_transition(flights) -> None:
    filt = SimplifiedUKF(p003_mode_model(**_opts()))
    u = dict(flights.controls)
    ref = filt(flights.measurements, flights.initial_mean, flights.initial_cov, mask=flights.mask, controls=u)
    fused = FusedFilter(filt, engine="eager")
    out = fused(flights.measurements, flights.initial_mean, flights.initial_cov, mask=flights.mask, controls=u)
    assert torch.allclose(out.mean, ref.mean, rtol=1e-10, atol=1e-10)
    assert torch.allclose(out.log_likelihood, ref.log_likelihood, rtol=1e-10, atol=1e-9)


def test_bad_precomputed_entry_is_rejected(flights) -> None:
    dyn = SinsErrorDynamics()
    u = dict(flights.controls)
    with pytest.raises(ValueError, match=r"sins\.Phi.*\[B, T, 20, 20\]"):
        dyn.precompute_controls({**u, dyn.transition_key: torch.zeros(3, 2, 20, 20, dtype=F64)})
    with pytest.raises(ValueError, match=r"sins\.Phi"):
        dyn.precompute_controls({**u, dyn.transition_key: "phi"})
    # inputs without the SINS entries (or a plain tensor) pass through; the step reports what is missing
    partial = {k: v for k, v in u.items() if k != "f_n"}
    assert dyn.precompute_controls(partial) is partial
    tensor = torch.zeros(3, 4, 2)
    assert dyn.precompute_controls(tensor) is tensor
    with pytest.raises(KeyError, match="f_n"):
        dyn.matrix(slice_controls(partial, 0))
    no_dt = {k: v for k, v in u.items() if k != "dt"}
    assert dyn.precompute_controls(no_dt) is no_dt  # no dt anywhere: nothing to precompute
    with pytest.raises(KeyError, match="dt"):
        dyn.matrix(slice_controls(no_dt, 0))


@pytest.mark.parametrize("metres", [True, False])
@pytest.mark.parametrize("rates", [True, False])
def test_precomputed_measurement_geometry_equals_per_step(flights, metres: bool, rates: bool) -> None:
    meas = SinsPseudorangeMeasurement(num_satellites=6, position_in_metres=metres, rates=rates)
    u = dict(flights.controls)
    out = meas.precompute_controls(u)
    added = {"sins.los", "sins.range", "sins.scale"} | ({"sins.ins_rate"} if rates else set())
    assert set(out) - set(u) == added
    g = torch.Generator().manual_seed(4)
    x = torch.randn(3, 7, 20, generator=g, dtype=F64) * (3.0 if metres else 5e-7)  # 7 points per trajectory
    for t in (0, 5, 11):
        plain = meas(x, {k: v[:, t, None] for k, v in u.items()})
        fast = meas(x, {k: v[:, t, None] for k, v in out.items()})
        assert torch.allclose(fast, plain, rtol=1e-13, atol=1e-12)
    # a linearized model, or inputs without satellites, derive nothing
    lin = SinsPseudorangeMeasurement(num_satellites=6, linearized=True)
    assert lin.precompute_controls(u) is u
    no_sat = {k: v for k, v in u.items() if k != "sat_pos"}
    assert meas.precompute_controls(no_sat) is no_sat


def test_online_step_builds_one_transition_per_step_for_all_modes(flights, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    original = SinsErrorDynamics._transition
    monkeypatch.setattr(SinsErrorDynamics, "_transition", lambda self, u: calls.append(1) or original(self, u))
    imm = p003_imm(model=_opts(), transition=((0.95, 0.05), (0.1, 0.9)))
    u = dict(flights.controls)
    belief = imm.initial_belief(flights.initial_mean, flights.initial_cov, 3, controls=slice_controls(u, 0))
    calls.clear()
    for t in range(4):
        belief, _, _ = imm.step(
            belief, flights.measurements[:, t], None if flights.mask is None else flights.mask[:, t], slice_controls(u, t)
        )
    assert len(calls) == 4


def test_forward_builds_derived_inputs_in_bounded_blocks(flights, monkeypatch: pytest.MonkeyPatch) -> None:
    import difffilter.filters.base as base

    imm = p003_imm(model=_opts(), transition=((0.95, 0.05), (0.1, 0.9)))
    args = (flights.measurements, flights.initial_mean, flights.initial_cov)
    whole = imm(*args, mask=flights.mask, controls=dict(flights.controls))
    calls = []
    original = SinsErrorDynamics._transition
    monkeypatch.setattr(SinsErrorDynamics, "_transition", lambda self, u: calls.append(u["llh"].shape[1]) or original(self, u))
    monkeypatch.setattr(base, "PRECOMPUTE_BLOCK", 15)  # B = 3: blocks of 5 steps
    blocks = imm(*args, mask=flights.mask, controls=dict(flights.controls))
    assert calls == [5, 5, 2]  # T = 12
    assert torch.allclose(blocks.mean, whole.mean, rtol=1e-12, atol=1e-12)
    assert torch.allclose(blocks.log_likelihood, whole.log_likelihood, rtol=1e-12, atol=1e-10)
