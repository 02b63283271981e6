"""The generated engine's on-disk cache of lowered steps (``difffilter.engines.cache``).

* the key changes with everything material: dtype, mask, a model option, a frozen value, the
  set of trained parameters, the source text of a user's model class;
* a process that finds a stored step does not trace, and computes exactly what a cold build
  computes (outputs and gradients), which equals the reference filter;
* a stored step that no longer matches the filter's code (a method replaced at run time, which
  no source hash sees, or a foreign entry under the key) is detected and rebuilt.
"""

from __future__ import annotations

import copy
import importlib
import shutil
import sys
import textwrap

import pytest
import torch

from difffilter.engines import FusedFilter, cache
from difffilter.engines.trace import StepLayout
from difffilter.filters import EKF, UKF, MerweScaled
from difffilter.models.base import StateSpaceModel
from tests.test_fused import FIELDS, _range_bearing_data

F64 = torch.float64


@pytest.fixture
def fresh_cache(tmp_path, monkeypatch: pytest.MonkeyPatch):  # type: ignore[no-untyped-def]
    monkeypatch.setenv("DIFFFILTER_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("DIFFFILTER_PROGRAM_CACHE", raising=False)
    return tmp_path


def _layout(n: int, m: int, dtype: torch.dtype = F64, *, mask: bool = False, controls: int | None = 2) -> StepLayout:
    ctrl = None if controls is None else (("", (controls,), dtype),)
    return StepLayout(belief=(("cov", (n, n), dtype), ("mean", (n,), dtype)), measurement_dim=m, has_mask=mask, controls=ctrl, dtype=dtype)


def _run(fused: FusedFilter, z, u, m0, p0):  # type: ignore[no-untyped-def]
    """Outputs and the gradients of the total log-likelihood w.r.t. the parameters and the inputs."""
    z = z.clone().requires_grad_(True)
    m0 = m0.clone().requires_grad_(True)
    out = fused(z, m0, p0, controls=u)
    params = [p for p in fused.filter.parameters() if p.requires_grad]
    grads = torch.autograd.grad(out.log_likelihood.sum(), [*params, z, m0])
    return out, grads


def _program(fused: FusedFilter):  # type: ignore[no-untyped-def]
    (prog,) = fused.generated_engine()._programs.values()
    return prog


def test_key_changes_with_everything_material() -> None:
    model, *_ = _range_bearing_data()
    base = UKF(model)
    key = cache.program_key(base, _layout(4, 2))
    assert key is not None and key == cache.program_key(UKF(copy.deepcopy(model)), _layout(4, 2))
    keys = {
        "float32": cache.program_key(UKF(copy.deepcopy(model).float()), _layout(4, 2, torch.float32)),
        "mask": cache.program_key(base, _layout(4, 2, mask=True)),
        "no controls": cache.program_key(base, _layout(4, 2, controls=None)),
        "sigma points": cache.program_key(UKF(model, sigma_points=MerweScaled(alpha=0.5, beta=2.0, kappa=1.0)), _layout(4, 2)),
        "redraw": cache.program_key(UKF(model, redraw_after_predict=False), _layout(4, 2)),
        "filter class": cache.program_key(EKF(model), _layout(4, 2)),
    }
    frozen = copy.deepcopy(model)
    frozen.measurement.requires_grad_(False)
    keys["learnable set"] = cache.program_key(UKF(frozen), _layout(4, 2))
    changed = copy.deepcopy(frozen)
    with torch.no_grad():
        changed.measurement.R = changed.measurement.R * 2.0
    keys["frozen value"] = cache.program_key(UKF(changed), _layout(4, 2))
    assert None not in keys.values()
    assert len(set(keys.values()) | {key}) == len(keys) + 1, keys


def test_key_follows_the_source_of_a_user_model(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    src = """
        import torch
        from difffilter.models.base import MeasurementModel
        from difffilter.params import register_covariance
        class Scaled(MeasurementModel):
            def __init__(self):
                super().__init__()
                self.measurement_dim = 2
                register_covariance(self, "R", torch.eye(2, dtype=torch.float64), "diagonal")
            def forward(self, x, u=None):
                return x[..., :2] * {scale}
    """
    path = tmp_path / "user_model_for_cache_key.py"
    path.write_text(textwrap.dedent(src.format(scale=1.0)))
    monkeypatch.syspath_prepend(str(tmp_path))
    module = importlib.import_module("user_model_for_cache_key")
    try:
        model, *_ = _range_bearing_data()
        filt = UKF(StateSpaceModel(model.dynamics, module.Scaled()))
        before = cache.program_key(filt, _layout(4, 2))
        path.write_text(textwrap.dedent(src.format(scale=2.0)))
        monkeypatch.setattr(cache, "_digests", {})  # a new process: no memo of the old text
        assert cache.program_key(filt, _layout(4, 2)) not in (None, before)
    finally:
        sys.modules.pop("user_model_for_cache_key", None)


def test_a_stored_step_is_used_and_equals_a_cold_build(fresh_cache, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    model, z, u, m0, p0 = _range_bearing_data(batch=5, steps=12)
    cold_fused = FusedFilter(UKF(model), engine="generated")
    cold, cold_grads = _run(cold_fused, z, u, m0, p0)
    assert not _program(cold_fused).from_cache
    assert len(list((fresh_cache / "programs").glob("step_*.pkl"))) == 1

    def no_trace(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise AssertionError("traced again")

    monkeypatch.setattr(cache, "trace_step", no_trace)
    filt = UKF(copy.deepcopy(model))  # a new filter object of the same structure, as a new process builds
    warm_fused = FusedFilter(filt, engine="generated")
    warm, warm_grads = _run(warm_fused, z, u, m0, p0)
    assert _program(warm_fused).from_cache
    for name in FIELDS:
        assert torch.equal(getattr(warm, name), getattr(cold, name)), name
    for a, b in zip(warm_grads, cold_grads, strict=True):
        assert torch.equal(a, b)
    ref = filt(z, m0, p0, controls=u)
    torch.testing.assert_close(warm.log_likelihood, ref.log_likelihood, rtol=1e-10, atol=1e-10)


def test_a_stored_step_that_no_longer_matches_the_code_is_rebuilt(fresh_cache, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    model, z, u, m0, p0 = _range_bearing_data(batch=4, steps=10)
    FusedFilter(UKF(model), engine="generated")(z, m0, p0, controls=u)
    # the measurement function replaced at run time: same source files, so the same key
    original = type(model.measurement).forward
    monkeypatch.setattr(type(model.measurement), "forward", lambda self, x, u=None: original(self, x, u) * 1.01)
    filt = UKF(copy.deepcopy(model))
    fused = FusedFilter(filt, engine="generated")
    out = fused(z, m0, p0, controls=u)
    assert not _program(fused).from_cache
    ref = filt(z, m0, p0, controls=u)
    for name in FIELDS:
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=1e-9, atol=1e-10)


def test_a_foreign_entry_under_the_key_is_rebuilt(fresh_cache) -> None:  # type: ignore[no-untyped-def]
    model, z, u, m0, p0 = _range_bearing_data(batch=4, steps=10)
    FusedFilter(UKF(model), engine="generated")(z, m0, p0, controls=u)
    (stored,) = (fresh_cache / "programs").glob("step_*.pkl")
    other = UKF(copy.deepcopy(model), sigma_points=MerweScaled(alpha=0.5, beta=2.0, kappa=1.0))
    key = cache.program_key(other, _layout(4, 2))
    assert key is not None and cache.program_path(key) != stored
    shutil.copy(stored, cache.program_path(key))  # the first filter's step where the second's belongs
    fused = FusedFilter(other, engine="generated")
    out = fused(z, m0, p0, controls=u)
    assert not _program(fused).from_cache
    torch.testing.assert_close(out.log_likelihood, other(z, m0, p0, controls=u).log_likelihood, rtol=1e-10, atol=1e-10)


def test_the_cache_can_be_turned_off(fresh_cache, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setenv("DIFFFILTER_PROGRAM_CACHE", "0")
    model, z, u, m0, p0 = _range_bearing_data(batch=2, steps=5)
    FusedFilter(UKF(model), engine="generated")(z, m0, p0, controls=u)
    assert not list(fresh_cache.glob("programs/*.pkl"))
