"""What users write in a model runs on the generated engine (issue 26, coverage): ``hypot``,
``atan2``, NumPy scalars and constants, a per-group scale picked by a data label (README's
heteroscedastic example).  Lowered values and reverse derivatives against torch (fast, no
compiler), then whole filters against the eager ones in float64 (values and gradients)."""

from __future__ import annotations

import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import Tensor

from difffilter.engines import FusedFilter
from difffilter.engines.adjoint import backprop
from difffilter.engines.graph import LANE, UnsupportedOp, evaluate
from difffilter.filters import UKF, MerweScaled
from difffilter.models import FunctionalModel

from .test_fused_generated import lowered_graph

F64 = torch.float64
README = Path(__file__).resolve().parents[1] / "README.md"


def _lowered_with_grads(fn, *examples: Tensor) -> tuple[np.ndarray, list[np.ndarray]]:  # type: ignore[no-untyped-def]
    """``fn``'s output and the gradient of ``sum(w * fn(...))`` (fixed weights ``w``) w.r.t. every
    floating example, both computed from the lowered scalar graph."""
    g, arrays, values, out = lowered_graph(fn, *examples)
    out = np.asarray(out)
    weights = np.linspace(0.5, 1.5, out.size)
    adjoint, _ = backprop(g, {int(o): g.const(float(w)) for o, w in zip(out.reshape(-1), weights, strict=True)}, LANE)
    zero = g.const(0.0)
    got = np.array(evaluate(g, [int(x) for x in out.reshape(-1)], values), dtype=float).reshape(out.shape)
    grads = []
    for ex, arr in zip(examples, arrays, strict=True):
        if ex.is_floating_point():
            nodes = [adjoint.get(int(x), zero) for x in arr.reshape(-1)]
            grads.append(np.array(evaluate(g, nodes, values), dtype=float).reshape(ex.shape))
    return got, grads


def _check_against_torch(fn, *examples: Tensor) -> None:  # type: ignore[no-untyped-def]
    got, grads = _lowered_with_grads(fn, *examples)
    leaves = [ex.clone().requires_grad_() if ex.is_floating_point() else ex for ex in examples]
    want = fn(*leaves)
    weights = torch.linspace(0.5, 1.5, want.numel(), dtype=F64).reshape(want.shape)
    want_grads = torch.autograd.grad((want * weights).sum(), [x for x in leaves if x.requires_grad])
    np.testing.assert_allclose(got, want.detach().numpy(), rtol=1e-12, atol=1e-12)
    for a, b in zip(grads, want_grads, strict=True):
        np.testing.assert_allclose(a, b.numpy(), rtol=1e-12, atol=1e-12)


def test_hypot_atan2_and_numpy_constants_lower_with_their_derivatives() -> None:
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(3, 4, dtype=F64, generator=g) * 5, torch.randn(3, 4, dtype=F64, generator=g) * 5
    _check_against_torch(lambda x, y: torch.hypot(x, y) + x.hypot(2.0 * y), a, b)
    _check_against_torch(lambda x, y: torch.atan2(x, y) * np.float64(0.5) + np.pi * x / np.sqrt(2.0), a, b)
    _check_against_torch(lambda x, y: x ** np.int64(2) + torch.as_tensor(np.array([1.0, 2.0, 3.0, 4.0])) * y, a, b)


def test_one_component_written_in_place_lowers_with_its_derivatives() -> None:
    """``y = x.clone(); y[..., k] = ...`` (``select_scatter``), also with a negative index, on a
    state vector and on a batch of them: on a vector the target is a single element, where a 0-d
    source array was once stored as the element itself (a TypeError, and the filter ran eagerly)."""

    def write(x: Tensor) -> Tensor:
        y = x.clone()
        y[..., 1] = 2.0 * x[..., 0]
        y[..., -1] = torch.sin(x[..., 2])
        return y * x

    g = torch.Generator().manual_seed(1)
    for shape in ((4,), (3, 4)):
        _check_against_torch(write, torch.randn(*shape, dtype=F64, generator=g))


