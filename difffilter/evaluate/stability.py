"""Numerical-stability helpers used while learning."""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator

from .. import linalg

__all__ = ["OnceWarner", "bounded_jitter"]


@contextlib.contextmanager
def bounded_jitter(max_jitter: float | None) -> Iterator[None]:
    """Limit the relative jitter :func:`difffilter.linalg.safe_cholesky` may add (its ladder
    :data:`~difffilter.linalg.JITTER_LEVELS` is cut at ``max_jitter``) inside the block
    (:func:`difffilter.linalg.jitter_bound`).

    A smaller bound keeps an ill-conditioned covariance from being silently regularised by a
    large jitter (up to 1e-2 of its mean diagonal by default); what then happens to a matrix that
    still fails is ``safe_cholesky``'s rule (an identity factor for that batch element), so use a
    bound only where the covariances are known to be well conditioned.  ``None`` leaves the
    library default.  The bound is restored on exit; process-wide (not thread-safe).
    """
    with linalg.jitter_bound(max_jitter):
        yield


class OnceWarner:
    """Emits each distinct warning key once per instance (counters keep the totals)."""

    def __init__(self) -> None:
        self._seen: set[str] = set()

    def __call__(self, key: str, message: str) -> None:
        if key not in self._seen:
            self._seen.add(key)
            warnings.warn(message, RuntimeWarning, stacklevel=3)
