"""Kinematic motion models: constant velocity, constant acceleration, Singer and "current statistical".

Every model here moves ``axes`` independent Cartesian axes (1 to 3) and orders the state axis by
axis: ``[p_1, v_1, p_2, v_2, ...]`` for constant velocity and ``[p_1, v_1, a_1, p_2, v_2, a_2,
...]`` for the acceleration models (the layout of p000's ``[s_e, v_e, a_e, s_n, v_n, a_n]``).

The sample interval is the constructor's ``dt`` unless the per-step inputs carry one:
``u = {"dt": Tensor [..., 1]}`` (broadcast against the state's leading dimensions), which lets
irregularly sampled data through the same module.

The Singer pieces (:func:`singer_transition`, :func:`singer_process_noise`) are pure
differentiable functions of ``alpha = 1/tau``.  Their closed forms cancel catastrophically for
small ``alpha * T`` (``q_11`` divides an ``O(x^5)`` difference by ``x^5``), so each entry is
written as ``T^p * f(x)`` with ``x = alpha * T`` and ``f`` evaluated by a 32-term Taylor series for
``x <= 2`` and by the closed form above; the measured relative error of every entry is below
``1e-6`` in float32 and ``1e-14`` in float64 for ``x`` from ``0`` to ``1e3`` (see
``tests/test_motion.py``).  Both branches get clamped copies of ``x`` so that the branch that
``torch.where`` discards never produces an ``inf`` whose zero gradient would turn into ``nan``.
"""

from __future__ import annotations

import math
from fractions import Fraction

import torch
from torch import Tensor

from ..params import Interval, Positive, register_constrained
from .base import Controls, DynamicsModel

__all__ = [
    "ConstantAcceleration",
    "ConstantVelocity",
    "CurrentStatistical",
    "Singer",
    "axis_block_diag",
    "constant_acceleration_noise",
    "constant_acceleration_transition",
    "constant_velocity_discrete_noise",
    "constant_velocity_noise",
    "current_statistical_variance",
    "singer_noise_from_variance",
    "singer_process_noise",
    "singer_transition",
]

# Each Singer entry is (poly(x) + c1 e^{-x} + c2 x e^{-x} + c3 e^{-2x}) / (d x^p); the first p
# Taylor coefficients of the numerator vanish, which is what the series below exploits.
# Spec: (polynomial coefficients, c1, c2, c3, p, d).
_SPECS: dict[str, tuple[tuple[Fraction, ...], int, int, int, int, int]] = {
    "q11": ((Fraction(1), Fraction(2), Fraction(-2), Fraction(2, 3)), 0, -4, -1, 5, 2),
    "q12": ((Fraction(1), Fraction(-2), Fraction(1)), -2, 2, 1, 4, 2),
    "q13": ((Fraction(1),), 0, -2, -1, 3, 2),
    "q22": ((Fraction(-3), Fraction(2)), 4, 0, -1, 3, 2),
    "q23": ((Fraction(1),), -2, 0, 1, 2, 2),
    "q33": ((Fraction(1),), 0, 0, -1, 1, 2),
    "phi13": ((Fraction(-1), Fraction(1)), 1, 0, 0, 2, 1),
    "phi23": ((Fraction(1),), -1, 0, 0, 1, 1),
}
_SERIES_TERMS = 32
_SWITCH = 2.0


def _numerator_coefficient(spec: tuple[tuple[Fraction, ...], int, int, int, int, int], n: int) -> Fraction:
    poly, c1, c2, c3, _, _ = spec
    c = poly[n] if n < len(poly) else Fraction(0)
    c += c1 * Fraction((-1) ** n, math.factorial(n))
    if n >= 1:
        c += c2 * Fraction((-1) ** (n - 1), math.factorial(n - 1))
    return c + c3 * Fraction((-2) ** n, math.factorial(n))


def _series(spec: tuple[tuple[Fraction, ...], int, int, int, int, int]) -> tuple[float, ...]:
    p, d = spec[4], spec[5]
    if any(_numerator_coefficient(spec, n) != 0 for n in range(p)):  # pragma: no cover - table error
        raise AssertionError("Singer series table is inconsistent")
    return tuple(float(_numerator_coefficient(spec, n) / d) for n in range(p, p + _SERIES_TERMS))


