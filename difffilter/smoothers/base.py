"""Rauch-Tung-Striebel smoothing on top of any supported filter: the shared backward pass.

A smoother runs its filter forward over a window, then a backward pass over the filter's
posteriors ``(x_t, P_t)`` and priors ``(x-_t, P-_t)``:

.. math::
    G_t = C_t (P^-_t)^{-1},\\qquad
    x_{t-1|T} = x_{t-1} + G_t (x_{t|T} - x^-_t),\\qquad
    P_{t-1|T} = P_{t-1} + G_t (P_{t|T} - P^-_t) G_t^T,

with ``C_t = Cov(x_{t-1}, x_t | z_{0:t-1})`` the prediction's cross-covariance
(:mod:`difffilter.smoothers.transition`) and the lag-one smoothed cross-covariance
``P_{t-1,t|T} = G_t P_{t|T}``.  Conventions follow the filters: ``(initial_mean, initial_cov)``
(or a carried-over ``belief``) is the belief about ``x_{-1}``, the state before the first
measurement, so a window is smoothed against its own measurements and the prior it starts from,
and ``x_{-1}`` is smoothed too (``SmootherResult.initial_mean``).  Masks and controls are the
filter's: a missing step has posterior = prior and the backward pass needs nothing else.

Only the backward recursion runs as a Python loop over time; the cross-covariances and gains
of all ``B * T`` steps are computed in single batched calls (optionally in chunks of
``time_chunk`` steps to bound memory), and nothing loops over the batch.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor, nn
from torch._C import _functorch
from torch.nn.utils import parametrize

from ..filters.base import Belief, FilterResult, RecursiveFilter
from ..filters.scan import scan_rts
from ..linalg import psd_solve, safe_cholesky, symmetrize
from ..models.base import Controls, DynamicsModel
from ..threads import scoped_forward
from .backward import sequential_rts
from .result import SmootherResult

#: Default bound on the states (batch x time steps) of one batched cross-covariance call.
MAX_CHUNK_STATES = 65536
#: Ways :func:`rts_backward` solves the recursion.
BACKWARD_METHODS = ("auto", "sequential", "scan")
#: ``method="auto"`` scans windows of at least this many steps over at most
#: :data:`SCAN_MAX_BATCH` trajectories; larger batches amortise the loop's per-step cost, and
#: there the scan's extra passes over ``[B, T, n, n]`` make it slower (results/benchmark_engine.md:
#: B = 1, T = 5000: scan 6x faster; B = 256, T = 500: sequential 2.5-4x faster).
SCAN_MIN_STEPS = 32
SCAN_MAX_BATCH = 8

__all__ = [
    "BACKWARD_METHODS",
    "MAX_CHUNK_STATES",
    "SCAN_MAX_BATCH",
    "SCAN_MIN_STEPS",
    "Smoother",
    "flatten_steps",
    "previous_posteriors",
    "rts_backward",
    "rts_step",
    "smoother_gains",
]


def flatten_steps(controls: Controls, start: int, stop: int) -> Controls:
    """Steps ``start:stop`` of per-step inputs ``[B, T, ...]`` as one batch ``[B * (stop - start), ...]``."""
    if controls is None:
        return None

    def flat(v: Tensor) -> Tensor:
        return v[:, start:stop].reshape(-1, *v.shape[2:])

    return flat(controls) if isinstance(controls, Tensor) else {k: flat(v) for k, v in controls.items()}


def previous_posteriors(result: FilterResult, initial: Belief) -> tuple[Tensor, Tensor]:
    """``(x_{t-1}, P_{t-1})`` for ``t = 0..T-1`` ``[B, T, n]``, ``[B, T, n, n]``: the initial belief,
    then the filter's posteriors shifted by one step."""
    mean = torch.cat([initial["mean"][:, None], result.mean[:, :-1]], 1)
    cov = torch.cat([initial["cov"][:, None], result.cov[:, :-1]], 1)
    return mean, cov


def _plain(*tensors: Tensor) -> bool:
    """Whether none of ``tensors`` is wrapped by a ``torch.func`` transform: the hand-written
    reverse modes here (:class:`_GainSolve`, :func:`~difffilter.smoothers.backward.sequential_rts`)
    are for plain autograd only."""
    return all(_functorch.maybe_get_level(x) == -1 for x in tensors)


class _GainSolve(torch.autograd.Function):
    """``G = C P^{-1}`` from the Cholesky factor ``L`` of ``P``, with the solve's own reverse mode:
    ``dC = dG P^{-1}`` (one more solve with the same factor), ``dP = -G^T dC``; torch's would
    differentiate the factorisation itself (``cholesky`` backward), which costs several times
    the solve on the ``B * T`` matrices of a window."""

    @staticmethod
    def forward(cross: Tensor, cov: Tensor, chol: Tensor) -> Tensor:
        return torch.cholesky_solve(cross.mT, chol).mT

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Tensor, Tensor, Tensor], output: Tensor) -> None:
        ctx.save_for_backward(inputs[2], output)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, Tensor, None]:
        chol, gain = ctx.saved_tensors
        d_cross = torch.cholesky_solve(grad.mT, chol).mT
        return d_cross, symmetrize(-(gain.mT @ d_cross)), None


