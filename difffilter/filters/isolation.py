"""Keep one non-finite trajectory from reaching the other trajectories' gradients.

Every trajectory of a batch is filtered independently, so its *values* never mix with another's.
Its *gradients* can: the parameters (``Q``, ``R``...) are shared, and their gradient is a sum
over the batch of each trajectory's contribution.  A trajectory whose run turns non-finite (a
NaN control, a measurement at 1e300 whose square overflows) contributes ``0 * inf = NaN`` to
that sum even when the loss leaves it out (the learner drops non-finite trajectories from its
mean), so one bad trajectory made every parameter gradient NaN.

:func:`isolated_run` runs the batch once; when gradients are being recorded and some
trajectories' results are non-finite anywhere (any entry of ``mean``, ``cov``, ``prior_mean``,
``prior_cov``, ``log_likelihood`` or ``nis``), it runs the finite ones again as a batch of their
own and returns a result whose rows for those come from that second run (with their gradients)
and whose rows for the others are the first run's values, detached: they are flagged in
``extras["untrusted"]`` and pass no gradient anywhere, which is all a non-finite run could pass
on.  A batch without a non-finite trajectory costs one check of the outputs; no gradient, one
trajectory, or every trajectory non-finite costs nothing more.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from ..linalg import inside_vmap, nonfinite_rows
from .protocol import FilterResult

__all__ = ["isolated_run", "nonfinite_trajectories"]

_FIELDS = ("mean", "cov", "prior_mean", "prior_cov", "log_likelihood", "nis", "num_observed")


def nonfinite_trajectories(result: FilterResult) -> Tensor:
    """``[B]`` bool: trajectories with a non-finite entry in any of the result's main fields."""
    bad: Tensor | None = None
    for name in _FIELDS[:-1]:
        v = getattr(result, name)
        if v.is_floating_point():
            # a field shared by the batch (expanded, stride 0: a Kalman filter's common
            # covariances) is checked once, not once per trajectory
            shared = v.dim() > 1 and v.shape[0] > 1 and v.stride(0) == 0
            row = nonfinite_rows(v[:1] if shared else v)
            row = row.expand(v.shape[0]) if shared else row
            bad = row if bad is None else bad | row
    assert bad is not None
    return bad


def _take(x: Any, idx: Tensor, bsz: int) -> Any:
    """Rows ``idx`` of the batch dimension of a batch-first tensor / dict of tensors (masks,
    controls, beliefs; an entry whose first size is not the batch's is shared and kept)."""
    if isinstance(x, Tensor):
        return x.index_select(0, idx) if x.dim() > 0 and x.shape[0] == bsz else x
    if isinstance(x, dict):
        return {k: _take(v, idx, bsz) for k, v in x.items()}
    return x


def _merge(full: Any, part: Any, idx: Tensor, bsz: int) -> Any:
    """``full`` detached, with rows ``idx`` replaced by ``part`` (differentiably)."""
    if isinstance(full, Tensor):
        if full.dim() == 0 or full.shape[0] != bsz or not isinstance(part, Tensor) or part.shape[1:] != full.shape[1:]:
            return full
        return full.detach().index_copy(0, idx, part.to(full.dtype))
    if isinstance(full, dict):
        return {k: _merge(v, part.get(k) if isinstance(part, dict) else None, idx, bsz) for k, v in full.items()}
    return full


def isolated_run(
    run: Callable[..., FilterResult],
    measurements: Tensor,
    initial_mean: Tensor | None,
    initial_cov: Tensor | None,
    mask: Tensor | None,
    controls: Any,
    belief: dict[str, Tensor] | None,
) -> FilterResult:
    """``run(measurements, initial_mean, initial_cov, mask, controls, belief=belief)`` with the
    non-finite trajectories' gradients cut off from the rest (module docstring)."""
    result = run(measurements, initial_mean, initial_cov, mask, controls, belief=belief)
    bsz = measurements.shape[0]
    if bsz < 2 or not torch.is_grad_enabled() or not any(getattr(result, f).requires_grad for f in _FIELDS[:-1]):
        return result
    if inside_vmap():  # each sample is its own run there: nothing mixes, and values cannot be read
        return result
    bad = nonfinite_trajectories(result)
    if not bool(bad.any()) or bool(bad.all()):
        return result
    idx = (~bad).nonzero()[:, 0]
    sub = run(
        measurements.index_select(0, idx),
        initial_mean.index_select(0, idx) if initial_mean is not None and initial_mean.dim() == 2 else initial_mean,
        initial_cov.index_select(0, idx) if initial_cov is not None and initial_cov.dim() == 3 else initial_cov,
        _take(mask, idx, bsz),
        _take(controls, idx, bsz),
        belief=_take(belief, idx, bsz),
    )
    merged = {f: _merge(getattr(result, f), getattr(sub, f), idx, bsz) for f in _FIELDS}
    return FilterResult(
        **merged,
        final_belief=_merge(result.final_belief, sub.final_belief, idx, bsz),
        extras=_merge(result.extras, sub.extras, idx, bsz),
    )
