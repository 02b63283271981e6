"""The sensor-model extras the real-data protocol learns jointly with the noise (issue 28, item 4).

Configuration (the ``extras`` entry of a ``conf/realdata/smartloc*.yaml``; absent: every extra on,
started at zero)::

    extras:
      enabled: true                 # false: the model without extras (protocols v1-v3)
      lever_arm: [0.0, 0.0, 0.0]    # start (m; forward, left, up), null: not modelled
      latency: 0.0                  # start (s; receiver time offset), null: not modelled
      elevation_bias: [0.0, 0.0]    # start (m; c_g / sin(el) per constellation), null: not modelled
      prior_sd: {lever_arm: 1.0, latency: 0.1, elevation_bias: 2.0}

Every extra started at zero leaves the model's predictions exactly those of the model without it
(zero offset, zero bias), so the untrained start and the hand-tuned filter are unchanged.  The
extras are signed, so their prior is a Gaussian pull towards the start on a linear scale
(:class:`LinearDistancePrior`), not the log-distance prior of the positive parameters.
A constant per-constellation bias is not an extra: the clock-bias and ISB states absorb it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

__all__ = ["EXTRAS", "LinearDistancePrior", "extras_options", "extras_priors", "learn_patterns"]

#: The extras' parameter names (as registered on the pseudorange measurement model).
EXTRAS = ("lever_arm", "latency", "elevation_bias")
_SIZES = {"lever_arm": 3, "latency": 1}
_PRIOR_SD = {"lever_arm": 1.0, "latency": 0.1, "elevation_bias": 2.0}


class LinearDistancePrior:
    """``log p(v) = -sum ((v - v_ref) / scale)^2 / 2``: a Gaussian pull of a signed parameter
    towards ``reference`` (maximum exactly at the reference)."""

    def __init__(self, *, reference: Tensor | float, scale: float) -> None:
        if not (math.isfinite(float(scale)) and float(scale) > 0):
            raise ValueError(f"scale must be a positive number, got {scale}")
        self.reference, self.scale = torch.as_tensor(reference, dtype=torch.float64).detach().clone(), float(scale)

    def log_prob(self, value: Tensor) -> Tensor:
        return -0.5 * (((value - self.reference.to(value.dtype)) / self.scale) ** 2).sum()


def _numbers(key: str, value: Any, size: int | None) -> list[float]:
    vals = value if isinstance(value, (list, tuple)) else [value]
    if isinstance(value, bool) or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
        raise ValueError(f"extras.{key} must be {'a number' if size == 1 else 'a list of numbers'} or null, got {value!r}")
    out = [float(v) for v in vals]
    if (size is not None and len(out) != size) or not out or not all(math.isfinite(v) for v in out):
        want = f"{size} finite number(s)" if size is not None else "one finite number per constellation"
        raise ValueError(f"extras.{key} must be {want}, got {value!r}")
    return out


def extras_options(cfg: Mapping[str, Any], num_groups: int) -> dict[str, Any]:
    """``{lever_arm, latency, elevation_bias}`` start values for
    :func:`~experiments.papers.smartloc.model.make_smartloc_model` (``None``: not modelled) from
    ``cfg["extras"]`` (module docstring); all ``None`` when ``enabled`` is false.  ``ValueError``
    naming the key for a bad entry (the bounds themselves are checked by the model)."""
    raw = cfg.get("extras")
    spec = {} if raw is None else dict(raw)
    unknown = sorted(set(spec) - {"enabled", "prior_sd", *EXTRAS})
    if unknown:
        raise ValueError(f"extras has unknown keys {unknown}; expected enabled, prior_sd, {', '.join(EXTRAS)}")
    enabled = spec.get("enabled", True)
    if not isinstance(enabled, bool):
        raise ValueError(f"extras.enabled must be true or false, got {enabled!r}")
    if not enabled:
        return dict.fromkeys(EXTRAS)
    out: dict[str, Any] = {}
    for key in EXTRAS:
        value = spec.get(key, [0.0] * num_groups if key == "elevation_bias" else 0.0 if key == "latency" else [0.0] * 3)
        if value is None:
            out[key] = None
            continue
        nums = _numbers(key, value, _SIZES.get(key, num_groups))
        out[key] = nums[0] if key == "latency" else nums
    return out


def extras_priors(cfg: Mapping[str, Any], names: list[str], owners: Mapping[str, Any]) -> dict[str, LinearDistancePrior]:
    """Linear-distance priors (towards the start values) of the learned ``names`` that are extras,
    with the standard deviations ``cfg["extras"]["prior_sd"]`` (defaults 1 m, 0.1 s, 2 m)."""
    given = dict(dict(cfg.get("extras") or {}).get("prior_sd") or {})
    unknown = sorted(set(given) - set(EXTRAS))
    if unknown:
        raise ValueError(f"extras.prior_sd has unknown keys {unknown}; expected {list(EXTRAS)}")
    sd = {**_PRIOR_SD, **given}
    for key, v in sd.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(float(v)) and float(v) > 0):
            raise ValueError(f"extras.prior_sd.{key} must be a positive number, got {v!r}")
    out = {}
    for name in names:
        attr = name.rsplit(".", 1)[-1]
        if attr in EXTRAS:
            out[name] = LinearDistancePrior(reference=getattr(owners[name][0], owners[name][1]).detach(), scale=float(sd[attr]))
    return out


def learn_patterns(cfg: Mapping[str, Any]) -> list[str]:
    """``cfg["learn"]`` plus the modelled extras (lever arm, latency, elevation bias) unless
    ``extras.enabled`` is false: the extras train jointly with the noise by default."""
    spec = dict(cfg.get("extras") or {})
    if spec.get("enabled", True) is False:
        return list(cfg["learn"])
    return list(cfg["learn"]) + [k for k in EXTRAS if (k not in spec or spec[k] is not None) and k not in cfg["learn"]]