def smoother_gains(cross_cov: Tensor, prior_cov: Tensor) -> Tensor:
    """``G = C (P^-)^{-1}`` ``[..., n, n]`` by a Cholesky solve (never an inverse).

    With gradients, the solve is differentiated as a solve (:class:`_GainSolve`) when every factor
    came out without jitter; under a ``torch.func`` transform or after a repair (jitter, or an
    identity stand-in for a failed factor, whose gradient must not reach ``P``) it is torch's
    differentiation of the factorisation, as before."""
    cov = symmetrize(prior_cov)
    if not (_plain(cross_cov, cov) and torch.is_grad_enabled() and (cov.requires_grad or cross_cov.requires_grad)):
        return psd_solve(cov, cross_cov.mT).mT
    with torch.no_grad():
        chol, jitter = safe_cholesky(cov)
    if bool(jitter.any()):
        return psd_solve(cov, cross_cov.mT).mT
    return _GainSolve.apply(cross_cov, cov, chol)


def rts_step(
    mean: Tensor,
    cov: Tensor,
    gain: Tensor,
    prior_mean: Tensor,
    prior_cov: Tensor,
    s_mean: Tensor,
    s_cov: Tensor,
    space: DynamicsModel | None = None,
) -> tuple[Tensor, Tensor]:
    """One backward step: smoothed ``(x_{t-1|T}, P_{t-1|T})`` from the posterior at ``t - 1``,
    the gain and prior at ``t`` and the smoothed moments at ``t`` (any leading dimensions).

    When ``space`` (the filter's dynamics) declares angular states, the correction is
    ``space.add(x, G space.residual(x_s, x-))``: both differences and the sum wrapped."""
    if space is not None and space.angular:
        step = (gain @ space.residual(s_mean, prior_mean)[..., None])[..., 0]
        new_mean = space.add(mean, step)
    else:
        new_mean = mean + (gain @ (s_mean - prior_mean)[..., None])[..., 0]
    new_cov = symmetrize(cov + gain @ (s_cov - prior_cov) @ gain.mT)
    return new_mean, new_cov