_NAMES = tuple(_SPECS)
_INDEX = {name: i for i, name in enumerate(_NAMES)}
# Series coefficients [terms, entries] and closed-form numerators over the basis
# [1, x, x^2, x^3, e^{-x}, x e^{-x}, e^{-2x}] as [7, entries]: all entries are evaluated at once
# (two small matrix products; a Horner loop per entry dominated the filters' run time).
_SERIES = torch.tensor([_series(_SPECS[k]) for k in _NAMES], dtype=torch.float64).T.contiguous()
_CLOSED = torch.tensor(
    [[float(poly[i]) if i < len(poly) else 0.0 for i in range(4)] + [c1, c2, c3] for poly, c1, c2, c3, _, _ in _SPECS.values()],
    dtype=torch.float64,
).T.contiguous()
_POWER = torch.tensor([spec[4] for spec in _SPECS.values()], dtype=torch.float64)
_DENOM = torch.tensor([spec[5] for spec in _SPECS.values()], dtype=torch.float64)


def _scaled_entries(x: Tensor) -> Tensor:
    """All dimensionless Singer entries ``f(x) [..., 8]`` (order of ``_SPECS``), ``x = alpha T >= 0``."""
    dd = {"dtype": x.dtype, "device": x.device}
    xs = x.clamp(max=_SWITCH)[..., None]
    series = (xs ** torch.arange(_SERIES_TERMS, **dd)) @ _SERIES.to(**dd)
    xc = x.clamp(min=_SWITCH)[..., None]
    e1 = torch.exp(-xc)
    basis = torch.cat([torch.ones_like(xc), xc, xc * xc, xc * xc * xc, e1, xc * e1, e1 * e1], -1)
    closed = (basis @ _CLOSED.to(**dd)) / (_DENOM.to(**dd) * xc ** _POWER.to(**dd))
    return torch.where(x[..., None] <= _SWITCH, series, closed)


def _as_tensor(value: Tensor | float, like: Tensor) -> Tensor:
    if isinstance(value, Tensor):
        return value.to(dtype=like.dtype, device=like.device)
    return torch.tensor(float(value), dtype=like.dtype, device=like.device)


def _matrix(rows: list[list[Tensor]]) -> Tensor:
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def singer_transition(alpha: Tensor, dt: Tensor | float) -> Tensor:
    """Singer transition matrix per axis ``[..., 3, 3]`` for state ``[p, v, a]``.

    .. math::
        \\Phi = \\begin{bmatrix} 1 & T & (\\alpha T - 1 + e^{-\\alpha T})/\\alpha^2 \\\\
        0 & 1 & (1 - e^{-\\alpha T})/\\alpha \\\\ 0 & 0 & e^{-\\alpha T}\\end{bmatrix}

    (p000 eq. (18) with the ``1/alpha^2`` fix).  ``alpha = 1/tau >= 0`` any shape, ``dt`` a float
    or a tensor broadcastable with ``alpha``; ``alpha = 0`` gives the constant-acceleration matrix.
    """
    dt = _as_tensor(dt, alpha)
    alpha, dt = torch.broadcast_tensors(alpha, dt)
    x = alpha * dt
    f = _scaled_entries(x)
    one, zero = torch.ones_like(x), torch.zeros_like(x)
    return _matrix(
        [
            [one, dt, dt * dt * f[..., _INDEX["phi13"]]],
            [zero, one, dt * f[..., _INDEX["phi23"]]],
            [zero, zero, torch.exp(-x)],
        ]
    )


def singer_process_noise(alpha: Tensor, dt: Tensor | float, sigma: Tensor | float) -> Tensor:
    """Exact discrete Singer process noise per axis ``[..., 3, 3]``.

    ``Q = 2 alpha sigma^2 \\int_0^T g(s) g(s)^T ds`` with ``g(s) = Phi(s) [0, 0, 1]^T``: the
    acceleration is the Gauss-Markov process ``da = -alpha a dt + dW`` whose stationary variance
    is ``sigma^2`` (the driving spectral density is ``2 alpha sigma^2``).  Entry ``(i, j)`` is
    ``2 sigma^2 T^(p_ij - 1) x f_ij(x)``, ``x = alpha T`` (module docstring for the numerics).
    ``alpha``, ``dt`` and ``sigma`` broadcast together; as ``alpha -> 0`` with ``sigma`` fixed
    the noise vanishes, as in the continuous model.
    """
    sigma = _as_tensor(sigma, alpha)
    return singer_noise_from_variance(alpha, dt, sigma * sigma)


