"""Heteroscedastic measurement noise: variances from per-step side information, and a learnable
robust gate.

Real sensors report how good each measurement is: a GNSS receiver gives every pseudorange its
satellite's elevation and carrier-to-noise density C/N0 (and often its own variance estimate).
The standard practice is a *noise model* ``sigma^2 = g(side information; theta)`` with a few
parameters ``theta``, not one constant.  The variance modules here map the per-step inputs
``u`` (a dict of ``[..., K]`` tensors, one entry per measurement component) to variances
``[..., K]``; every parameter is positive and bounded (a log-scale
:class:`~difffilter.params.Interval` around its initial value), so it trains by
back-propagation like any other constrained parameter and cannot run away:

* :class:`ElevationVariance` - ``a_g + b_g / sin^2(el)``;
* :class:`CN0Variance` - ``a_g + b_g 10^(-C/N0 / 10)``;
* :class:`MonotoneVariance` - piecewise linear in one input through knot values that are
  monotone by construction (a ratio ``>= 1`` between neighbouring knots);
* :class:`ScaledVariance` - ``s_g u[key]`` (a reported variance times a learnable scale: the
  "single-scale R");
* :class:`SumVariance` - the sum of several of these.

The index ``g`` is a component's group (a GNSS constellation): ``groups=G`` gives each group
its own parameters, read from ``u[group_key]`` (integers ``0..G-1``, ``[..., K]``).

:class:`RobustGate` inflates the variance of a component whose residual is too large for it
(hard or smooth; threshold, floor and softness learnable), and
:class:`HeteroscedasticMeasurement` gives ANY measurement model the noise
``R(x, u) = diag(sigma^2(u))`` (optionally gated)::

    # a position fix whose noise grows with the receiver's reported HDOP, per fix type
    variance = ScaledVariance(key="hdop_sq", scale=4.0, groups=2, group_key="fix_type")
    gps = HeteroscedasticMeasurement(linear_measurement(H, R0), variance=variance,
                                     gate=RobustGate(threshold=3.0, softness=0.2), observed_key="z")
    model = StateSpaceModel(dynamics, gps)
    filt(z, m0, P0, controls={"hdop_sq": hdop**2, "fix_type": kind, "z": z})   # each [B, T, K]

(:class:`~difffilter.models.navigation.pseudorange.PseudorangeMeasurement` takes a variance
module as ``noise_model=`` and its gate is a :class:`RobustGate`.)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from .._util import control
from ..params import Interval, Positive, register_constrained, remove_constrained
from .base import Controls, MeasurementModel

__all__ = [
    "CN0Variance",
    "ElevationVariance",
    "HeteroscedasticMeasurement",
    "MonotoneVariance",
    "RobustGate",
    "ScaledVariance",
    "SideInformationVariance",
    "SumVariance",
]

_LOG_REJECT = math.log(1e6)  # the reject gate's variance factor 1e6, as a logarithm
_MIN_SOFTNESS = 1e-3


def _positive_vector(value: float | Sequence[float], groups: int, name: str) -> Tensor:
    v = torch.as_tensor(value, dtype=torch.float64).reshape(-1)
    if v.numel() == 1:
        v = v.expand(groups).clone()
    if v.numel() != groups:
        raise ValueError(f"{name} must be a number or {groups} numbers (one per group), got {v.tolist()}")
    if not bool((v > 0).all() and torch.isfinite(v).all()):
        raise ValueError(f"{name} must be positive and finite, got {v.tolist()}")
    return v


class SideInformationVariance(nn.Module):
    """Base of the variance models: ``forward(u, like) -> [..., K]`` variances.

    Subclasses register their parameters with :meth:`_register` (positive, bounded to
    ``[min / bound, max * bound]`` of their initial values on a log scale) and read them per
    component with :meth:`_per_group`.

    Args:
        groups: number of parameter groups ``G`` (1: one set of parameters for all components).
        group_key: key of ``u`` holding each component's group ``[..., K]`` (needed for ``G > 1``).
        bound: ratio ``>= 1`` bounding every parameter around its initial value (``None``:
            positive only, ``floor + softplus(raw)``; bounded parameters train in log scale).
    """

    def __init__(self, *, groups: int = 1, group_key: str = "constellation", bound: float | None = 1e3) -> None:
        super().__init__()
        if int(groups) < 1:
            raise ValueError(f"groups must be >= 1, got {groups}")
        if bound is not None and not float(bound) >= 1.0:
            raise ValueError(f"bound must be None or >= 1, got {bound}")
        self.groups, self.group_key = int(groups), str(group_key)
        self.bound = None if bound is None else float(bound)

    def _register(self, name: str, value: float | Sequence[float], dtype: torch.dtype) -> None:
        v = _positive_vector(value, self.groups, name)
        if self.bound is None or self.bound == 1.0:
            constraint: nn.Module = Positive(1e-12)
        else:
            constraint = Interval(float(v.min()) / self.bound, float(v.max()) * self.bound)
        register_constrained(self, name, v.to(dtype), constraint)

    def _per_group(self, param: Tensor, u: Controls, like: Tensor) -> Tensor:
        """``param [G]`` for every component: ``[..., K]`` (or a scalar when ``G = 1``)."""
        param = param.to(like.dtype)
        if self.groups == 1:
            return param[0]
        idx = control(u, self.group_key).to(torch.long).clamp(0, self.groups - 1)
        return param[idx]

    def forward(self, u: Controls, like: Tensor) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError


class ElevationVariance(SideInformationVariance):
    """``sigma^2 = a_g + b_g / sin^2(el)`` from the elevation ``u[key]`` (degrees, or radians
    with ``degrees=False``), clamped below at ``min_elevation_deg`` so that empty slots (elevation
    0) stay finite.  ``a``, ``b`` in the measurement's squared units; ``a=None`` drops the
    constant (for a sum with another model that has one)."""

    def __init__(
        self,
        *,
        a: float | Sequence[float] | None = 4.0,
        b: float | Sequence[float] = 4.0,
        key: str = "elevation",
        degrees: bool = True,
        min_elevation_deg: float = 1.0,
        dtype: torch.dtype = torch.float64,
        **kwargs: object,
    ) -> None:
        super().__init__(**kwargs)  # type: ignore[arg-type]
        self.key, self.degrees = str(key), bool(degrees)
        self.min_elevation = math.radians(float(min_elevation_deg))
        self.has_constant = a is not None
        if a is not None:
            self._register("a", a, dtype)
        self._register("b", b, dtype)

    def forward(self, u: Controls, like: Tensor) -> Tensor:
        el = control(u, self.key).to(like.dtype)
        el = torch.deg2rad(el) if self.degrees else el
        s = torch.sin(el.clamp_min(self.min_elevation))
        out = self._per_group(self.b, u, like) / (s * s)
        return out + self._per_group(self.a, u, like) if self.has_constant else out


class CN0Variance(SideInformationVariance):
    """``sigma^2 = a_g + b_g 10^(-C/N0 / 10)`` from the carrier-to-noise density ``u[key]``
    (dB-Hz); ``10^(-C/N0/10)`` is the inverse of C/N0 in Hz, so ``b`` is a variance times Hz
    (``b = 1e5`` m^2 Hz gives 10 m^2 at 40 dB-Hz); ``a=None`` drops the constant."""

    def __init__(
        self,
        *,
        a: float | Sequence[float] | None = 4.0,
        b: float | Sequence[float] = 1e5,
        key: str = "cn0",
        dtype: torch.dtype = torch.float64,
        **kwargs: object,
    ) -> None:
        super().__init__(**kwargs)  # type: ignore[arg-type]
        self.key = str(key)
        self.has_constant = a is not None
        if a is not None:
            self._register("a", a, dtype)
        self._register("b", b, dtype)

    def forward(self, u: Controls, like: Tensor) -> Tensor:
        cn0 = control(u, self.key).to(like.dtype)
        out = self._per_group(self.b, u, like) * torch.pow(10.0, -cn0 / 10.0)
        return out + self._per_group(self.a, u, like) if self.has_constant else out


class MonotoneVariance(SideInformationVariance):
    """Piecewise-linear variance in one input ``u[key]`` through ``J`` knots, monotone by
    construction: ``sigma^2(k_0) = v_g`` and ``sigma^2(k_{j+1}) = sigma^2(k_j) r_{g,j}`` with
    ratios ``r >= 1`` (``decreasing=True``: ``sigma^2(k_{j+1}) = sigma^2(k_j) / r``); constant
    outside the knots.  Learnable: ``first`` (``v``, ``[G]``) and ``ratios`` (``[G, J - 1]``,
    ``1 + softplus(raw)``).

    Args:
        knots: increasing input values ``[J]`` (e.g. elevations 10, 30, 60, 90 degrees).
        values: initial variances at the knots (``[J]`` or ``[G, J]``), monotone in the
            declared direction.
        key: the input (``"elevation"``, ``"cn0"``, ...).
        decreasing: whether the variance falls as the input grows (elevation, C/N0).
    """

    def __init__(
        self,
        *,
        knots: Sequence[float],
        values: Sequence[float] | Sequence[Sequence[float]],
        key: str,
        decreasing: bool = True,
        dtype: torch.dtype = torch.float64,
        **kwargs: object,
    ) -> None:
        super().__init__(**kwargs)  # type: ignore[arg-type]
        k = torch.as_tensor(knots, dtype=torch.float64).reshape(-1)
        if k.numel() < 2 or not bool((k[1:] > k[:-1]).all()):
            raise ValueError(f"knots must be >= 2 increasing numbers, got {k.tolist()}")
        v = torch.as_tensor(values, dtype=torch.float64)
        v = v.expand(self.groups, k.numel()) if v.ndim == 1 else v
        if tuple(v.shape) != (self.groups, k.numel()) or not bool((v > 0).all()):
            raise ValueError(f"values must be {k.numel()} positive numbers (or [{self.groups}, {k.numel()}]), got {v.tolist()}")
        steps = v[:, 1:] / v[:, :-1]
        ratios = 1.0 / steps if decreasing else steps
        if not bool((ratios >= 1.0).all()):
            raise ValueError(f"values must be {'non-increasing' if decreasing else 'non-decreasing'} along the knots, got {v.tolist()}")
        self.key, self.decreasing = str(key), bool(decreasing)
        self.register_buffer("knots", k.to(dtype))
        self._register("first", v[:, 0].tolist(), dtype)
        # ratio - 1 >= 0; a tiny floor keeps equal neighbours representable (softplus(-inf) = 0)
        register_constrained(self, "ratios", (ratios - 1.0).clamp_min(1e-9).to(dtype), Positive(0.0))

    def knot_values(self) -> Tensor:
        """Variances at the knots ``[G, J]``."""
        log_r = torch.log1p(self.ratios)
        log_r = -log_r if self.decreasing else log_r
        logs = torch.cat([torch.zeros_like(log_r[:, :1]), torch.cumsum(log_r, -1)], -1)
        return self.first[:, None] * torch.exp(logs)

    def forward(self, u: Controls, like: Tensor) -> Tensor:
        x = control(u, self.key).to(like.dtype)
        knots = self.knots.to(like.dtype)
        vals = self.knot_values().to(like.dtype)  # [G, J]
        xc = x.clamp(knots[0], knots[-1])
        j = torch.searchsorted(knots, xc.detach().contiguous(), right=True).clamp(1, knots.numel() - 1)
        k0, k1 = knots[j - 1], knots[j]
        w = (xc - k0) / (k1 - k0)
        if self.groups == 1:
            v0, v1 = vals[0][j - 1], vals[0][j]
        else:
            g = control(u, self.group_key).to(torch.long).clamp(0, self.groups - 1)
            v0, v1 = vals[g, j - 1], vals[g, j]
        return v0 + w * (v1 - v0)


class ScaledVariance(SideInformationVariance):
    """``sigma^2 = s_g u[key]``: a variance the sensor reports (``"pr_var"``), times a learnable
    scale per group (``groups=1``: the single-scale ``R``)."""

    def __init__(
        self, *, scale: float | Sequence[float] = 1.0, key: str = "pr_var", dtype: torch.dtype = torch.float64, **kwargs: object
    ) -> None:
        super().__init__(**kwargs)  # type: ignore[arg-type]
        self.key = str(key)
        self._register("scale", scale, dtype)

    def forward(self, u: Controls, like: Tensor) -> Tensor:
        return self._per_group(self.scale, u, like) * control(u, self.key).to(like.dtype)


class SumVariance(nn.Module):
    """``sigma^2 = sum_i term_i(u)`` (e.g. an elevation model plus a C/N0 model); the terms'
    parameters are named ``terms.<i>.<name>``."""

    def __init__(self, *terms: nn.Module) -> None:
        super().__init__()
        if not terms:
            raise ValueError("SumVariance needs at least one term")
        self.terms = nn.ModuleList(terms)

    def forward(self, u: Controls, like: Tensor) -> Tensor:
        out = self.terms[0](u, like)
        for term in self.terms[1:]:
            out = out + term(u, like)
        return out


class RobustGate(nn.Module):
    """Outlier gate by noise inflation: ``R_jj <- f_j R_jj`` from the normalised residual
    ``n_j = |z_j - h_j(x)| / sqrt(R_jj + floor^2)`` (``x``: the prior mean the filter passes in;
    ``floor`` allows for the prior uncertainty, which ``R`` alone ignores).

    * ``kind="huber"``: ``f = max(1, n / threshold)`` (the Huber M-estimator's weight as a
      variance factor);
    * ``kind="reject"``, hard (``softness=None``): ``f = 1e6`` when ``n > threshold`` (a chi-square
      gate with one degree of freedom that keeps shapes fixed);
    * ``kind="reject"``, smooth (``softness = t > 0``): ``f = 1e6 ** sigmoid((n - threshold) / t)``,
      which tends to the hard gate as ``t -> 0`` and is differentiable in ``n``, ``threshold``,
      ``floor`` and ``t``.

    The smooth gate registers ``gate_softness`` (``0.001 + softplus(raw)``); with
    ``learnable=True`` it also registers ``gate_threshold`` (``0.5 + softplus(raw)``) and
    ``gate_floor`` (``softplus(raw)``, metres), all selectable by name.  A hard gate keeps plain
    numbers (no parameters: its switch has no useful gradient).
    """

    def __init__(
        self,
        *,
        kind: str = "reject",
        threshold: float = 3.0,
        floor: float = 0.0,
        softness: float | None = None,
        learnable: bool = False,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        if kind not in ("huber", "reject"):
            raise ValueError(f"kind must be 'huber' or 'reject', got {kind!r}")
        if not float(threshold) > 0.5 or not float(floor) >= 0.0:
            raise ValueError(f"threshold must exceed 0.5 and floor be >= 0, got {threshold}, {floor}")
        self.kind, self.soft = kind, False
        self._threshold, self._floor = float(threshold), float(floor)
        self.learnable = False
        self.set_softness(softness, dtype=dtype)
        if learnable:
            self.set_learnable(True)

    @property
    def threshold(self) -> Tensor | float:
        return self.gate_threshold if self.learnable else self._threshold

    @property
    def floor(self) -> Tensor | float:
        return self.gate_floor if self.learnable else self._floor

    def set_softness(self, value: float | None, *, dtype: torch.dtype | None = None) -> None:
        """Hard (``None`` or ``0``) or smooth (``value > 0.001``) reject gate, its parameter in
        ``dtype`` (default: the current softness's, else float64).  Switching back to the hard
        gate keeps the current threshold and floor as plain numbers."""
        if value is None or float(value) == 0.0:
            if self.learnable:
                self.set_learnable(False)
            if self.soft:
                remove_constrained(self, "gate_softness")
            self.soft = False
            return
        if self.kind != "reject":
            raise ValueError(f"a smooth gate needs kind='reject', got {self.kind!r}")
        if not float(value) > _MIN_SOFTNESS:
            raise ValueError(f"gate_softness must be None, 0 or > {_MIN_SOFTNESS}, got {value!r}")
        dtype = dtype or (self.gate_softness.dtype if self.soft else torch.float64)
        register_constrained(self, "gate_softness", torch.tensor(float(value), dtype=dtype), Positive(_MIN_SOFTNESS))
        self.soft = True

    def set_learnable(self, flag: bool) -> None:
        """Register (``True``, smooth gate only) or remove threshold and floor as parameters."""
        if flag == self.learnable:
            return
        if flag:
            if not self.soft:
                raise ValueError("a learnable threshold and floor need the smooth gate (set_softness(t > 0) first)")
            dtype = self.gate_softness.dtype
            register_constrained(self, "gate_threshold", torch.tensor(self._threshold, dtype=dtype), Positive(0.5))
            register_constrained(self, "gate_floor", torch.tensor(max(self._floor, 1e-6), dtype=dtype), Positive(0.0))
        else:
            self._threshold, self._floor = float(self.gate_threshold.detach()), float(self.gate_floor.detach())
            remove_constrained(self, "gate_threshold")
            remove_constrained(self, "gate_floor")
        self.learnable = bool(flag)

    def normalised(self, residual: Tensor, var: Tensor) -> Tensor:
        """``n = |residual| / sqrt(var + floor^2)``."""
        return residual.abs() / torch.sqrt(var + self.floor**2)

    def factor(self, residual: Tensor, var: Tensor) -> Tensor:
        """Variance factors ``f [..., K]`` for residuals and variances ``[..., K]``."""
        n = self.normalised(residual, var)
        if self.kind == "huber":
            return torch.clamp(n / self.threshold, min=1.0)
        if self.soft:
            return torch.exp(_LOG_REJECT * torch.sigmoid((n - self.threshold) / self.gate_softness))  # 1e6 ** sigmoid(...)
        return torch.where(n > self.threshold, torch.full_like(n, 1e6), torch.ones_like(n))

    def inflate(self, r: Tensor, residual: Tensor, extra: int = 0) -> Tensor:
        """``R [..., m, m]`` with its first ``K`` components (``K = residual.shape[-1]``) inflated
        (``D R D``, ``D = diag(sqrt(f))``); ``extra`` further components are left alone."""
        k = residual.shape[-1]
        var = torch.diagonal(r, dim1=-2, dim2=-1)[..., :k]
        f = self.factor(residual, var)
        if r.shape[-1] > k:
            f = torch.cat([f, torch.ones(*f.shape[:-1], r.shape[-1] - k, dtype=f.dtype, device=f.device)], -1)
        d = torch.sqrt(f)
        return r * d[..., :, None] * d[..., None, :]


class HeteroscedasticMeasurement(MeasurementModel):
    """Any measurement model with the noise ``R(x, u) = diag(variance(u))``, optionally gated.

    ``h``, its Jacobian and ``residual`` are ``base``'s; ``variance`` is a variance module of this
    file (``(u, like) -> [..., m]``); ``gate`` (a :class:`RobustGate`) inflates components whose
    residual against the observed values ``u[observed_key] [..., m]`` is too large.  The
    parameters are ``base.*``, ``variance.*`` and ``gate.*`` (``learn: [a, b, gate_softness]``).
    Every filter takes it: ``R`` is evaluated where the filter evaluates the noise (the prior
    mean; :class:`~difffilter.filters.IteratedEKF`: each iterate, so its gate follows the
    iterate), and ``matrix()`` is ``base``'s, so a linear ``base`` also runs in
    :class:`~difffilter.filters.KalmanFilter`.
    """

    def __init__(self, base: MeasurementModel, *, variance: nn.Module, gate: RobustGate | None = None, observed_key: str = "z_obs") -> None:
        super().__init__()
        self.base, self.variance, self.gate = base, variance, gate
        self.observed_key = str(observed_key)
        self.measurement_dim = int(base.measurement_dim)
        self.angular = tuple(base.angular)  # residual is base's

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        return self.base(x, u)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor | None:
        return self.base.jacobian(x, u)

    def matrix(self, u: Controls = None) -> Tensor | None:
        # h is base's whatever R does: a gated linear measurement still runs in KalmanFilter.
        return self.base.matrix(u)

    def residual(self, z: Tensor, z_ref: Tensor) -> Tensor:
        return self.base.residual(z, z_ref)

    def measurement_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        r = torch.diag_embed(self.variance(u, x))
        if self.gate is None:
            return r
        res = self.base.residual(control(u, self.observed_key).to(x.dtype), self.base(x, u))
        return self.gate.inflate(r, res)
