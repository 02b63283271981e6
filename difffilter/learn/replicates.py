"""Training replicates: what one ``seed`` of a multirun changes.

``python experiments/train.py experiment=X -m seed=0,1,2,3,4`` trains five independent
replicates.  The ``seed`` drives

* the **training and validation data**: ``data.seeds`` are ``${replicate_seed:${seed},0}`` and
  ``${replicate_seed:${seed},1}`` = ``1000 seed + offset`` (seed 0 keeps the single-run seeds 0
  and 1), while the **test** seed stays fixed, so every replicate and every filter is evaluated
  on the same test runs and the comparisons can be paired;
* the **initial values** of the learned parameters: ``learner.init_perturbation`` (a log-scale
  standard deviation, default 0 = start from the hand-tuned values exactly) multiplies them by
  ``exp(sigma z)`` with ``z`` drawn from ``learner.init_seed`` (``${seed}``), see
  :func:`perturb_initial_values`;
* everything else random in training (``pl.seed_everything(seed)``).

The ``replicate_seed`` resolver is registered with OmegaConf when this module is imported
(importing :mod:`difffilter.learn` does).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import torch
from omegaconf import OmegaConf
from torch import Tensor, nn
from torch.nn.utils import parametrize

from ..params import Bounded, Interval, RowStochastic
from ..selection import assign_parameters, parameter_owners

__all__ = ["SEED_STRIDE", "perturb_initial_values", "replicate_seed"]

#: Distance between the data seeds of consecutive replicates (the offsets 0, 1 of the splits stay below it).
SEED_STRIDE = 1000


def replicate_seed(seed: int | str, offset: int | str) -> int:
    """Data seed of split ``offset`` (train 0, val 1) for replicate ``seed``: ``1000 seed + offset``."""
    s, o = int(seed), int(offset)
    if s < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed}")
    if not 0 <= o < SEED_STRIDE:
        raise ValueError(f"offset must lie in [0, {SEED_STRIDE}), got {offset}")
    return SEED_STRIDE * s + o


OmegaConf.register_new_resolver("replicate_seed", replicate_seed, replace=True)


def _constraint(module: nn.Module, attr: str) -> nn.Module | None:
    if not parametrize.is_parametrized(module, attr):
        return None
    chain = list(module.parametrizations[attr])  # type: ignore[index,union-attr]
    return chain[0] if len(chain) == 1 else None


def _perturbed(value: Tensor, constraint: nn.Module | None, z: Tensor, sigma: float) -> Tensor:
    """``value`` moved by a log-scale step ``sigma z`` in the way its constraint allows."""
    factor = torch.exp(sigma * z)
    square = value.ndim >= 2 and value.shape[-1] == value.shape[-2]
    if isinstance(constraint, RowStochastic):
        new = value * factor
        return new / new.sum(-1, keepdim=True)
    if isinstance(constraint, Bounded | Interval):
        lo, hi = (constraint.lower, constraint.upper)
        width = hi - lo
        return (value * factor).clamp(lo + 1e-6 * width, hi - 1e-6 * width)
    if square and bool(torch.allclose(value, value.mT)) and bool((torch.diagonal(value, dim1=-2, dim2=-1) > 0).all()):
        # a covariance: scale each component's standard deviation, keep the correlations (D V D)
        d = torch.exp(0.5 * sigma * z[..., 0, :])
        return value * d[..., :, None] * d[..., None, :]
    return value * factor


def _warn_if_past_bound(name: str, moved: Tensor, lo: float, hi: float) -> None:
    """Say when a perturbed bounded start is clamped: it then sits 1e-6 of the width inside the
    bound, ~14 logit units out, further than a short training moves it (p001's two failed seeds).
    The clamp itself is kept: every seeded start of the committed sweeps depends on it."""
    margin = 1e-6 * (hi - lo)  # the clamp of _perturbed
    past = int(((moved < lo + margin) | (moved > hi - margin)).sum())
    if past:
        warnings.warn(
            f"init_perturbation moved {past} element(s) of {name!r} past its bound [{lo}, {hi}]; they start 1e-6 of the "
            "width inside it, where a bounded (logit) parametrization barely moves — consider a smaller init_perturbation",
            RuntimeWarning,
            stacklevel=3,
        )


def perturb_initial_values(module: nn.Module, names: Sequence[str], sigma: float, *, seed: int) -> dict[str, Tensor]:
    """Multiply the constrained values of ``names`` by independent log-normal factors ``exp(sigma z)``.

    * positive scalars and vectors (noise sigmas, ``tau``), plain parameters: element-wise;
    * covariance matrices: ``D V D`` with ``D = diag(exp(sigma z / 2))`` (every variance scaled
      by ``exp(sigma z_i)``, correlations kept);
    * ``Interval``/``Bounded`` values: element-wise, then clamped inside the bounds;
    * row-stochastic matrices: element-wise, then rows renormalised;
    * when the parametrization cannot represent the perturbed value (a ``ScaledMatrix`` or
      grouped scale), one common factor ``exp(sigma z)`` for the whole value.

    Returns ``{dotted name: new value}``.  ``sigma = 0`` changes nothing.  The draws come from
    their own generator seeded with ``seed`` (reproducible, independent of the global RNG).
    """
    sigma = float(sigma)
    if not (math.isfinite(sigma) and sigma >= 0.0):
        raise ValueError(f"init_perturbation must be a non-negative number (log-scale std), got {sigma}")
    if sigma == 0.0:
        return {}
    gen = torch.Generator().manual_seed(int(seed))
    owners = parameter_owners(module)
    out: dict[str, Tensor] = {}
    for name in sorted(set(names)):
        mod, attr, _ = owners[name]
        with torch.no_grad():
            value = getattr(mod, attr).detach().clone()
            z = torch.randn(value.shape, generator=gen, dtype=torch.float64).to(value.dtype)
            constraint = _constraint(mod, attr)
            if isinstance(constraint, Bounded | Interval):
                _warn_if_past_bound(name, value * torch.exp(sigma * z), constraint.lower, constraint.upper)
            try:
                assign_parameters(module, {name: _perturbed(value, constraint, z, sigma)})
            except ValueError:
                # the constraint has fewer degrees of freedom (a scale times a fixed shape)
                assign_parameters(module, {name: value * torch.exp(sigma * z.flatten()[0])})
            out[name] = getattr(mod, attr).detach().clone()
    return out
