"""The pseudorange noise models the real-data protocol compares, and their starting values.

Every variant is the loader's odometry + pseudorange model (:func:`~experiments.papers.smartloc.model.make_smartloc_model`)
with a different ``R``:

* ``receiver`` - ``R = diag(pr_var)``, the receiver's own variances (the hand-tuned filter);
* ``scale`` - ``R = s diag(pr_var)``, one learnable scale (the "single-scale R");
* ``elev_cn0`` - ``sigma^2 = a_g + b_g / sin^2(el) + c_g 10^(-C/N0/10)`` per constellation ``g``
  (GPS, GLONASS), from side information only;
* ``receiver_elev_cn0`` - ``sigma^2 = s_g pr_var + b_g / sin^2(el) + c_g 10^(-C/N0/10)``: the
  receiver's variance plus elevation and C/N0 terms.

The side-information terms start from a non-negative least-squares fit of the receiver's variances
on the training epochs (:func:`fit_variance_terms`), so every variant starts near the hand-tuned
noise level.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from difffilter.models.heteroscedastic import CN0Variance, ElevationVariance, ScaledVariance, SumVariance

from .data import SmartLocData

__all__ = ["VARIANTS", "fit_variance_terms", "noise_model", "start_coefficients"]

VARIANTS = ("receiver", "scale", "elev_cn0", "receiver_elev_cn0")


def _features(data: SmartLocData, first: int, stop: int, elevation_mask_deg: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    sl = slice(first, stop)
    used = data.mask[sl] & (data.elevation[sl] >= elevation_mask_deg)
    el = torch.deg2rad(data.elevation[sl][used])
    inv_cn0 = torch.pow(10.0, -data.cn0[sl][used] / 10.0)
    feats = torch.stack([torch.ones_like(el), 1.0 / torch.sin(el) ** 2, inv_cn0, data.pr_var[sl][used]], -1)
    return feats, data.pr_var[sl][used], data.constellation[sl][used], used


def _nnls(a: Tensor, y: Tensor) -> Tensor:
    """Non-negative least squares for a few columns by enumerating the active sets."""
    best, best_err = torch.zeros(a.shape[1], dtype=a.dtype), float(y.pow(2).sum())
    for r in range(1, a.shape[1] + 1):
        for cols in itertools.combinations(range(a.shape[1]), r):
            sol = torch.linalg.lstsq(a[:, list(cols)], y[:, None]).solution[:, 0]
            if bool((sol >= 0).all()):
                err = float((a[:, list(cols)] @ sol - y).pow(2).sum())
                if err < best_err:
                    best, best_err = torch.zeros(a.shape[1], dtype=a.dtype), err
                    best[list(cols)] = sol
    return best


def fit_variance_terms(
    drives: Sequence[tuple[SmartLocData, int, int]],
    columns: Sequence[int],
    *,
    groups: int = 2,
    elevation_mask_deg: float = 15.0,
    floor: float = 0.02,
) -> Tensor:
    """Coefficients ``[groups, len(columns)]`` of the receiver's variances on the features
    ``[1, 1/sin^2(el), 10^(-C/N0/10), pr_var]`` (the ``columns`` chosen), fitted by non-negative
    least squares per constellation on the epochs ``[first, stop)`` of each drive.  A coefficient
    the fit sets to 0 gets ``floor`` x the mean variance's share instead, so it is positive and can
    train (log scale)."""
    parts = [_features(d, a, b, elevation_mask_deg) for d, a, b in drives]
    feats = torch.cat([p[0] for p in parts])[:, list(columns)]
    var, grp = torch.cat([p[1] for p in parts]), torch.cat([p[2] for p in parts])
    out = torch.zeros(groups, len(columns), dtype=torch.float64)
    for g in range(groups):
        sel = grp == g
        if not bool(sel.any()):
            sel = torch.ones_like(grp, dtype=torch.bool)
        coef = _nnls(feats[sel], var[sel])
        share = floor * float(var[sel].mean()) / feats[sel].mean(0).clamp_min(1e-300)
        out[g] = torch.where(coef > share, coef, share)
    return out


_COLUMNS = {"elev_cn0": [0, 1, 2], "receiver_elev_cn0": [3, 1, 2]}


def start_coefficients(variant: str, drives: Sequence[tuple[SmartLocData, int, int]], *, elevation_mask_deg: float = 15.0) -> Tensor:
    """The starting coefficients ``[2, 3]`` of a side-information variant (:func:`fit_variance_terms`);
    an empty tensor for ``receiver`` and ``scale``."""
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    if variant not in _COLUMNS:
        return torch.zeros(0, dtype=torch.float64)
    return fit_variance_terms(drives, _COLUMNS[variant], groups=2, elevation_mask_deg=elevation_mask_deg)


def noise_model(variant: str, coefficients: Tensor, *, bound: float = 10.0) -> nn.Module | None:
    """The variance module of ``variant`` (``None`` for ``receiver``: the model's ``noise_from_data``)
    started from ``coefficients`` (:func:`start_coefficients`), parameters bounded to
    ``[start / bound, start * bound]``."""
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    if variant == "receiver":
        return None
    groups, kw = 2, {"bound": bound, "group_key": "constellation"}
    if variant == "scale":
        return ScaledVariance(scale=1.0, key="pr_var", groups=1, bound=bound)
    c = coefficients
    if variant == "elev_cn0":
        return SumVariance(
            ElevationVariance(a=c[:, 0].tolist(), b=c[:, 1].tolist(), groups=groups, **kw),
            CN0Variance(a=None, b=c[:, 2].tolist(), groups=groups, **kw),
        )
    return SumVariance(
        ScaledVariance(scale=c[:, 0].tolist(), key="pr_var", groups=groups, **kw),
        ElevationVariance(a=None, b=c[:, 1].tolist(), groups=groups, **kw),
        CN0Variance(a=None, b=c[:, 2].tolist(), groups=groups, **kw),
    )
