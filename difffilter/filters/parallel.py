"""The Kalman filter parallel in time: :class:`ParallelKalmanFilter`."""

from __future__ import annotations

from torch import Tensor
from torch.nn.utils import parametrize

from ..models.base import Controls, StateSpaceModel
from ..threads import scoped_forward
from .base import Belief, FilterResult, RecursiveFilter, concat_results, slice_controls, slice_steps
from .diffuse import DIFFUSE_COV
from .kalman import KalmanFilter
from .scan import AffineSystem, scan_filter
from .update import untrusted_steps

__all__ = ["ParallelKalmanFilter", "linear_system"]


def _per_step(value: Tensor, bsz: int, steps: int, trailing: tuple[int, ...]) -> Tensor:
    """A model's matrix (``[*trailing]``, per trajectory ``[B, *trailing]`` or per step
    ``[B T, *trailing]``) expanded to ``[B, T, *trailing]``."""
    k = len(trailing)
    if value.ndim == k:
        return value.expand(bsz, steps, *trailing)
    lead = value.shape[: value.ndim - k]
    if lead == (bsz * steps,):
        return value.reshape(bsz, steps, *trailing)
    if lead == (bsz,):
        return value[:, None].expand(bsz, steps, *trailing)
    raise ValueError(f"a model matrix has shape {tuple(value.shape)}; expected [{', '.join(map(str, trailing))}] with leading [B] or [B*T]")


def _flat(controls: Controls) -> Controls:
    if controls is None:
        return None
    if isinstance(controls, Tensor):
        return controls.reshape(-1, *controls.shape[2:])
    return {k: v.reshape(-1, *v.shape[2:]) for k, v in controls.items()}


def linear_system(filt: KalmanFilter, controls: Controls, bsz: int, steps: int, like: Tensor) -> AffineSystem:
    """The per-step matrices ``[B, T, ...]`` of ``filt``'s linear model for the (precomputed)
    ``controls [B, T, ...]``: ``F = dynamics.matrix(u)``, ``c = f(0, u)``, ``Q``, ``H``,
    ``d = h(0, u)``, ``R`` (the noise covariances as the filter forms them, at the zero state:
    a linear-Gaussian model's do not depend on the state)."""
    n, m = filt.state_dim, filt.measurement_dim
    u = _flat(controls)
    zero = like.new_zeros(bsz * steps, n)
    dyn, meas = filt.model.dynamics, filt.model.measurement
    return AffineSystem(
        F=_per_step(filt.transition_jacobian(zero, u), bsz, steps, (n, n)),
        c=dyn(zero, u).reshape(bsz, steps, n),
        Q=_per_step(filt.process_noise_cov(zero, u), bsz, steps, (n, n)),
        H=_per_step(filt.measurement_jacobian(zero, u), bsz, steps, (m, n)),
        d=meas(zero, u).reshape(bsz, steps, m),
        R=_per_step(filt.measurement_noise_cov(zero, u), bsz, steps, (m, m)),
    )


class ParallelKalmanFilter(KalmanFilter):
    """Kalman filter for linear-Gaussian models, parallel in time (associative scan).

    Same model, arguments and :class:`~difffilter.filters.protocol.FilterResult` as
    :class:`~difffilter.filters.KalmanFilter`, and the same values up to rounding: the filtered
    moments of all ``T`` steps come from one prefix scan of ``O(log T)`` sequential depth
    (Särkkä & García-Fernández 2021; equations in :mod:`difffilter.filters.scan`), then the
    priors, innovations, log-likelihoods and NIS of all steps from one batched call.  That is
    what a GPU needs for long windows with few trajectories; it does about twice the
    arithmetic of the sequential filter but in ``O(log T)`` batched calls instead of ``T`` rounds
    of small ones (measured speeds: ``docs/parallel.md``).

    Supported as in :class:`KalmanFilter`: whole-step and per-component masks (the missing
    components removed exactly), controls (``f(x, u) = F(u) x + c(u)``,
    ``h(x, u) = H(u) x + d(u)``), matrices that vary per trajectory or per step (a model whose
    ``matrix(u)`` reads the step's inputs, e.g.
    :class:`~difffilter.models.TimeVaryingLinearModel`), float32/float64, belief carry-over and
    a diffuse initial covariance (its first steps, until the measurements resolve it, run the
    sequential exact diffuse update; the rest is scanned).  ``Q`` and ``R`` must not depend on
    the state (they are evaluated at zero).  Angular state or measurement components are
    refused (the scan adds, it cannot wrap).  :meth:`step` is the sequential filter's.

    The engine policy (:mod:`difffilter.engines.policy`, ``DIFFFILTER_ENGINE``) never routes
    this filter to the compiled engine, whatever the call's size: its diffuse steps run eagerly.

    Learnable: ``Q``, ``R`` and the model's parameters; gradients flow through the scan.
    """

    uses_engine_policy = False

    def __init__(self, model: StateSpaceModel, *, joseph: bool = True) -> None:
        super().__init__(model, joseph=joseph)
        if model.dynamics.angular or model.measurement.angular:
            raise ValueError("ParallelKalmanFilter cannot wrap angular components; use KalmanFilter for a model with angular states")

    @scoped_forward
    def forward(
        self,
        measurements: Tensor,
        initial_mean: Tensor | None = None,
        initial_cov: Tensor | None = None,
        mask: Tensor | None = None,
        controls: Controls = None,
        *,
        belief: Belief | None = None,
    ) -> FilterResult:
        """Filter ``measurements [B, T, m]`` (arguments as :meth:`RecursiveFilter.forward`)."""
        z, mask3, mean0, cov0 = self.check_inputs(measurements, initial_mean, initial_cov, mask, controls)
        if belief is None and (mean0 is None or cov0 is None):
            raise ValueError("initial_mean and initial_cov are required unless belief= is given")
        bsz, steps = z.shape[:2]
        with parametrize.cached():
            derived = self.precompute_controls(controls)
            if belief is None:
                assert mean0 is not None and cov0 is not None  # checked above
                belief = self.start_belief(mean0, cov0, slice_controls(derived, 0))
            parts, t = [], 0
            # a diffuse part is resolved by the exact sequential update, step by step
            while t < steps and DIFFUSE_COV in belief:
                mk = None if mask3 is None else mask3[:, t : t + 1]
                part = RecursiveFilter.forward(self, z[:, t : t + 1], mask=mk, controls=slice_steps(controls, t, t + 1), belief=belief)
                parts.append(part)
                belief, t = part.final_belief, t + 1
            if t < steps:
                rest = slice_steps(derived, t, steps)
                system = linear_system(self, rest, bsz, steps - t, z)
                parts.append(self._scan(system, z[:, t:], None if mask3 is None else mask3[:, t:], belief))
        return concat_results(parts)

    def _scan(self, system: AffineSystem, z: Tensor, mask: Tensor | None, belief: Belief) -> FilterResult:
        mean, cov, pmean, pcov, loglik, nis, nobs = scan_filter(system, z, mask, belief["mean"], belief["cov"])
        untrusted = untrusted_steps(mean, cov, pcov, loglik)
        return FilterResult(
            mean=mean,
            cov=cov,
            prior_mean=pmean,
            prior_cov=pcov,
            log_likelihood=loglik,
            nis=nis,
            num_observed=nobs,
            final_belief={"mean": mean[:, -1], "cov": cov[:, -1]},
            extras={"untrusted": untrusted},
        )
