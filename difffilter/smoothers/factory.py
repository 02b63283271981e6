"""Pick the smoother for a filter from a name (what the ``smoother`` config group sets)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..filters.base import RecursiveFilter
from ..mixers.imm import IMM
from .base import Smoother
from .fixed_lag import FixedLagSmoother
from .imm import IMMSmoother
from .rts import RTSSmoother

__all__ = ["make_smoother", "smoother_spec"]

KINDS = ("rts", "fixed_lag")


def smoother_spec(spec: str | Mapping[str, Any] | None) -> dict[str, Any] | None:
    """Normalise a smoother choice: ``None``, ``"rts"``, ``"fixed_lag"`` or a mapping with ``kind``
    (and ``lag``, ``time_chunk``, ``train``, ``evaluate``) -> a plain dict or ``None``."""
    if spec is None:
        return None
    out = {"kind": spec} if isinstance(spec, str) else dict(spec)
    if out.get("kind") is None:
        return None
    if out["kind"] not in KINDS:
        raise ValueError(f"smoother kind must be one of {list(KINDS)} (or null for none), got {out['kind']!r}")
    unknown = set(out) - {"kind", "lag", "time_chunk", "train", "evaluate"}
    if unknown:
        raise ValueError(f"unknown smoother settings {sorted(unknown)}; known: kind, lag, time_chunk, train, evaluate")
    if out["kind"] == "fixed_lag" and out.get("lag") is None:
        raise ValueError("smoother kind 'fixed_lag' needs lag (an int >= 0)")
    return out


def make_smoother(filter: RecursiveFilter, kind: str = "rts", *, lag: int | None = None, time_chunk: int | None = None) -> Smoother:  # noqa: A002
    """The smoother of ``kind`` for ``filter``.

    ``"rts"``: :class:`IMMSmoother` for an :class:`~difffilter.mixers.IMM`, else
    :class:`RTSSmoother` (extended RTS for KF/EKF, unscented RTS for the UKF family).
    ``"fixed_lag"``: :class:`FixedLagSmoother` with ``lag``.  Raises ``TypeError`` for filters
    no smoother supports (``Blend``, ``ColoredNoiseUKF``) and ``ValueError`` for a bad kind.
    """
    spec = smoother_spec({"kind": kind, "lag": lag})
    assert spec is not None
    if isinstance(filter, IMM):
        if spec["kind"] != "rts":
            raise ValueError("IMM filters support the fixed-interval smoother only (kind='rts')")
        return IMMSmoother(filter, time_chunk=time_chunk)
    if spec["kind"] == "fixed_lag":
        return FixedLagSmoother(filter, lag=int(spec["lag"]), time_chunk=time_chunk)
    return RTSSmoother(filter, time_chunk=time_chunk)