def singer_noise_from_variance(alpha: Tensor, dt: Tensor | float, variance: Tensor | float) -> Tensor:
    """:func:`singer_process_noise` parametrised by ``variance = sigma^2`` (no square root, so
    the gradient stays finite where the adaptive variance of :class:`CurrentStatistical` is 0)."""
    dt = _as_tensor(dt, alpha)
    variance = _as_tensor(variance, alpha)
    alpha, dt, variance = torch.broadcast_tensors(alpha, dt, variance)
    x = alpha * dt
    f = _scaled_entries(x)[..., :6] * (2.0 * variance * x)[..., None]
    t = torch.stack([dt**4, dt**3, dt**2, dt**2, dt, torch.ones_like(dt)], -1)
    q11, q12, q13, q22, q23, q33 = (f * t).unbind(-1)
    return _matrix([[q11, q12, q13], [q12, q22, q23], [q13, q23, q33]])


def constant_acceleration_transition(dt: Tensor) -> Tensor:
    """``[[1, T, T^2/2], [0, 1, T], [0, 0, 1]]`` ``[..., 3, 3]`` (the ``alpha -> 0`` Singer limit)."""
    one, zero = torch.ones_like(dt), torch.zeros_like(dt)
    return _matrix([[one, dt, dt * dt / 2], [zero, one, dt], [zero, zero, one]])


def constant_velocity_noise(dt: Tensor) -> Tensor:
    """White-noise-acceleration covariance per unit spectral density ``[..., 2, 2]``:
    ``[[T^3/3, T^2/2], [T^2/2, T]]``."""
    return _matrix([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])


def constant_velocity_discrete_noise(dt: Tensor) -> Tensor:
    """Piecewise-constant white acceleration per unit variance ``[..., 2, 2]``: ``g g^T`` with
    ``g = [T^2/2, T]`` (filterpy's ``Q_discrete_white_noise``), a rank-one covariance."""
    g = torch.stack([dt * dt / 2, dt], -1)
    return g[..., :, None] * g[..., None, :]


def constant_acceleration_noise(dt: Tensor) -> Tensor:
    """White-jerk covariance per unit spectral density ``[..., 3, 3]``: p000's ``Q_axis`` =
    ``[[T^5/20, T^4/8, T^3/6], [T^4/8, T^3/3, T^2/2], [T^3/6, T^2/2, T]]``."""
    return _matrix(
        [
            [dt**5 / 20, dt**4 / 8, dt**3 / 6],
            [dt**4 / 8, dt**3 / 3, dt**2 / 2],
            [dt**3 / 6, dt**2 / 2, dt],
        ]
    )


def axis_block_diag(blocks: Tensor) -> Tensor:
    """``[..., A, k, k]`` per-axis blocks -> block-diagonal ``[..., A k, A k]``."""
    a, k = blocks.shape[-3], blocks.shape[-1]
    eye = torch.eye(a, dtype=blocks.dtype, device=blocks.device)
    full = blocks[..., :, :, None, :] * eye[:, None, :, None]  # [..., A, k, A, k]
    return full.reshape(*blocks.shape[:-3], a * k, a * k)


def current_statistical_variance(a_hat: Tensor, a_max: Tensor, sigma_min: float = 0.0) -> Tensor:
    """Zhou Hongren's adaptive acceleration variance (p000 ref. [3]).

    ``sigma^2 = (4 - pi)/pi (a_max - |a_hat|)^2 + sigma_min^2``, which is ``(a_max - a_hat)^2``
    for ``a_hat > 0`` and ``(a_max + a_hat)^2`` for ``a_hat < 0``; ``|a_hat|`` is clamped to
    ``a_max`` so that an estimate beyond the bound does not raise the variance again.
    """
    gap = (a_max - a_hat.abs()).clamp_min(0.0)
    return (4.0 - math.pi) / math.pi * gap * gap + sigma_min**2


