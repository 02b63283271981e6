"""Numerical-stability helpers used while learning (the jitter bound is
:func:`difffilter.linalg.jitter_bound`)."""

from __future__ import annotations

import warnings

__all__ = ["OnceWarner"]


class OnceWarner:
    """Emits each distinct warning key once per instance (counters keep the totals)."""

    def __init__(self) -> None:
        self._seen: set[str] = set()

    def __call__(self, key: str, message: str) -> None:
        if key not in self._seen:
            self._seen.add(key)
            warnings.warn(message, RuntimeWarning, stacklevel=3)
