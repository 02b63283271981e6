"""Sigma-point sets for unscented / cubature filters.

Every set places points at ``mean``, ``mean + gamma * L[:, i]`` and ``mean - gamma * L[:, i]``
(``L`` a square root of the covariance, columns ``i = 1..n``), in that order, with mean weights
``wm`` and covariance weights ``wc``; the centre point is omitted when the set has none.
Weights are computed once per ``(n, dtype, device)`` and cached.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["Cubature", "Julier", "MerweScaled", "SigmaPoints"]


class SigmaPoints:
    """Base class: subclasses define :meth:`_lambda` (or override the weight rules)."""

    has_center: bool = True

    def __init__(self) -> None:
        self._cache: dict[tuple[int, torch.dtype, torch.device], tuple[Tensor, Tensor]] = {}

    def _lambda(self, n: int) -> float:  # pragma: no cover - abstract
        raise NotImplementedError

    def _center_weights(self, n: int, lam: float) -> tuple[float, float]:
        w0 = lam / (n + lam)
        return w0, w0

    def gamma(self, n: int) -> float:
        """Spread ``sqrt(n + lambda)`` of the points along each square-root column."""
        lam = self._lambda(n)
        if n + lam <= 0:
            raise ValueError(f"{type(self).__name__}: n + lambda must be > 0 for n = {n} (got {n + lam})")
        return math.sqrt(n + lam)

    def num_points(self, n: int) -> int:
        return 2 * n + (1 if self.has_center else 0)

    def weights(self, n: int, dtype: torch.dtype, device: torch.device | str = "cpu") -> tuple[Tensor, Tensor]:
        """Mean and covariance weights ``([S], [S])``."""
        key = (n, dtype, torch.device(device))
        if key not in self._cache:
            g2 = self.gamma(n) ** 2
            wi = 1.0 / (2.0 * g2)
            if self.has_center:
                wm0, wc0 = self._center_weights(n, self._lambda(n))
                wm = [wm0] + [wi] * (2 * n)
                wc = [wc0] + [wi] * (2 * n)
            else:
                wm = wc = [wi] * (2 * n)
            self._cache[key] = (
                torch.tensor(wm, dtype=dtype, device=device),
                torch.tensor(wc, dtype=dtype, device=device),
            )
        return self._cache[key]

    def generate(self, mean: Tensor, sqrt_cov: Tensor) -> Tensor:
        """Points ``[..., S, n]`` from ``mean [..., n]`` and lower square root ``[..., n, n]``."""
        n = mean.shape[-1]
        offsets = self.gamma(n) * sqrt_cov.mT  # rows = scaled columns of L
        center = mean[..., None, :]
        parts = [center] if self.has_center else []
        parts += [center + offsets, center - offsets]
        return torch.cat(parts, -2)

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v}" for k, v in vars(self).items() if not k.startswith("_"))
        return f"{type(self).__name__}({args})"


class Julier(SigmaPoints):
    """Julier's set: ``lambda = kappa``, ``W0 = kappa / (n + kappa)``, ``Wi = 1 / (2 (n + kappa))``.

    p000 uses ``n + kappa = 3`` (``kappa = 3 - n``, a negative centre weight for ``n > 3``).
    """

    def __init__(self, kappa: float = 0.0) -> None:
        super().__init__()
        self.kappa = float(kappa)

    def _lambda(self, n: int) -> float:
        return self.kappa


class MerweScaled(SigmaPoints):
    """Scaled set: ``lambda = alpha^2 (n + kappa) - n``; ``Wc0 = Wm0 + 1 - alpha^2 + beta``."""

    def __init__(self, alpha: float = 1e-3, beta: float = 2.0, kappa: float = 0.0) -> None:
        super().__init__()
        if alpha <= 0:
            raise ValueError(f"alpha must be > 0, got {alpha}")
        self.alpha, self.beta, self.kappa = float(alpha), float(beta), float(kappa)

    def _lambda(self, n: int) -> float:
        return self.alpha**2 * (n + self.kappa) - n

    def _center_weights(self, n: int, lam: float) -> tuple[float, float]:
        wm0 = lam / (n + lam)
        return wm0, wm0 + 1.0 - self.alpha**2 + self.beta


class Cubature(SigmaPoints):
    """Third-degree spherical-radial cubature: ``2n`` equally weighted points at ``+-sqrt(n)``."""

    has_center = False

    def _lambda(self, n: int) -> float:
        return 0.0
