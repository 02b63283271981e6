"""FusedFilter's engines under issue 17's numerics: each engine equals the reference filter, or refuses.

* angular models (circular unscented means, wrapped state addition): the generated and the
  inductor engine (its step run eagerly) run the filter's own wrap-aware step and equal it,
  gradients included;
* the Joseph-form fallback where ``P - K S K^T`` cancels (float32, a variance reduced 1000-fold):
  both engines equal the reference, and the reference without the fallback does not (the
  comparison can fail);
* a diffuse prior (``P0 = 1e24 I``): its first steps run in the reference's exact two-part form,
  the rest on the engine; outputs and gradients equal the reference's;
* ``extras["untrusted"]`` equals the reference's on every run above.
"""

from __future__ import annotations

import math

import pytest
import torch

from difffilter import linalg
from difffilter.engines import FusedFilter
from difffilter.filters import EKF, UKF, Julier, KalmanFilter, SimplifiedUKF, SquareRootUKF
from difffilter.filters import update as update_module
from difffilter.models import LinearModel
from difffilter.models.base import wrap_angle
from tests.test_adversarial_angles import heading_model
from tests.test_adversarial_range import case
from tests.test_fused import FIELDS

F64 = torch.float64
ANGULAR = {
    "ukf": lambda m: UKF(m),
    "ukf_julier_reuse": lambda m: UKF(m, sigma_points=Julier(kappa=-0.5), redraw_after_predict=False),
    "sukf": lambda m: SimplifiedUKF(m),
    "srukf": lambda m: SquareRootUKF(m),
    "ekf": lambda m: EKF(m),
}


def _assert_same(out, ref, *, rtol: float, atol: float) -> None:  # type: ignore[no-untyped-def]
    for name in FIELDS:
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=rtol, atol=atol, msg=name)
    assert torch.equal(out.extras["untrusted"], ref.extras["untrusted"])


def _grads(filt, result, inputs):  # type: ignore[no-untyped-def]
    params = [p for p in filt.parameters() if p.requires_grad]
    loss = result.log_likelihood.sum() + result.mean.square().sum()
    return torch.autograd.grad(loss, params + inputs)


def _headings(batch: int = 3, steps: int = 12) -> torch.Tensor:
    """Compass readings of headings that cross the +-pi cut."""
    g = torch.Generator().manual_seed(3)
    walk = math.pi - 0.3 + torch.cumsum(0.08 + 0.02 * torch.randn(batch, steps, 1, generator=g, dtype=F64), 1)
    return wrap_angle(walk + 0.1 * torch.randn(batch, steps, 1, generator=g, dtype=F64))


@pytest.mark.parametrize("name", list(ANGULAR))
@pytest.mark.parametrize("engine", ["generated", "eager"])
def test_engines_equal_the_wrap_aware_reference(name: str, engine: str) -> None:
    filt = ANGULAR[name](heading_model(linear=name == "sukf"))
    z = _headings().requires_grad_(True)
    m0, p0 = torch.tensor([3.0], dtype=F64), torch.tensor([[0.04]], dtype=F64)
    fused = FusedFilter(filt, engine=engine)
    out, ref = fused(z, m0, p0), filt(z, m0, p0)
    assert fused.last_engine == engine
    assert float(out.mean.detach().abs().max()) <= math.pi and float(ref.mean.detach().abs().max()) > 2.8  # the cut is crossed
    _assert_same(out, ref, rtol=1e-10, atol=1e-12)
    for a, b in zip(_grads(filt, out, [z]), _grads(filt, ref, [z]), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10)


def test_auto_uses_the_generated_engine_for_angular_models() -> None:
    fused = FusedFilter(UKF(heading_model()))
    fused(_headings(), torch.tensor([3.0], dtype=F64), torch.tensor([[0.04]], dtype=F64))
    assert fused.last_engine == "generated"


def _sharp_update_case() -> tuple[LinearModel, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Prior variance 1e5 measured with variance 1e-2: the first update reduces the measured
    variances 1e7-fold, below the fallback's switch (``64 sqrt(eps)`` = 9.5e-7) but not beyond
    the diffuse-prior threshold (``eps^-1/2`` = 6.7e7); ``P - K S K^T`` keeps only ~1e-9
    relative accuracy there."""
    dt = F64
    f = torch.tensor([[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]], dtype=dt)
    h = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]], dtype=dt)
    model = LinearModel(F=f, H=h, Q=0.01 * torch.eye(4, dtype=dt), R=1e-2 * torch.eye(2, dtype=dt))
    g = torch.Generator().manual_seed(5)
    z = (torch.randn(4, 6, 2, generator=g) * 3.0 + 1.7).to(dt)
    m0 = torch.tensor([0.3, -0.2, 0.1, 0.0], dtype=dt)
    p0 = torch.diag(torch.tensor([1e5, 1e5, 1.0, 1.0], dtype=dt)) + 0.3
    return model, z, m0, p0


@pytest.mark.parametrize("name", ["ukf", "sukf", "ekf"])
@pytest.mark.parametrize("engine", ["generated", "eager"])
def test_engines_take_the_joseph_fallback_where_the_reference_does(name: str, engine: str, monkeypatch: pytest.MonkeyPatch) -> None:
    model, z, m0, p0 = _sharp_update_case()
    filt = {"ukf": UKF, "sukf": SimplifiedUKF, "ekf": lambda m: EKF(m, joseph=False)}[name](model)
    ref = filt(z, m0, p0)
    assert "diffuse_cov" not in filt.initial_belief(m0, p0, batch_size=1)
    ratio = torch.diagonal(ref.cov.detach()[:, 0], dim1=-2, dim2=-1) / torch.diagonal(ref.prior_cov.detach()[:, 0], dim1=-2, dim2=-1)
    assert float(ratio.min()) < 64 * torch.finfo(F64).eps ** 0.5  # the fallback's regime
    out = FusedFilter(filt, engine=engine)(z, m0, p0)
    rtol, atol = 1e-10, 1e-12
    _assert_same(out, ref, rtol=rtol, atol=atol)
    # without the fallback the reference differs beyond these tolerances: the comparison has teeth
    monkeypatch.setattr(update_module, "any_set", lambda flags: False)
    naive = filt(z, m0, p0)
    assert not torch.allclose(naive.cov, ref.cov, rtol=rtol, atol=atol)
    assert linalg.any_set(torch.tensor([False, True]))


@pytest.mark.parametrize("name", ["kf", "ukf"])
def test_a_diffuse_prior_runs_its_exact_phase_then_the_engine(name: str) -> None:
    mats, z, p0 = case(1e24, "float64")
    filt = (KalmanFilter if name == "kf" else UKF)(LinearModel(**mats))
    z = z.expand(2, -1, -1).clone().requires_grad_(True)
    m0 = torch.zeros(4, dtype=F64)
    assert "diffuse_cov" in filt.initial_belief(m0, p0, batch_size=2)
    fused = FusedFilter(filt, engine="generated")
    out, ref = fused(z, m0, p0), filt(z, m0, p0)
    assert fused.last_engine == "generated"  # the steps after the diffuse phase
    _assert_same(out, ref, rtol=1e-9, atol=1e-9)
    assert set(out.final_belief) == set(ref.final_belief)
    for a, b in zip(_grads(filt, out, [z]), _grads(filt, ref, [z]), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-9)
