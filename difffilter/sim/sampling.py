"""In-family trajectory sampler: draw truth and measurements from any :class:`StateSpaceModel`.

For a model ``(f, h, Q, R)`` and an initial belief ``N(m_0, P_0)``

.. math::
    x_0 \\sim N(m_0, P_0), \\quad
    x_k = f(x_{k-1}, u_k) + w_k,\\ w_k \\sim N(0, Q(x_{k-1}, u_k)), \\quad
    z_k = h(x_k, u_k) + v_k,\\ v_k \\sim N(0, R(x_k, u_k)),

(``f(x_{k-1}, w_k, u_k)`` / ``h(x_k, v_k, u_k)`` for models that declare non-additive noise),

for ``k = 1..T``.  ``truth[:, t]`` is ``x_{t+1}`` and ``measurements[:, t]`` is ``z_{t+1}``, so
``(m_0, P_0)`` is exactly the belief *before* the first measurement that every difffilter filter
expects, and a filter run with the sampling model's own parameters is the optimal (oracle)
filter for linear-Gaussian models.  State-dependent ``Q``/``R`` (``process_noise`` /
``measurement_noise`` overrides) are honoured.

Randomness comes from one ``torch.Generator`` seeded by ``seed``; everything is drawn and
propagated in float64 and cast to the requested dtype at the end, so the float32 data set is the
float64 one rounded, and a seed gives the same trajectories on every machine.

Such data is "in-family": the filter's model class contains the truth, which is what parameter
recovery tests and oracle comparisons need.  Paper scenarios with scripted manoeuvres live in
the per-paper simulators of :mod:`experiments.papers`.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor
from torch.nn.utils import parametrize

from .._util import as_dtype, generator
from ..filters.base import slice_controls
from ..linalg import safe_cholesky
from ..models.base import Controls, StateSpaceModel
from ..models.layout import model_defaults
from ..params import constrained_values
from ..selection import assign_parameters
from .trajectories import TrajectorySet, cast_controls

__all__ = ["ModelSimulator", "SampledTrajectories", "sample_trajectories", "simulate"]


def _noise_factor(cov: Tensor, batch: int, dim: int) -> Tensor:
    cov = cov.expand(batch, dim, dim) if cov.ndim == 2 else cov
    return safe_cholesky(cov).factor


@dataclass(kw_only=True)
class SampledTrajectories(TrajectorySet):
    """Trajectories drawn from a model (batch-first, ``T`` steps): a
    :class:`~difffilter.sim.TrajectorySet` with ``truth [B, T, n]`` (``x_1..x_T``), ``mask [B, T]``
    (or ``None``), ``initial_mean [B, n]`` (``m_0``) and ``initial_cov [n, n]`` (``P_0``), plus:

    Attributes:
        initial_state: ``[B, n]`` the drawn ``x_0``.
        true_params: constrained parameter values of the sampling model, ``{dotted name: value}``
            (e.g. ``{"dynamics.Q": ..., "measurement.R": ...}``), for an oracle filter.
        dt: sampling period (s) if known.
        model: the sampling model (float64 copy); see :meth:`make_model`.
    """

    initial_state: Tensor
    true_params: dict[str, Tensor] = field(default_factory=dict)
    dt: float | None = None
    model: StateSpaceModel | None = None

    def make_model(self) -> StateSpaceModel:
        """A fresh copy of the sampling model in this data's dtype (the oracle model)."""
        if self.model is None:
            raise ValueError("these trajectories carry no model")
        return copy.deepcopy(self.model).to(self.measurements.dtype)


