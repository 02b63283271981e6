"""Training replicates: what one ``seed`` of a multirun changes.

``python experiments/train.py experiment=X -m seed=0,1,2,3,4`` trains five independent
replicates.  The ``seed`` drives

* the **training and validation data**: ``data.seeds`` are ``${replicate_seed:${seed},0}`` and
  ``${replicate_seed:${seed},1}`` = ``1000 seed + offset`` (seed 0 keeps the single-run seeds 0
  and 1), while the **test** seed stays fixed, so every replicate and every filter is evaluated
  on the same test runs and the comparisons can be paired;
* the **initial values** of the learned parameters: ``learner.init_perturbation`` (a log-scale
  standard deviation, default 0 = start from the hand-tuned values exactly) multiplies them by
  ``exp(sigma z)`` with ``z`` drawn from ``learner.init_seed`` (``${seed}``); bounded ones
  (``Bounded``: ``Psi``, ``rho``, ``delta``) take the step ``sigma z`` in logit space instead, so
  they stay inside their bounds, see :func:`perturb_initial_values`;
* everything else random in training (``pl.seed_everything(seed)``).

The ``replicate_seed`` resolver is registered with OmegaConf when this module is imported
(importing :mod:`difffilter.learn` does).
"""

from __future__ import annotations

import math
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
    # parametrizations is a ModuleDict on a parametrized module; nn.Module's __getattr__ types it
    # as Tensor | Module, which is not indexable by a name
    chain = list(module.parametrizations[attr])  # type: ignore[index]
    return chain[0] if len(chain) == 1 else None


def _logit_step(value: Tensor, lo: float, hi: float, z: Tensor, sigma: float) -> Tensor:
    """``lo + w sigmoid(logit((value - lo) / w) + sigma z)``, ``w = hi - lo``, computed in float64."""
    width = hi - lo
    u = torch.logit((value.double() - lo) / width)  # finite: the parametrization keeps value strictly inside
    return (lo + width * torch.sigmoid(u + sigma * z.double())).to(value.dtype)


def _log_fold(value: Tensor, lo: float, hi: float, z: Tensor, sigma: float) -> Tensor:
    """``value exp(sigma z)`` with ``log value`` folded back (mirrored) at ``log lo`` and ``log hi``."""
    product = value * torch.exp(sigma * z.to(value.dtype))  # the multiplicative step, bit for bit, where it stays inside
    a, length = math.log(lo), math.log(hi) - math.log(lo)
    t = torch.remainder(torch.log(value.double()) + sigma * z.double() - a, 2.0 * length)
    folded = torch.exp(a + torch.where(t <= length, t, 2.0 * length - t)).clamp(lo, hi).to(value.dtype)
    return torch.where((product > lo) & (product < hi), product, folded)


def _perturbed(value: Tensor, constraint: nn.Module | None, z: Tensor, sigma: float) -> Tensor:
    """``value`` moved by a step ``sigma z`` in the way its constraint allows (``z`` float64)."""
    if isinstance(constraint, Bounded) or (isinstance(constraint, Interval) and not constraint.log_scale):
        return _logit_step(value, constraint.lower, constraint.upper, z, sigma)
    if isinstance(constraint, Interval):
        return _log_fold(value, constraint.lower, constraint.upper, z, sigma)
    z = z.to(value.dtype)  # (the multiplicative steps in the value's dtype, as every committed sweep drew them)
    factor = torch.exp(sigma * z)
    square = value.ndim >= 2 and value.shape[-1] == value.shape[-2]
    if isinstance(constraint, RowStochastic):
        new = value * factor
        return new / new.sum(-1, keepdim=True)
    if square and bool(torch.allclose(value, value.mT)) and bool((torch.diagonal(value, dim1=-2, dim2=-1) > 0).all()):
        # a covariance: scale each component's standard deviation, keep the correlations (D V D)
        d = torch.exp(0.5 * sigma * z[..., 0, :])
        return value * d[..., :, None] * d[..., None, :]
    return value * factor


def perturb_initial_values(module: nn.Module, names: Sequence[str], sigma: float, *, seed: int) -> dict[str, Tensor]:
    """Move the constrained start values of ``names`` by independent seeded steps of size ``sigma``.

    With ``z ~ N(0, 1)`` per element:

    * positive scalars and vectors (noise sigmas, ``tau``), plain parameters: ``value exp(sigma z)``;
    * covariance matrices: ``D V D`` with ``D = diag(exp(sigma z / 2))`` (every variance scaled
      by ``exp(sigma z_i)``, correlations kept);
    * ``Bounded`` and linear ``Interval`` values in ``(lo, hi)``: a step in logit space,
      ``u = logit((value - lo) / w)``, ``w = hi - lo``, ``value' = lo + w sigmoid(u + sigma z)``.
      The start stays strictly inside, at logit distance exactly ``sigma |z|`` from the
      unperturbed one, i.e. where training on the logit parametrization can reach it.  Near the
      lower bound this is about the multiplicative step in ``value - lo`` (``rho``, ``delta`` near
      0: about ``value exp(sigma z)``); near the upper bound it is multiplicative in the distance
      ``hi - value`` (``rho = 0.95``: ``1 - rho`` is scaled by about ``exp(-sigma z)``); in the middle
      (``Psi = 0`` in ``(-1, 1)``, an exponent 0 in ``(-4, 4)``) it moves the value by about
      ``w sigma z / 4``, where the old multiplicative step left a zero start at zero.  A start on a
      bound (``rho = 1``) is held by the parametrization at the nearest representable value
      inside, a logit of about 37 (float64) or 17 (float32): the step leaves it there, on the
      bound the user chose.  (Before, the value was multiplied by ``exp(sigma z)`` and clamped to
      ``1e-6 w`` inside a bound it passed: a logit of 13.8, farther than a short training moves.)
    * log-scale ``Interval`` values (time constants spanning decades): ``value exp(sigma z)``, a
      step of ``sigma z`` in the constraint's own coordinate ``log value``, folded back (mirrored)
      at ``log lo`` and ``log hi``, so it stays inside; inside the bounds it is the
      multiplicative step unchanged;
    * row-stochastic matrices: element-wise ``exp(sigma z)``, then rows renormalised;
    * one ``Bounded``/``Interval`` value shared by several components (a constraint with an
      ``inner`` one, e.g. :class:`~experiments.papers.smartloc.SharedPsiColoredUKF`'s ``psi``): the
      step above with one draw for all of them;
    * when the parametrization cannot represent the perturbed value (a ``ScaledMatrix`` or
      grouped scale), one common factor ``exp(sigma z)`` for the whole value.

    Returns ``{dotted name: new value}``.  ``sigma = 0`` changes nothing.  The draws come from
    their own generator seeded with ``seed`` (reproducible, independent of the global RNG): one
    float64 ``torch.randn`` of each value's shape, in sorted name order.
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
            z = torch.randn(value.shape, generator=gen, dtype=torch.float64)
            constraint = _constraint(mod, attr)
            inner = getattr(constraint, "inner", None)
            if isinstance(inner, Bounded | Interval) and not isinstance(constraint, Bounded | Interval):
                # one bounded value shared by several components: one draw moves them together
                constraint, z = inner, z.flatten()[0].expand(value.shape)
            try:
                assign_parameters(module, {name: _perturbed(value, constraint, z, sigma)})
            except ValueError:
                # the constraint has fewer degrees of freedom (a scale times a fixed shape)
                assign_parameters(module, {name: value * torch.exp(sigma * z.to(value.dtype).flatten()[0])})
            out[name] = getattr(mod, attr).detach().clone()
    return out
