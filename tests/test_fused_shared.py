"""The generated engine's shared-covariance Kalman filter (``difffilter.engines.shared``).

When a plain KalmanFilter's covariances are the same for every trajectory (same initial
covariance, same mask, no controls) the engine runs the covariance recursion once; every output
field and every gradient must equal the ordinary per-trajectory run and the reference filter,
and anything per-trajectory must fall back to the ordinary run.
"""

from __future__ import annotations

import pytest
import torch

from difffilter.engines import FusedFilter, shared
from difffilter.filters import UKF, KalmanFilter
from difffilter.models.base import LinearModel
from tests.test_fused import _range_bearing_data

F64 = torch.float64
FIELDS = ("mean", "cov", "prior_mean", "prior_cov", "log_likelihood", "nis", "num_observed")


@pytest.fixture(autouse=True)
def small_batches(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(shared, "MIN_SHARED_BATCH", 2)  # the tests' batches are small


def _model(dtype: torch.dtype = F64) -> LinearModel:
    dt = 0.5
    f = torch.tensor([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=dtype)
    h = torch.tensor([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0.3, 0, 0, 1.0]], dtype=dtype)
    q = torch.diag(torch.tensor([0.01, 0.02, 0.1, 0.2], dtype=dtype))
    r = torch.tensor([[0.5, 0.1, 0.0], [0.1, 0.4, 0.05], [0.0, 0.05, 0.3]], dtype=dtype)
    return LinearModel(F=f, H=h, Q=q, R=r)


def _data(batch: int = 9, steps: int = 25, seed: int = 0):  # type: ignore[no-untyped-def]
    g = torch.Generator().manual_seed(seed)
    z = torch.cumsum(torch.randn(batch, steps, 3, generator=g, dtype=F64), 1)
    m0 = torch.randn(batch, 4, generator=g, dtype=F64)
    p0 = torch.eye(4, dtype=F64) * 2.0 + 0.1
    mask = torch.rand(1, steps, 3, generator=g) > 0.3
    return z, m0, p0, mask.expand(batch, -1, -1).clone()


def _run(fused, z, m0, p0, mask):  # type: ignore[no-untyped-def]
    """Outputs, and gradients of a loss on every output field w.r.t. parameters, z, m0, P0."""
    z, m0, p0 = (x.clone().requires_grad_(True) for x in (z, m0, p0))
    out = fused(z, m0, p0, mask=mask)
    loss = sum((getattr(out, f) * (0.1 + i)).sum() for i, f in enumerate(FIELDS[:-1]))
    params = [p for p in fused.parameters() if p.requires_grad]
    grads = torch.autograd.grad(loss, [*params, z, m0, p0])
    return out, grads


def _engines(filt: KalmanFilter) -> tuple[FusedFilter, FusedFilter]:
    fast, slow = FusedFilter(filt, engine="generated"), FusedFilter(filt, engine="generated")
    slow.generated_engine().shared_covariance = False
    return fast, slow


@pytest.mark.parametrize("masked", [False, True])
def test_shared_covariance_equals_the_per_trajectory_run(masked: bool) -> None:
    filt = KalmanFilter(_model())
    z, m0, p0, mask = _data()
    mask = mask if masked else None
    fast, slow = _engines(filt)
    out, grads = _run(fast, z, m0, p0, mask)
    assert fast.generated_engine().last_path == "shared covariance"
    ref, ref_grads = _run(slow, z, m0, p0, mask)
    assert slow.generated_engine().last_path == "per trajectory"
    plain, plain_grads = _run(filt, z, m0, p0, mask)  # the reference filter itself
    for other, other_grads in ((ref, ref_grads), (plain, plain_grads)):
        for name in FIELDS:
            torch.testing.assert_close(getattr(out, name), getattr(other, name), rtol=1e-10, atol=1e-10)
        for a, b in zip(grads, other_grads, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
    assert torch.equal(out.extras["untrusted"], ref.extras["untrusted"])
    for key in ("mean", "cov"):
        torch.testing.assert_close(out.final_belief[key], ref.final_belief[key], rtol=1e-10, atol=1e-10)
    # a next window from the final belief (truncated back-propagation) stays on the shared path
    nxt = fast(z[:, :5], belief={k: v.detach() for k, v in out.final_belief.items()})
    assert fast.generated_engine().last_path == "shared covariance"
    torch.testing.assert_close(
        nxt.mean, filt(z[:, :5], belief={k: v.detach() for k, v in ref.final_belief.items()}).mean, rtol=1e-10, atol=1e-10
    )


def test_per_trajectory_mask_or_covariance_falls_back() -> None:
    filt = KalmanFilter(_model())
    z, m0, p0, mask = _data()
    fast, _ = _engines(filt)
    engine = fast.generated_engine()
    own_mask = mask.clone()
    own_mask[3, 4, 0] = ~own_mask[3, 4, 0]
    out = fast(z, m0, p0, mask=own_mask)
    assert engine.last_path == "per trajectory"
    torch.testing.assert_close(out.log_likelihood, filt(z, m0, p0, mask=own_mask).log_likelihood, rtol=1e-10, atol=1e-10)
    own_p0 = p0.expand(z.shape[0], -1, -1).clone()
    own_p0[2] = own_p0[2] * 1.5
    out = fast(z, m0, own_p0)
    assert engine.last_path == "per trajectory"
    torch.testing.assert_close(out.cov, filt(z, m0, own_p0).cov, rtol=1e-10, atol=1e-10)
    # the same values per trajectory, but a leaf of its own whose gradient is per trajectory
    fast(z, m0, p0.expand(z.shape[0], -1, -1).clone().requires_grad_(True))
    assert engine.last_path == "per trajectory"
    fast(z, m0, p0)
    assert engine.last_path == "shared covariance"


def test_only_plain_kalman_filters_on_linear_models_share() -> None:
    z, m0, p0, _ = _data()
    belief = KalmanFilter(_model()).start_belief(m0, p0.expand(z.shape[0], -1, -1))

    class Subclass(KalmanFilter):
        pass

    assert shared.shares_covariance(KalmanFilter(_model()), None, belief, None)
    assert not shared.shares_covariance(Subclass(_model()), None, belief, None)
    assert not shared.shares_covariance(KalmanFilter(_model()), None, belief, torch.zeros(z.shape[0], z.shape[1], 1))


def test_controls_shared_by_the_batch_are_read_once_per_step() -> None:
    """Any filter: a control expanded over the batch becomes the kernel's per-step shared input;
    outputs and gradients (controls included) equal the reference filter's."""
    model, z, u, m0, p0 = _range_bearing_data(batch=6, steps=10)
    filt = UKF(model)
    u1 = u[:1].clone().requires_grad_(True)
    fused = FusedFilter(filt, engine="generated")
    out = fused(z, m0, p0, controls=u1.expand(6, -1, -1))
    (prog,) = fused.generated_engine()._programs.values()
    assert prog.traced.layout.shared == ("",) and prog.traced.layout.step_size == 2
    ref = filt(z, m0, p0, controls=u1.expand(6, -1, -1))
    params = [p for p in filt.parameters() if p.requires_grad]
    grads = torch.autograd.grad(out.log_likelihood.sum() + out.mean.sum(), [*params, u1])
    ref_grads = torch.autograd.grad(ref.log_likelihood.sum() + ref.mean.sum(), [*params, u1])
    for name in FIELDS:
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=1e-10, atol=1e-10)
    for a, b in zip(grads, ref_grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("masked", [False, True])
def test_batch_one_kernel_records_the_updates_gain_factor_and_log_determinant(masked: bool) -> None:
    """The shared path takes each step's ``K``, Cholesky factor of ``S`` and ``log det S`` from the
    batch-one kernel (SharedGainRecorder): they equal the closed form on the reference filter's
    prior covariances, ``K = P H_o^T (H_o P H_o^T + R_oo)^{-1}`` over the observed rows ``o``."""
    from difffilter.engines.generated import GeneratedEngine

    model = _model()
    filt = KalmanFilter(model)
    z, m0, p0, mask = _data(batch=1)
    mask = mask if masked else None
    ref = filt(z, m0, p0, mask=mask)
    engine = GeneratedEngine(shared.SharedGainRecorder(filt), shared_covariance=False)
    zc, mask3, mean0, cov0 = filt.check_inputs(z, m0, p0, mask, None)
    field, _ = engine._fields(zc, mask3, filt.start_belief(mean0, cov0), None)
    n, m = 4, 3
    h, r = model.measurement.matrix(None).detach(), model.measurement.measurement_noise(None, None).detach()
    gains, chols, logdets = field("shared_gain")[0], field("shared_chol")[0], field("shared_logdet")[0, :, 0]
    for t in range(z.shape[1]):
        obs = torch.ones(m, dtype=torch.bool) if mask is None else mask[0, t]
        p = ref.prior_cov[0, t].detach()
        s_oo = h[obs] @ p @ h[obs].T + r[obs][:, obs]
        k = torch.zeros(n, m, dtype=F64)
        k[:, obs] = torch.linalg.solve(s_oo, h[obs] @ p).T
        low = chols[t].reshape(m, m)
        torch.testing.assert_close(gains[t].reshape(n, m), k, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close((low @ low.T)[obs][:, obs], s_oo, rtol=1e-10, atol=1e-12)
        assert torch.equal(low, torch.tril(low))
        torch.testing.assert_close(logdets[t], torch.logdet(s_oo), rtol=1e-10, atol=1e-12)