@torch.no_grad()
def sample_trajectories(
    model: StateSpaceModel,
    *,
    batch_size: int,
    num_steps: int,
    initial_mean: Tensor | Sequence[float],
    initial_cov: Tensor | Sequence[float] | Sequence[Sequence[float]],
    seed: int | torch.Generator = 0,
    dtype: torch.dtype | str | None = torch.float64,
    controls: Controls = None,
    missing_prob: float = 0.0,
    dt: float | None = None,
) -> SampledTrajectories:
    """Draw ``batch_size`` trajectories of ``num_steps`` steps from ``model``.

    Args:
        model: any state-space model (its parameters are read, never changed).
        batch_size, num_steps: ``B`` and ``T``.
        initial_mean: ``[n]`` or ``[B, n]`` prior mean ``m_0``.
        initial_cov: ``[n, n]`` prior covariance ``P_0`` (``x_0 ~ N(m_0, P_0)``), or its
            diagonal ``[n]``.
        seed: integer seed or a ``torch.Generator``.
        dtype: dtype of the returned tensors (sampling itself runs in float64).
        controls: per-step inputs ``[B, T, ...]`` (tensor or dict) passed to ``f`` and ``h``.
        missing_prob: probability that a step's measurement is missing (``mask`` False, value
            NaN), drawn independently per step.
        dt: sampling period to record in the result.

    Returns:
        :class:`SampledTrajectories`.
    """
    if batch_size < 1 or num_steps < 1:
        raise ValueError(f"batch_size and num_steps must be >= 1, got {batch_size}, {num_steps}")
    if not 0.0 <= missing_prob < 1.0:
        raise ValueError(f"missing_prob must lie in [0, 1), got {missing_prob}")
    out_dtype = as_dtype(dtype)
    f64 = torch.float64
    gen = generator(seed)
    sim = copy.deepcopy(model).to(f64)
    n = sim.state_dim
    mean0 = torch.as_tensor(initial_mean, dtype=f64)
    cov0 = torch.as_tensor(initial_cov, dtype=f64)
    if cov0.ndim == 1:
        cov0 = torch.diag(cov0)
    if mean0.shape not in ((n,), (batch_size, n)):
        raise ValueError(f"initial_mean must have shape [{n}] or [B, {n}] = [{batch_size}, {n}], got {tuple(mean0.shape)}")
    if cov0.shape != (n, n):
        raise ValueError(f"initial_cov must have shape [{n}, {n}], got {tuple(cov0.shape)}")
    mean0 = mean0.expand(batch_size, n)
    u_all = cast_controls(controls, f64)

    chol0 = safe_cholesky(cov0).factor
    x = mean0 + (chol0 @ torch.randn(batch_size, n, 1, generator=gen, dtype=f64))[..., 0]
    x0 = x
    states, meas = [], []
    # cached(): constrained values are computed once for the whole run, as inside a filter.
    with parametrize.cached():
        for t in range(num_steps):
            u = slice_controls(u_all, t)
            # with_noise is f(x, u) + w for additive models and f(x, w, u) otherwise (noise of Q's size)
            q = sim.dynamics.process_noise(x, u)
            lq = _noise_factor(q, batch_size, q.shape[-1])
            x = sim.dynamics.with_noise(x, (lq @ torch.randn(batch_size, q.shape[-1], 1, generator=gen, dtype=f64))[..., 0], u)
            r = sim.measurement.measurement_noise(x, u)
            lr = _noise_factor(r, batch_size, r.shape[-1])
            z = sim.measurement.with_noise(x, (lr @ torch.randn(batch_size, r.shape[-1], 1, generator=gen, dtype=f64))[..., 0], u)
            states.append(x)
            meas.append(z)
    truth = torch.stack(states, 1)
    measurements = torch.stack(meas, 1)
    mask = None
    if missing_prob > 0:
        mask = torch.rand(batch_size, num_steps, generator=gen, dtype=f64) >= missing_prob
        measurements = torch.where(mask[..., None], measurements, torch.full_like(measurements, float("nan")))
    return SampledTrajectories(
        truth=truth.to(out_dtype),
        measurements=measurements.to(out_dtype),
        mask=mask,
        controls=cast_controls(controls, out_dtype),
        initial_mean=mean0.to(out_dtype).clone(),
        initial_cov=cov0.to(out_dtype),
        initial_state=x0.to(out_dtype),
        true_params={k: v.to(out_dtype) for k, v in constrained_values(sim).items()},
        dt=dt,
        model=sim,
    )