def rts_backward(
    mean: Tensor,
    cov: Tensor,
    prior_mean: Tensor,
    prior_cov: Tensor,
    gains: Tensor,
    initial_mean: Tensor,
    initial_cov: Tensor,
    space: DynamicsModel | None = None,
    *,
    method: str = "auto",
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Fixed-interval backward pass.

    Args:
        mean, cov: filter posteriors ``[B, T, n]``, ``[B, T, n, n]``.
        prior_mean, prior_cov: filter priors at the same steps.
        gains: ``G_t`` ``[B, T, n, n]`` linking ``x_{t-1}`` (``x_{-1}`` for ``t = 0``) and ``x_t``.
        initial_mean, initial_cov: the belief about ``x_{-1}`` ``[B, n]``, ``[B, n, n]``.
        space: the filter's dynamics model; its angular states are wrapped (:func:`rts_step`).
        method: ``"sequential"`` (a loop over time), ``"scan"`` (the same affine recursion by a
            reverse associative scan, :func:`~difffilter.filters.scan.scan_rts`: ``O(log T)``
            batched levels instead of ``T`` small steps) or ``"auto"`` (the scan for at most
            :data:`SCAN_MAX_BATCH` trajectories of at least :data:`SCAN_MIN_STEPS` steps, unless
            angular states need the wrapped step, which is not affine).  Both agree to rounding;
            the sequential loop is one autograd node (:mod:`difffilter.smoothers.backward`).

    Returns ``(mean, cov, cross_cov, initial_mean, initial_cov)`` smoothed, with
    ``cross_cov[:, t] = P_{t-1,t|T}``.
    """
    if method not in BACKWARD_METHODS:
        raise ValueError(f"method must be one of {list(BACKWARD_METHODS)}, got {method!r}")
    angular = space is not None and bool(space.angular)
    if method == "scan" and angular:
        raise ValueError("method='scan' cannot wrap angular states (the wrapped step is not affine); use 'sequential' or 'auto'")
    small = mean.shape[0] <= SCAN_MAX_BATCH and mean.shape[1] >= SCAN_MIN_STEPS
    if method == "scan" or (method == "auto" and not angular and small):
        return scan_rts(gains, mean, cov, prior_mean, prior_cov, initial_mean, initial_cov)
    args = (mean, cov, prior_mean, prior_cov, gains, initial_mean, initial_cov)
    if not angular and _plain(*args):
        return sequential_rts(*args)
    # unbind once: indexing [:, t] inside the loop would make every step's backward fill a
    # zero gradient of the whole [B, T, ...] tensor (quadratic in T)
    m_t, p_t, pm_t, pp_t, g_t = (x.unbind(1) for x in (mean, cov, prior_mean, prior_cov, gains))
    s_mean, s_cov = m_t[-1], p_t[-1]
    means, covs, crosses = [s_mean], [s_cov], []
    for t in range(len(m_t) - 1, -1, -1):
        g = g_t[t]
        crosses.append(g @ s_cov)
        prev_m, prev_p = (m_t[t - 1], p_t[t - 1]) if t > 0 else (initial_mean, initial_cov)
        s_mean, s_cov = rts_step(prev_m, prev_p, g, pm_t[t], pp_t[t], s_mean, s_cov, space)
        means.append(s_mean)
        covs.append(s_cov)
    init_mean, init_cov = means.pop(), covs.pop()
    rev = lambda xs: torch.stack(xs[::-1], 1)  # noqa: E731
    return rev(means), rev(covs), rev(crosses), init_mean, init_cov


class Smoother(nn.Module):
    """Base class of the smoothers: holds a filter (and through it the parameters), never beliefs.

    ``smoother(measurements, initial_mean, initial_cov, mask=None, controls=None, belief=None)``
    takes exactly a filter's arguments and returns a :class:`SmootherResult`;
    :meth:`smooth` runs only the backward pass on a :class:`FilterResult` computed elsewhere
    (e.g. by :class:`~difffilter.filters.FusedFilter` running the same filter).

    Args:
        filter: the forward filter.
        time_chunk: compute the cross-covariances of at most this many time steps per batched
            call (``None``: as many as keep a call within :data:`MAX_CHUNK_STATES` states, which
            bounds the memory of the sigma points of long windows; results do not depend on it).
    """

    def __init__(self, filter: RecursiveFilter, *, time_chunk: int | None = None) -> None:  # noqa: A002 - the field's word
        super().__init__()
        if not isinstance(filter, RecursiveFilter):
            raise TypeError(f"filter must be a difffilter RecursiveFilter, got {type(filter).__name__}")
        if time_chunk is not None and int(time_chunk) < 1:
            raise ValueError(f"time_chunk must be a positive int or None, got {time_chunk!r}")
        self.filter = filter
        self.time_chunk = None if time_chunk is None else int(time_chunk)

    @property
    def state_dim(self) -> int:
        return self.filter.state_dim

    def initial_belief(
        self, measurements: Tensor, initial_mean: Tensor | None, initial_cov: Tensor | None, belief: Belief | None
    ) -> Belief:
        """The belief about ``x_{-1}`` a window starts from (``belief`` if given)."""
        if belief is not None:
            return belief
        if initial_mean is None or initial_cov is None:
            raise ValueError("initial_mean and initial_cov are required unless belief= is given")
        return self.filter.initial_belief(initial_mean, initial_cov, batch_size=measurements.shape[0])

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
    ) -> SmootherResult:
        """Filter ``measurements [B, T, m]`` forward, then smooth (arguments as the filter's)."""
        result = self.filter(measurements, initial_mean, initial_cov, mask=mask, controls=controls, belief=belief)
        return self.smooth(result, self.initial_belief(measurements, initial_mean, initial_cov, belief), controls)

    def smooth(self, result: FilterResult, initial: Belief, controls: Controls = None) -> SmootherResult:  # pragma: no cover - abstract
        """Backward pass over ``result`` of a window that started from the belief ``initial``."""
        raise NotImplementedError

    def per_step(
        self, fn: Callable[[Tensor, Tensor, Controls], Tensor], mean: Tensor, cov: Tensor, controls: Controls, *, whole: bool = False
    ) -> Tensor:
        """``fn(mean, cov, u)`` evaluated on all ``[B, T]`` steps as one flattened batch (in chunks
        of ``time_chunk`` steps, or in one call when ``whole`` says ``fn`` needs no more memory
        than its inputs), reshaped to ``[B, T, ...]``; ``mean [B, T, n]``, ``cov [B, T, n, n]``."""
        bsz, steps, n = mean.shape
        chunk = steps if whole else self.time_chunk or max(1, MAX_CHUNK_STATES // bsz)
        outs = []
        with parametrize.cached():
            if chunk >= steps:  # one call: no concatenation, no slices to fill with zeros in the backward pass
                out = fn(mean.reshape(-1, n), cov.reshape(-1, n, n), flatten_steps(controls, 0, steps))
                return out.reshape(bsz, steps, *out.shape[1:])
            for start in range(0, steps, chunk):
                stop = min(start + chunk, steps)
                m = mean[:, start:stop].reshape(-1, n)
                p = cov[:, start:stop].reshape(-1, n, n)
                out = fn(m, p, flatten_steps(controls, start, stop))
                outs.append(out.reshape(bsz, stop - start, *out.shape[1:]))
        return torch.cat(outs, 1)