def test_a_data_label_picks_one_of_several_scales() -> None:
    """``scale[label]`` with the label among the data (negative labels as torch reads them)."""
    g = torch.Generator().manual_seed(1)
    scales = torch.rand(3, 2, dtype=F64, generator=g) + 0.5
    labels = torch.tensor([[0, 2, 1], [-1, 1, 0]])
    x = torch.randn(2, 3, 2, dtype=F64, generator=g)
    _check_against_torch(lambda s, lab, v: s[lab] * v, scales, labels, x)
    _check_against_torch(lambda s, lab, v: s[:, lab.clamp(0, 1)].sum(0) * v[..., 0], scales, labels, x)


def test_boolean_data_index_is_refused() -> None:
    with pytest.raises(UnsupportedOp, match="boolean"):
        _lowered_with_grads(lambda s, v: s[v > 0], torch.ones(4, dtype=F64), torch.randn(4, dtype=F64))


def _docs_block(marker: str) -> str:
    """The first ```python block of README or a docs page that contains ``marker``."""
    pages = [README, *sorted((README.parent / "docs").rglob("*.md"))]
    blocks = [b for page in pages for b in re.findall(r"```python\n(.*?)```", page.read_text(), re.S)]
    return next(b for b in blocks if marker in b)


def _same_run(filt, args, kwargs) -> None:  # type: ignore[no-untyped-def]
    """The generated engine (no fallback, no warning) equals ``filt`` to 1e-12 in values and in the
    gradients w.r.t. every parameter and the initial mean."""
    fused = FusedFilter(filt, engine="generated")

    def run(runner):  # type: ignore[no-untyped-def]
        m0 = args[1].clone().requires_grad_()
        out = runner(args[0], m0, *args[2:], **kwargs)
        params = [p for p in filt.parameters() if p.requires_grad]
        loss = out.log_likelihood.sum() + 0.01 * out.mean.sum()
        return out, torch.autograd.grad(loss, [m0, *params])

    ref, g_ref = run(filt)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out, g_out = run(fused)
    assert fused.last_engine == "generated"
    for name in ("mean", "cov", "log_likelihood"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=1e-12, atol=1e-12, msg=name)
    for a, b in zip(g_out, g_ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("g++") is None and shutil.which("c++") is None, reason="needs a C++ compiler")
def test_readme_first_example_runs_on_the_generated_engine() -> None:
    """The range-bearing model of docs/filters/ukf.md (``hypot`` and ``atan2``, a wrapped bearing),
    with NumPy constants in ``f`` and a mask."""
    ns: dict = {}
    exec(_docs_block(".hypot(").split("for points in")[0], ns)  # noqa: S102 - the docs' own code
    dt = np.float64(1.0)
    model = FunctionalModel(
        f=lambda x: x @ ns["F"].mT * np.float64(1.0) + 0.0 * np.pi * dt * x,
        h=ns["h"],
        Q=0.1 * torch.eye(4, dtype=F64),
        R=torch.diag(torch.tensor([0.25, 1e-4], dtype=F64)),
        angular_measurements=[1],
    )
    ukf = UKF(model, sigma_points=MerweScaled(alpha=1.0, beta=2.0, kappa=0.0))
    z = ns["z"] + 0.1 * torch.randn(ns["z"].shape, dtype=F64, generator=torch.Generator().manual_seed(0))
    mask = torch.rand(z.shape[:2], generator=torch.Generator().manual_seed(1)) > 0.1
    _same_run(ukf, (z, ns["m0"], ns["P0"]), {"mask": mask})


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("g++") is None and shutil.which("c++") is None, reason="needs a C++ compiler")
def test_readme_heteroscedastic_example_runs_on_the_generated_engine() -> None:
    """Per-fix-type scales of the reported variance picked by a label among the controls, a gate."""
    ns: dict = {}
    exec(_docs_block("HeteroscedasticMeasurement(").split("opt = torch.optim")[0], ns)  # noqa: S102
    _same_run(ns["ekf"], (ns["z"], ns["m0"], ns["P0"]), {"controls": ns["controls"]})