class _Kinematic(DynamicsModel):
    """Shared plumbing: axes, per-axis order, the sample interval and block assembly."""

    order: int

    def __init__(self, *, axes: int, dt: float, dtype: torch.dtype | None) -> None:
        super().__init__()
        if axes not in (1, 2, 3):
            raise ValueError(f"axes must be 1, 2 or 3, got {axes}")
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be finite and positive, got {dt}")
        self.axes = axes
        self.state_dim = axes * self.order
        self.register_buffer("dt", torch.tensor(float(dt), dtype=dtype or torch.get_default_dtype()))

    def _per_axis(self, value: Tensor | float, name: str, dtype: torch.dtype | None) -> Tensor:
        t = torch.as_tensor(value, dtype=dtype or torch.get_default_dtype()).detach().clone()
        if t.ndim == 0:
            t = t.expand(self.axes).clone()
        if t.shape != (self.axes,):
            raise ValueError(f"{name} must be a scalar or have shape [{self.axes}], got {tuple(t.shape)}")
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"{name} must be finite, got {t.tolist()}")
        return t

    def validate_controls(self, controls: Controls) -> None:
        """``controls["dt"]`` (when given) must be finite and non-negative in every batch element.

        A zero interval is allowed: no time passes, the transition is the identity and the
        process noise zero (two samples at one instant, or a trajectory whose first step starts
        at its given belief)."""
        if not isinstance(controls, dict) or "dt" not in controls:
            return
        dt = controls["dt"]
        bad = ~(torch.isfinite(dt) & (dt >= 0))
        if bool(bad.any()):
            b, t = (int(i) for i in bad.nonzero()[0][:2])
            rows = sorted({int(i) for i in bad.nonzero()[:, 0]})[:10]
            raise ValueError(
                f"controls['dt'] must be finite and non-negative, got {float(dt[b, t].flatten()[0])} at [b, t] = [{b}, {t}] "
                f"(batch elements {rows})"
            )

    def step_dt(self, u: Controls) -> Tensor:
        """Sample interval: ``u["dt"][..., 0]`` when given, else the constructor's ``dt`` (0-d)."""
        if isinstance(u, dict) and "dt" in u:
            return u["dt"][..., 0]
        return self.dt

    def transition_blocks(self, u: Controls) -> Tensor:  # pragma: no cover - abstract
        """Per-axis transition blocks ``[..., axes, k, k]``."""
        raise NotImplementedError

    def matrix(self, u: Controls = None) -> Tensor:
        return axis_block_diag(self.transition_blocks(u))

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        return (self.matrix(u) @ x[..., None])[..., 0]

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        f = self.matrix(u)
        return f.expand(*torch.broadcast_shapes(x.shape[:-1], f.shape[:-2]), *f.shape[-2:])

    @property
    def Q(self) -> Tensor:  # noqa: N802 - field notation
        """Process noise at the constructor's ``dt`` (state-independent part)."""
        return self.process_noise(torch.zeros(self.state_dim, dtype=self.dt.dtype, device=self.dt.device))


class ConstantVelocity(_Kinematic):
    """Constant velocity (white-noise acceleration) per axis, state ``[p, v]`` per axis.

    ``x_k = blockdiag([[1, T], [0, 1]]) x_{k-1} + w``,
    ``Q = blockdiag(q_i [[T^3/3, T^2/2], [T^2/2, T]])`` (continuous white acceleration), or with
    ``noise="discrete"`` ``Q = blockdiag(q_i g g^T)``, ``g = [T^2/2, T]`` (an acceleration
    constant over each interval, variance ``q_i``): a rank-deficient ``Q`` whose intensity is
    learned while its structure stays exact.

    Args:
        axes: 1 to 3.
        dt: sample interval (s) unless ``u["dt"]`` is given.
        q: acceleration spectral density per axis (m^2/s^3; ``noise="discrete"``: acceleration
            variance, m^2/s^4), scalar or ``[axes]``; learnable (``Positive``).
        noise: ``"continuous"`` or ``"discrete"``.
    """

    order = 2

    def __init__(
        self, *, axes: int = 1, dt: float = 1.0, q: Tensor | float = 1.0, noise: str = "continuous", dtype: torch.dtype | None = None
    ) -> None:
        if noise not in ("continuous", "discrete"):
            raise ValueError(f"noise must be 'continuous' or 'discrete', got {noise!r}")
        super().__init__(axes=axes, dt=dt, dtype=dtype)
        self.noise = noise
        register_constrained(self, "q", self._per_axis(q, "q", dtype), Positive())

    def transition_blocks(self, u: Controls) -> Tensor:
        dt = self.step_dt(u)
        one, zero = torch.ones_like(dt), torch.zeros_like(dt)
        block = _matrix([[one, dt], [zero, one]])
        return block[..., None, :, :].expand(*block.shape[:-2], self.axes, 2, 2)

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        dt = self.step_dt(u)
        unit = constant_velocity_noise(dt) if self.noise == "continuous" else constant_velocity_discrete_noise(dt)
        return axis_block_diag(self.q[:, None, None] * unit[..., None, :, :])