class ModelSimulator:
    """A simulator ``(batch_size, seed, dtype) -> SampledTrajectories`` over a fixed model.

    The convention every difffilter simulator follows, so that
    :class:`~difffilter.learn.data.TrajectoryDataModule` can draw train/val/test sets from
    different seeds.  ``true_params`` sets constrained values on (a copy of) ``model`` first,
    using the name matching of :func:`difffilter.selection.assign_parameters`
    (``{"Q": ..., "R": [4.0, 4.0]}``), so one model config can serve as both the filter and the
    truth with different values.

    What the arguments leave open comes from the model's
    :class:`~difffilter.models.layout.ModelDefaults` (``model.defaults``): ``true_params=None``
    takes its ``reference`` values, ``initial_mean=None``/``initial_cov=None`` its default
    belief, ``controls=None`` its input sampler (if it has one).

    Args:
        model: the truth model.
        num_steps: trajectory length ``T``.
        initial_mean, initial_cov: prior ``N(m_0, P_0)`` (``initial_cov`` ``[n, n]`` or its
            diagonal); ``None``: the model's default belief.
        true_params: constrained values to set on the copy of ``model`` (``{}``: none;
            ``None``: the model's reference values).
        controls: ``(batch_size, num_steps, generator, dtype) -> controls`` callable or a fixed
            ``[1, T, ...]`` tensor broadcast over the batch; ``None``: the model's sampler.
        missing_prob: probability of a missing measurement step.
        dt: sampling period recorded in the result.
    """

    def __init__(
        self,
        *,
        model: StateSpaceModel,
        num_steps: int,
        initial_mean: Tensor | Sequence[float] | None = None,
        initial_cov: Tensor | Sequence[float] | Sequence[Sequence[float]] | None = None,
        true_params: Mapping[str, Any] | None = None,
        controls: Callable[..., Controls] | Tensor | None = None,
        missing_prob: float = 0.0,
        dt: float | None = None,
    ) -> None:
        defaults = model_defaults(model)
        if true_params is None and defaults is not None:
            true_params = defaults.reference
        if initial_mean is None or initial_cov is None:
            if defaults is None or defaults.initial_mean is None or defaults.initial_var is None:
                raise ValueError("initial_mean and initial_cov are required: the model has no default belief (model.defaults)")
            initial_mean = defaults.initial_mean if initial_mean is None else initial_mean
            initial_cov = defaults.initial_var if initial_cov is None else initial_cov
        if controls is None and defaults is not None:
            controls = defaults.controls
        self.model = copy.deepcopy(model).to(torch.float64)
        if true_params:
            assign_parameters(self.model, dict(true_params))
        self.num_steps = int(num_steps)
        self.initial_mean = torch.as_tensor(initial_mean, dtype=torch.float64)
        self.initial_cov = torch.as_tensor(initial_cov, dtype=torch.float64)
        self.controls = controls
        self.missing_prob = float(missing_prob)
        self.dt = dt

    def __call__(
        self,
        batch_size: int = 32,
        seed: int | torch.Generator = 0,
        dtype: torch.dtype | str | None = torch.float64,
        num_steps: int | None = None,
    ) -> SampledTrajectories:
        """Draw ``batch_size`` trajectories (``num_steps`` overrides the constructor's length)."""
        gen = generator(seed)
        steps = self.num_steps if num_steps is None else int(num_steps)
        controls: Controls
        if callable(self.controls) and not isinstance(self.controls, Tensor):
            controls = self.controls(batch_size, steps, gen, torch.float64)
        elif isinstance(self.controls, Tensor):
            fixed = self.controls[:, :steps]
            controls = fixed.expand(batch_size, *fixed.shape[1:])
        else:
            controls = None
        return sample_trajectories(
            self.model,
            batch_size=batch_size,
            num_steps=steps,
            initial_mean=self.initial_mean,
            initial_cov=self.initial_cov,
            seed=gen,
            dtype=dtype,
            controls=controls,
            missing_prob=self.missing_prob,
            dt=self.dt,
        )


def simulate(
    model: StateSpaceModel,
    *,
    num_steps: int,
    batch_size: int = 1,
    seed: int | torch.Generator = 0,
    initial_mean: Tensor | Sequence[float] | None = None,
    initial_cov: Tensor | Sequence[float] | Sequence[Sequence[float]] | None = None,
    controls: Callable[..., Controls] | Mapping[str, Tensor] | Tensor | None = None,
    missing_prob: float = 0.0,
    dtype: torch.dtype | str | None = torch.float64,
) -> SampledTrajectories:
    """Draw ``batch_size`` trajectories of ``num_steps`` steps from ``model`` as it is (its
    current parameter values; the model is not changed).

    ``initial_mean``/``initial_cov`` (the belief before the first measurement, ``x_0 ~ N(m_0,
    P_0)``; ``initial_cov`` ``[n, n]`` or its diagonal) and ``controls`` (a ``[1|B, T, ...]``
    tensor, a dict of ``[B, T, ...]`` tensors, or a ``(batch_size, num_steps, generator, dtype) ->
    controls`` sampler) default to the
    model's :class:`~difffilter.models.layout.ModelDefaults` when it has them.  The result's
    ``truth [B, T, n]``, ``measurements [B, T, m]``, ``mask``, ``controls``, ``initial_mean`` and
    ``initial_cov`` go straight into any filter::

        data = simulate(model, num_steps=100, batch_size=32, initial_mean=m0, initial_cov=P0)
        res = UKF(model)(data.measurements, data.initial_mean, data.initial_cov, mask=data.mask)

    A thin front of :class:`ModelSimulator` (what the data module calls) and
    :func:`sample_trajectories` (seeded; the same seed gives the same trajectories everywhere).
    """
    if isinstance(controls, Mapping) or (isinstance(controls, Tensor) and controls.shape[0] == batch_size and batch_size > 1):
        given = controls  # per-trajectory inputs, used as they are

        def fixed(b: int, t: int, g: torch.Generator | None, d: torch.dtype) -> Controls:
            return cast_controls(given[:, :t] if isinstance(given, Tensor) else {k: v[:, :t] for k, v in given.items()}, d)

    else:
        fixed = controls
    sim = ModelSimulator(
        model=model,
        num_steps=num_steps,
        initial_mean=initial_mean,
        initial_cov=initial_cov,
        true_params={},
        controls=fixed,
        missing_prob=missing_prob,
    )
    return sim(batch_size=batch_size, seed=seed, dtype=dtype)
