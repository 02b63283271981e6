"""A Kalman filter's covariance recursion computed once for a whole batch.

For a plain :class:`~difffilter.filters.KalmanFilter` on a
:class:`~difffilter.models.base.LinearModel` without controls, the covariances ``P-``, ``S``,
the gain ``K`` and ``P+`` do not depend on the measurements: when every trajectory starts from
the same covariance and has the same mask, they are the same for the whole batch.  Then the
covariance recursion runs once (the generated kernel at batch one, so every detail of the
filter's update - Joseph form, masking, the Cholesky repair - is the filter's own), and only
the mean recursion runs per trajectory:

``m+_t = (I - K_t D_t H) F m+_{t-1} + K_t D_t z_t`` (``D_t`` the mask), one small matrix
product per step for the whole batch; the innovations, log-likelihoods and normalised
innovations squared follow for all steps at once from the shared Cholesky factors of ``S_t``.
The batch-one run also computes the per-step gain, Cholesky factor and log-determinant
(:class:`SharedGainRecorder`), so that they and their gradients come from its kernel rather than
from some twenty small batched torch operations and their autograd nodes per call.
The result equals the per-trajectory recursion up to rounding.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from ..filters._common import StepInfo, mask_measurement_system
from ..filters.base import Belief, FilterResult, RecursiveFilter
from ..filters.kalman import KalmanFilter
from ..filters.update import untrusted_steps
from ..linalg import gaussian_log_density, nonfinite_rows, safe_cholesky
from ..models.base import Controls, LinearModel

__all__ = ["MIN_SHARED_BATCH", "SharedGainMean", "SharedGainRecorder", "shares_covariance", "shared_covariance_run"]

#: ``fields_of(z, mask, belief, controls) -> field``: a generated-kernel run, ``field(name)`` its output ``[B, T, ...]``
FieldsOf = Callable[[Tensor, "Tensor | None", Belief, Controls], Callable[[str], Tensor]]
#: the same with ``common``, controls ``[T, ...]`` the same for every trajectory
MeanFieldsOf = Callable[[Tensor, "Tensor | None", Belief, Controls, "dict[str, Tensor]"], Callable[[str], Tensor]]

#: below this batch size the per-trajectory run is as fast (process CPU time of a training step of
#: the benchmark's 4-state KF, T = 500, float64, experiments/benchmark_kf_shared.py, per trajectory
#: / shared: B = 16 0.51, 64 1.32, 256 1.81, 1024 3.09, 4096 2.01)
MIN_SHARED_BATCH = 64


def _same_for_all(x: Tensor) -> bool:
    if x.shape[0] == 1 or x.stride(0) == 0:
        return True
    return bool(torch.equal(x, x[:1].expand_as(x)))


def shares_covariance(filt: RecursiveFilter, mask: Tensor | None, belief: Belief, controls: Controls) -> bool:
    """Whether every trajectory of the batch has the same covariances (see the module docstring):
    a plain ``KalmanFilter`` on a plain ``LinearModel`` without angular components, no
    controls, a belief of mean and covariance only whose covariance is the same for every
    trajectory (and is not a per-trajectory leaf that wants its own gradient), the same mask for
    every trajectory, and a batch of at least :data:`MIN_SHARED_BATCH`."""
    model = getattr(filt, "model", None)
    if type(filt) is not KalmanFilter or type(model) is not LinearModel or controls is not None:
        return False
    if getattr(model.dynamics, "angular", ()) or getattr(model.measurement, "angular", ()):
        return False
    if not model.dynamics.additive_noise or not model.measurement.additive_noise:
        return False
    if set(belief) != {"mean", "cov"}:
        return False
    cov = belief["cov"]
    if cov.shape[0] < MIN_SHARED_BATCH:
        return False
    if cov.requires_grad and cov.stride(0) != 0:
        return False  # its gradient is per trajectory
    return _same_for_all(cov) and (mask is None or _same_for_all(mask))


class SharedGainMean(RecursiveFilter):
    """The mean recursion of a Kalman filter whose gains are given: per-step controls ``gain``
    ``[B, T, n m]`` (``K_t``, row-major), ``chol`` ``[B, T, m m]`` (the Cholesky factor of the
    masked ``S_t``) and ``logdet`` ``[B, T, 1]`` (its log-determinant), the same for every
    trajectory, so that the generated kernel reads them once per step (its ``shared`` input).  Its belief's ``cov`` is a
    ``[B, 1, 1]`` placeholder, passed through."""

    def predict(self, belief: Belief, u: Controls) -> Belief:
        return {"mean": self.model.dynamics(belief["mean"], None), "cov": belief["cov"]}

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        mean = belief["mean"]
        n, m = mean.shape[-1], z.shape[-1]
        e = self.model.measurement.residual(z, self.model.measurement(mean, None))
        if mask is None:
            num_obs = torch.full(e.shape[:-1], float(m), dtype=e.dtype)
        else:
            e = torch.where(mask, e, torch.zeros_like(e))
            num_obs = mask.to(e.dtype).sum(-1)
        gain = u["gain"].reshape(*e.shape[:-1], n, m)  # type: ignore[index]
        chol = u["chol"].reshape(*e.shape[:-1], m, m)  # type: ignore[index]
        loglik, maha = gaussian_log_density(e, chol, num_obs, logdet=u["logdet"][..., 0])  # type: ignore[index]
        new_mean = mean + (gain @ e[..., None])[..., 0]
        return {"mean": new_mean, "cov": belief["cov"]}, StepInfo(loglik, maha, num_obs)


#: belief entries :class:`SharedGainRecorder` adds: the gain ``K_t`` ``[n m]`` (row-major), the
#: Cholesky factor of the masked ``S_t`` ``[m m]`` and its log-determinant ``[1]``
GAIN_KEYS = ("shared_chol", "shared_gain", "shared_logdet")


def shared_gain(filt: KalmanFilter, prior: Belief, mask: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """``(K [B, n, m], L [B, m, m], log det S [B])`` of the update of ``prior`` (mean ``[B, n]``,
    cov ``[B, n, n]``): the masked innovation covariance ``S``, its Cholesky factor (repaired as
    the update repairs it) and the gain ``P- H^T S^{-1}`` by two triangular solves."""
    mean, cov = prior["mean"], prior["cov"]
    h = filt.measurement_jacobian(mean, None).to(cov.dtype)
    pht = cov @ h.mT  # [B, n, m]
    s = h @ pht + filt.measurement_noise_cov(mean, None)
    e = torch.zeros(*pht.shape[:-2], pht.shape[-1], dtype=cov.dtype, device=cov.device)
    _, s_m, pht_m, _ = mask_measurement_system(e, s, pht, mask)
    chol = safe_cholesky(s_m).factor
    w = torch.linalg.solve_triangular(chol, pht_m.mT, upper=False)  # [B, m, n]
    gain = torch.linalg.solve_triangular(chol.mT, w, upper=True).mT  # [B, n, m]
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    return gain, chol, logdet


class SharedGainRecorder(RecursiveFilter):
    """``filt``'s own steps (the wrapped filter's ``predict``/``update``, unchanged), with the
    update's gain, Cholesky factor and log-determinant (:func:`shared_gain`) added to the belief
    as :data:`GAIN_KEYS`, so that a generated kernel of it outputs them per step."""

    def __init__(self, filt: KalmanFilter) -> None:
        super().__init__(filt.model)
        self.inner = filt

    def predict(self, belief: Belief, u: Controls) -> Belief:
        return self.inner.predict(belief, u)

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        post, info = self.inner.update(belief, z, mask, u)
        gain, chol, logdet = shared_gain(self.inner, belief, mask)
        batch = gain.shape[0]
        extra = dict(zip(GAIN_KEYS, (chol.reshape(batch, -1), gain.reshape(batch, -1), logdet[:, None]), strict=True))
        return {**post, **extra}, info

    def finalize_belief(self, belief: Belief) -> Belief:
        return self.inner.finalize_belief(belief)

    def record(self, belief: Belief) -> dict[str, Tensor]:
        return self.inner.record(belief)


def shared_covariance_run(
    filt: KalmanFilter, z: Tensor, mask: Tensor | None, belief: Belief, fields_of: FieldsOf, mean_fields_of: MeanFieldsOf
) -> FilterResult:
    """The filter's result with the covariance recursion run once.

    ``fields_of(z, mask, belief, controls)`` runs the generated kernel of
    :class:`SharedGainRecorder` of ``filt`` and returns ``field(name)``, the per-step output
    ``name`` ``[B, T, ...]``; it is called at batch one.  ``mean_fields_of(z, mask, belief, None,
    common)`` does the same for :class:`SharedGainMean` on ``filt``'s model, on the whole batch,
    with its controls ``common`` given once ``[T, ...]``.
    """
    bsz, steps = z.shape[:2]
    m1 = None if mask is None else mask[:1]
    one = {"mean": belief["mean"][:1].detach(), "cov": belief["cov"][:1]}
    field = fields_of(z[:1].detach(), m1, one, None)
    prior_cov, post_cov = field("prior_cov")[0], field("cov")[0]  # [T, n, n]
    step_flag = field("step_untrusted")[0] != 0  # [T]
    # the update's own gain, factor and log-determinant, per step (computed once, not per trajectory)
    shared = {name: field(key)[0] for name, key in zip(("chol", "gain", "logdet"), GAIN_KEYS, strict=True)}
    mean_belief = {"mean": belief["mean"], "cov": belief["mean"].new_zeros(1, 1, 1).expand(bsz, 1, 1)}
    mf = mean_fields_of(z, mask, mean_belief, None, shared)
    post, prior, loglik = mf("mean"), mf("prior_mean"), mf("log_likelihood")
    cov = post_cov.expand(bsz, *post_cov.shape)
    pcov = prior_cov.expand(bsz, *prior_cov.shape)
    # untrusted_steps' checks: the covariance ones once (batch one), the per-trajectory ones here
    shared_bad = untrusted_steps(
        post_cov.new_zeros(1, steps, 1), post_cov[None].detach(), prior_cov[None].detach(), post_cov.new_zeros(1, steps)
    )
    untrusted = (shared_bad | step_flag[None]).repeat(bsz, 1)
    # nonfinite_rows: one sum for a finite run, the element-wise test only when it is not
    if bool(nonfinite_rows(loglik, 0)):
        untrusted = untrusted | ~torch.isfinite(loglik.detach())
    if bool(nonfinite_rows(post, 0)):
        untrusted = untrusted | nonfinite_rows(post, 2)
    return FilterResult(
        mean=post,
        cov=cov,
        prior_mean=prior,
        prior_cov=pcov,
        log_likelihood=loglik,
        nis=mf("nis"),
        num_observed=mf("num_observed"),
        final_belief={"mean": post[:, -1].clone(), "cov": post_cov[-1].expand(bsz, *post_cov.shape[1:])},
        extras={"untrusted": untrusted},
    )