class ConstantAcceleration(_Kinematic):
    """Constant acceleration (white-noise jerk) per axis, state ``[p, v, a]`` per axis.

    ``Phi = [[1, T, T^2/2], [0, 1, T], [0, 0, 1]]``, ``Q = q_i Q_axis(T)`` with p000's
    ``Q_axis`` (:func:`constant_acceleration_noise`).  p000's simplified model is this class with
    ``q_i = 2 sigma_i^2`` (:meth:`paper`).

    Args:
        axes: 1 to 3.
        dt: sample interval (s) unless ``u["dt"]`` is given.
        q: jerk spectral density per axis (m^2/s^5), scalar or ``[axes]``; learnable (``Positive``).
    """

    order = 3

    def __init__(self, *, axes: int = 1, dt: float = 1.0, q: Tensor | float = 1.0, dtype: torch.dtype | None = None) -> None:
        super().__init__(axes=axes, dt=dt, dtype=dtype)
        register_constrained(self, "q", self._per_axis(q, "q", dtype), Positive())

    @classmethod
    def paper(
        cls, *, axes: int = 2, dt: float = 0.1, sigma_a: Tensor | float = 1.0, dtype: torch.dtype | None = None
    ) -> ConstantAcceleration:
        """p000 eq. (19): CA transition with ``Q = diag(2 sigma_e^2 Q_e, 2 sigma_n^2 Q_n)``."""
        sigma = torch.as_tensor(sigma_a, dtype=dtype or torch.get_default_dtype())
        return cls(axes=axes, dt=dt, q=2.0 * sigma * sigma, dtype=dtype)

    def transition_blocks(self, u: Controls) -> Tensor:
        block = constant_acceleration_transition(self.step_dt(u))
        return block[..., None, :, :].expand(*block.shape[:-2], self.axes, 3, 3)

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        dt = self.step_dt(u)
        return axis_block_diag(self.q[:, None, None] * constant_acceleration_noise(dt)[..., None, :, :])


class _ManoeuvreTime(_Kinematic):
    """Adds the learnable manoeuvre time constant ``tau`` (``alpha = 1/tau``)."""

    order = 3

    def __init__(self, *, axes: int, dt: float, tau: Tensor | float, dtype: torch.dtype | None) -> None:
        super().__init__(axes=axes, dt=dt, dtype=dtype)
        register_constrained(self, "tau", self._per_axis(tau, "tau", dtype), Interval(0.1, 1e4))

    def _alpha_dt(self, u: Controls) -> tuple[Tensor, Tensor]:
        return 1.0 / self.tau, self.step_dt(u)[..., None]  # dt [..., 1] against the axes dimension


