"""The RTS smoother parallel in time: :class:`ParallelRTSSmoother`."""

from __future__ import annotations

from ..filters.base import Belief, FilterResult, RecursiveFilter
from ..filters.diffuse import total_cov
from ..filters.kalman import KalmanFilter
from ..filters.parallel import linear_system
from ..filters.scan import scan_smoother
from ..models.base import Controls
from .base import Smoother
from .result import SmootherResult

__all__ = ["ParallelRTSSmoother"]


class ParallelRTSSmoother(Smoother):
    """Rauch-Tung-Striebel smoother for linear-Gaussian models by a reverse associative scan.

    The smoothed moments of all steps (and of ``x_{-1}``, the state before the first
    measurement) from one scan of ``O(log T)`` sequential depth over the elements
    ``E_k = G_k``, ``g_k = x_{k|k} - G_k x^-_{k+1}``, ``L_k = P_{k|k} - G_k P^-_{k+1} G_k^T``
    (Särkkä & García-Fernández 2021; :mod:`difffilter.filters.scan`); equal to
    :class:`~difffilter.smoothers.RTSSmoother` on a :class:`~difffilter.filters.KalmanFilter` up
    to rounding, with the same :class:`SmootherResult` (lag-one ``cross_cov`` included).

    The forward pass is ``filter``'s: a :class:`~difffilter.filters.ParallelKalmanFilter` makes
    the whole smoother parallel; a :class:`~difffilter.filters.KalmanFilter` runs sequentially
    and only the backward pass is scanned.  Masks, controls and per-step matrices as the filter.

    Example::

        smoother = ParallelRTSSmoother(ParallelKalmanFilter(model))
        out = smoother(z, m0, P0, mask=mask)   # out.mean [B, T, n], out.filtered: the filter's result

    Args:
        filter: a :class:`~difffilter.filters.KalmanFilter` (or its parallel subclass).

    Learnable: the filter's parameters (gradients flow through both scans).
    """

    def __init__(self, filter: RecursiveFilter) -> None:  # noqa: A002 - the field's word
        if not isinstance(filter, KalmanFilter):
            raise TypeError(f"ParallelRTSSmoother needs a KalmanFilter or ParallelKalmanFilter, got {type(filter).__name__}")
        super().__init__(filter)

    def smooth(self, result: FilterResult, initial: Belief, controls: Controls = None) -> SmootherResult:
        """Backward scan over ``result`` of a window that started from the belief ``initial``."""
        bsz, steps = result.mean.shape[:2]
        system = linear_system(self.filter, self.filter.precompute_controls(controls), bsz, steps, result.mean)  # type: ignore[arg-type]
        mean, cov, cross, m0, p0 = scan_smoother(
            system, result.mean, result.cov, result.prior_mean, result.prior_cov, initial["mean"], total_cov(initial)
        )
        return SmootherResult(mean=mean, cov=cov, filtered=result, cross_cov=cross, initial_mean=m0, initial_cov=p0)
