"""The library behaves as its users expect: `help(cls.__init__)` documents the arguments,
`torch.compile(filter)` and unsupported dtypes fail with a message that says what to do,
`simulate(model, ...)` draws trajectories from one's own model, figures name the state
components and overlay the true mode, result tables summarise matrices."""

from __future__ import annotations

import inspect

import pytest
import torch
from matplotlib.figure import Figure

from difffilter import filters, mixers, models, params, sim, smoothers
from difffilter.filters import UKF, KalmanFilter
from difffilter.learn.plots import diagnostic_figures, state_labels
from difffilter.models import StateLayout, tracking_model
from difffilter.models.motion import ConstantVelocity
from difffilter.sim import sample_trajectories, simulate
from experiments.runner.reporting import _describe, parameter_summary, parameter_values

f64 = torch.float64
PUBLIC = [
    getattr(m, name)
    for m in (filters, mixers, models, params, sim, smoothers)
    for name in m.__all__
    if isinstance(getattr(m, name), type) and issubclass(getattr(m, name), torch.nn.Module)
]


def _model():
    return tracking_model(dynamics=ConstantVelocity(axes=2, dt=1.0, q=0.5, dtype=f64), R=[25.0, 25.0])


@pytest.mark.parametrize("cls", [c for c in PUBLIC if c.__init__ is not torch.nn.Module.__init__], ids=lambda c: c.__name__)
def test_init_help_describes_the_class(cls):
    # (abstract bases without a constructor of their own, DynamicsModel and MeasurementModel, take no arguments)
    doc = inspect.getdoc(cls.__init__) or ""
    assert doc and not doc.startswith("Initialize internal Module state"), f"help({cls.__name__}.__init__) shows nn.Module's text"
    if "__init__" in cls.__dict__:  # a class with its own constructor shows a signature of named arguments
        assert "*args" not in str(inspect.signature(cls)), cls


def test_ukf_init_help_is_the_ukf_documentation():
    doc = inspect.getdoc(UKF.__init__)
    assert "UKF" in doc and "sigma" in doc.lower()
    assert "sigma_points" in str(inspect.signature(UKF.__init__))


def test_input_checks_do_not_break_a_compiled_graph():
    # inside torch.compile only shapes and dtypes are checked (value checks read the data, which
    # breaks the graph at every call); eager calls keep every check
    model = _model()
    filt = KalmanFilter(model)
    z, m0, p0 = torch.randn(2, 3, 2, dtype=f64), torch.zeros(4, dtype=f64), torch.eye(4, dtype=f64)
    mask = torch.ones(2, 3, dtype=torch.bool)
    explained = torch._dynamo.explain(filt.check_inputs)(z, m0, p0, mask, None)
    assert explained.graph_break_count == 0, [str(b.reason)[:120] for b in explained.break_reasons]
    with pytest.raises(ValueError, match="non-finite"):
        filt(torch.full((2, 3, 2), float("nan"), dtype=f64), m0, p0)
    with pytest.raises(ValueError, match="positive definite"):
        filt(z, m0, -p0)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.int64])
def test_unsupported_dtypes_are_refused_by_name(dtype):
    model = _model()
    z = torch.ones(2, 3, 2).to(dtype)
    with pytest.raises(TypeError, match="float32 or float64"):
        KalmanFilter(model)(z, torch.zeros(4, dtype=f64), torch.eye(4, dtype=f64))
    if dtype.is_floating_point:  # a whole filter converted: the same message, not a Cholesky error
        filt = KalmanFilter(_model()).to(dtype)
        with pytest.raises(TypeError, match="float32 or float64"):
            filt(z, torch.zeros(4, dtype=dtype), torch.eye(4, dtype=dtype))


def test_simulate_is_the_library_sampler_on_ones_own_model():
    model = _model()
    m0, p0 = [0.0, 1.0, 0.0, 1.0], [10.0, 1.0, 10.0, 1.0]
    data = simulate(model, num_steps=20, batch_size=5, seed=3, initial_mean=m0, initial_cov=p0)
    ref = sample_trajectories(model, batch_size=5, num_steps=20, initial_mean=m0, initial_cov=p0, seed=3)
    assert torch.equal(data.truth, ref.truth) and torch.equal(data.measurements, ref.measurements)
    assert data.truth.shape == (5, 20, 4) and data.measurements.shape == (5, 20, 2)
    res = UKF(model)(data.measurements, data.initial_mean, data.initial_cov)
    assert torch.isfinite(res.mean).all()
    # the model's defaults fill the belief when it has them (models.motion: none -> a clear error)
    with pytest.raises(ValueError, match="initial_mean"):
        simulate(model, num_steps=2)
    # per-trajectory controls pass through
    u = {"dt": torch.ones(5, 20, 1, dtype=f64)}
    assert simulate(model, num_steps=20, batch_size=5, initial_mean=m0, initial_cov=p0, controls=u).controls["dt"].shape == (5, 20, 1)


def test_figures_use_layout_names_and_overlay_the_true_mode():
    layout = StateLayout(names=("x", "vx", "y", "vy"), units=("m", "m/s", "m", "m/s"), position=(0, 2))
    assert state_labels([0, 2], layout) == ["x [m]", "y [m]"] and state_labels([5]) == ["state[5]"]
    t = 30
    truth, mean = torch.randn(t, 4, dtype=f64), torch.randn(t, 4, dtype=f64)
    probs = torch.softmax(torch.randn(t, 2, dtype=f64), -1)
    modes = (torch.arange(t) >= 15).long()
    figs = diagnostic_figures(
        {"truth": truth, "mean": mean, "cov": torch.eye(4, dtype=f64).expand(t, 4, 4), "mode_probs": probs, "modes": modes},
        position_index=[0, 2],
        layout=layout,
    )
    assert set(figs) == {"trajectory", "error", "mode_probs"} and all(isinstance(f, Figure) for f in figs.values())
    ax = figs["trajectory"].axes[0]
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x [m]", "y [m]")
    assert [a.get_ylabel() for a in figs["error"].axes] == ["x [m]", "y [m]"]
    labels = [line.get_label() for line in figs["mode_probs"].axes[0].get_lines()]
    assert "true mode" in labels
    true_line = next(line for line in figs["mode_probs"].axes[0].get_lines() if line.get_label() == "true mode")
    assert list(true_line.get_ydata()) == [float(m) for m in modes]


def test_result_tables_summarise_matrices_and_keep_full_values():
    model = tracking_model(dynamics=ConstantVelocity(axes=2, dt=1.0, q=0.5, dtype=f64), R=[25.0, 36.0])
    filt = KalmanFilter(model)
    short = parameter_summary(filt, ["R", "q"])
    assert "R=diag[25, 36]" in short and len(short) < 120
    full = parameter_values(filt, ["R"])
    assert full == "R=[[25, 0], [0, 36]]"
    big = torch.diag(torch.arange(1.0, 21.0, dtype=f64))
    assert _describe(big) == "diag of 20 in [1, 20]"