class Singer(_ManoeuvreTime):
    """Singer manoeuvre model per axis, state ``[p, v, a]`` per axis (p000 eq. (18)).

    The acceleration is a zero-mean Gauss-Markov process with time constant ``tau`` and
    stationary standard deviation ``sigma_a``: ``Phi = singer_transition(1/tau, T)``,
    ``Q = singer_process_noise(1/tau, T, sigma_a)`` per axis.

    Args:
        axes: 1 to 3.
        dt: sample interval (s) unless ``u["dt"]`` is given.
        tau: manoeuvre time constant per axis (s), scalar or ``[axes]``; learnable
            (``Interval(0.1, 1e4)``, log scale).
        sigma_a: acceleration standard deviation per axis (m/s^2); learnable (``Positive``).
    """

    def __init__(
        self,
        *,
        axes: int = 1,
        dt: float = 1.0,
        tau: Tensor | float = 20.0,
        sigma_a: Tensor | float = 1.0,
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__(axes=axes, dt=dt, tau=tau, dtype=dtype)
        register_constrained(self, "sigma_a", self._per_axis(sigma_a, "sigma_a", dtype), Positive())

    def transition_blocks(self, u: Controls) -> Tensor:
        return singer_transition(*self._alpha_dt(u))

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        alpha, dt = self._alpha_dt(u)
        return axis_block_diag(singer_process_noise(alpha, dt, self.sigma_a))


class CurrentStatistical(_ManoeuvreTime):
    """Zhou Hongren's "current statistical" model (p000 ref. [3]), state ``[p, v, a]`` per axis.

    The acceleration relaxes towards its *current mean* ``a_bar`` instead of zero:
    ``da = -alpha (a - a_bar) dt + dW``.  With ``a_bar`` held over a step this gives
    ``x_k = Phi(alpha, T) x_{k-1} + U(alpha, T) a_bar`` with
    ``U = [T^2/2 - Phi_13, T - Phi_23, 1 - e^{-alpha T}]`` (the constant-acceleration column
    minus the Singer column), and ``Q = singer_process_noise(alpha, T, sigma(a_bar))`` with the
    adaptive ``sigma^2 = (4 - pi)/pi (a_max -/+ a_bar)^2`` (:func:`current_statistical_variance`).

    What is implemented: ``a_bar`` is the current acceleration estimate.  By default it is the
    acceleration of the state being propagated, so ``f(x) = Phi x + U a = Phi_CA x`` is the
    constant-acceleration transition exactly (the form p000 eq. (19) uses), its Jacobian is
    ``Phi_CA``, and ``alpha`` enters through ``Q`` only.  Zhou's recursion treats ``a_bar`` as a
    known input and propagates the covariance with ``Phi`` instead; pass ``u["a_mean"]
    [..., axes]`` to get exactly that (``f = Phi x + U a_bar``, Jacobian ``Phi``).  The variance
    uses the mean the filter passes to :meth:`process_noise` (the posterior before predicting).

    Args:
        axes, dt: as :class:`Singer`.
        tau: manoeuvre time constant per axis (s); learnable (``Interval(0.1, 1e4)``).
        a_max: largest expected acceleration magnitude per axis (m/s^2); learnable (``Positive``).
        sigma_min: fixed floor (m/s^2) added in quadrature so that ``Q`` stays positive definite
            when ``|a_bar|`` reaches ``a_max``.
        noise: ``"singer"`` (exact Singer Q) or ``"paper"`` (p000's simplification
            ``Q = 2 sigma^2 Q_axis(T)``, dropping ``alpha``).
    """

    def __init__(
        self,
        *,
        axes: int = 1,
        dt: float = 1.0,
        tau: Tensor | float = 20.0,
        a_max: Tensor | float = 3.0,
        sigma_min: float = 0.01,
        noise: str = "singer",
        dtype: torch.dtype | None = None,
    ) -> None:
        if noise not in ("singer", "paper"):
            raise ValueError(f"noise must be 'singer' or 'paper', got {noise!r}")
        super().__init__(axes=axes, dt=dt, tau=tau, dtype=dtype)
        register_constrained(self, "a_max", self._per_axis(a_max, "a_max", dtype), Positive())
        self.sigma_min = float(sigma_min)
        self.noise = noise

    @staticmethod
    def _mean_input(u: Controls) -> Tensor | None:
        return u["a_mean"] if isinstance(u, dict) and "a_mean" in u else None

    def transition_blocks(self, u: Controls) -> Tensor:
        if self._mean_input(u) is not None:
            return singer_transition(*self._alpha_dt(u))
        block = constant_acceleration_transition(self.step_dt(u))
        return block[..., None, :, :].expand(*block.shape[:-2], self.axes, 3, 3)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        a_bar = self._mean_input(u)
        out = (self.matrix(u) @ x[..., None])[..., 0]
        if a_bar is None:
            return out
        alpha, dt = self._alpha_dt(u)
        phi = singer_transition(alpha, dt)
        gain = (constant_acceleration_transition(dt) - phi)[..., :, 2]  # U per axis [..., axes, 3]
        drive = (gain * a_bar[..., :, None]).flatten(-2)
        return out + drive

    def acceleration_variance(self, x: Tensor, u: Controls = None) -> Tensor:
        """Adaptive ``sigma^2 [..., axes]`` from ``a_bar`` (state's accelerations or ``u["a_mean"]``)."""
        a_bar = self._mean_input(u)
        if a_bar is None:
            a_bar = x[..., 2::3]
        return current_statistical_variance(a_bar, self.a_max, self.sigma_min)

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        var = self.acceleration_variance(x, u)
        alpha, dt = self._alpha_dt(u)
        if self.noise == "paper":
            blocks = 2.0 * var[..., None, None] * constant_acceleration_noise(dt[..., 0])[..., None, :, :]
        else:
            blocks = singer_noise_from_variance(alpha, dt, var)
        return axis_block_diag(blocks)
