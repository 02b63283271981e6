"""Several sensors with their own dimension, noise and rate as one measurement model, and the
helper that puts per-sensor measurement streams on the filter's step grid.

:class:`MultiSensorMeasurement` stacks named :class:`~difffilter.models.base.MeasurementModel` s
(``z = [z_imu; z_gnss]``, ``R = blockdiag(R_imu, R_gnss)``); at each step only the sensors that
reported are used: the step's mask is False on the others' components, and the filters' masked
update is exactly the update with the reporting sensors alone (jointly; wrap the filter in
:class:`~difffilter.filters.SequentialUpdate` for one sensor after the other).
:func:`align_streams` builds those measurements and that mask from each sensor's own samples
and timestamps, so user code never pads by hand::

    sensors = MultiSensorMeasurement({"imu": accelerometer, "gnss": gnss}, rates={"imu": 100.0, "gnss": 10.0})
    grid = align_streams({"imu": (t_imu, a_imu), "gnss": (t_gnss, p_gnss)}, step_times=t_imu, sensors=sensors)
    result = KalmanFilter(StateSpaceModel(dynamics, sensors))(grid.measurements, m0, P0, mask=grid.mask)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from ..linalg import block_diag
from .base import Controls, MeasurementModel

__all__ = ["MultiSensorMeasurement", "SensorGrid", "align_streams", "event_times"]

Stream = tuple[Tensor, Tensor]


class MultiSensorMeasurement(MeasurementModel):
    """Named sensors stacked into one measurement ``z = [z_1; ...; z_S]`` (in the given order).

    ``h``, Jacobians, ``matrix`` (when every sensor is linear, so the Kalman filter applies),
    residuals (each sensor's own, e.g. angle wrapping) and the block-diagonal noise come from the
    sensors; each sensor keeps its parameters (``sensors.gnss.R``: ``learn: [R]`` matches every
    sensor's ``R``).  Non-additive sensors are supported (the noise vector is split by the
    sensors' noise dimensions).

    Args:
        sensors: ``{name: MeasurementModel}``.
        rates: optional ``{name: Hz}`` reporting rates (``None`` / missing: irregular), used by
            :meth:`rate_mask` and documented with the model.
    """

    def __init__(self, sensors: Mapping[str, MeasurementModel], *, rates: Mapping[str, float | None] | None = None) -> None:
        super().__init__()
        if not sensors or not all(isinstance(s, MeasurementModel) for s in sensors.values()):
            raise TypeError("sensors must be a non-empty mapping {name: MeasurementModel}")
        unknown = set(rates or {}) - set(sensors)
        if unknown:
            raise ValueError(f"rates name unknown sensors {sorted(unknown)}; sensors are {list(sensors)}")
        for name, rate in (rates or {}).items():
            if rate is not None and not (isinstance(rate, int | float) and rate > 0):
                raise ValueError(f"rates[{name!r}] must be a positive number of Hz or None, got {rate!r}")
        self.sensors = nn.ModuleDict(dict(sensors))
        self.rates = {name: (None if (rates or {}).get(name) is None else float(rates[name])) for name in sensors}  # type: ignore[index]
        self.slices: dict[str, slice] = {}
        start = 0
        for name, s in sensors.items():
            self.slices[name] = slice(start, start + int(s.measurement_dim))
            start += int(s.measurement_dim)
        self.measurement_dim = start
        self.additive_noise = all(s.additive_noise for s in sensors.values())
        # the sensors' angles, at their places in the stacked measurement (residual wraps them)
        self.angular = tuple(self.slices[name].start + int(i) for name, s in sensors.items() for i in s.angular)

    @property
    def names(self) -> list[str]:
        return list(self.sensors.keys())

    def _parts(self, z: Tensor) -> list[Tensor]:
        return [z[..., sl] for sl in self.slices.values()]

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        return torch.cat([s(x, u) for s in self.sensors.values()], -1)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor | None:
        jacs = [s.jacobian(x, u) for s in self.sensors.values()]
        if any(j is None for j in jacs):
            return None
        return torch.cat([j.expand(*x.shape[:-1], *j.shape[-2:]) for j in jacs], -2)  # type: ignore[union-attr]

    def matrix(self, u: Controls = None) -> Tensor | None:
        mats = [s.matrix(u) for s in self.sensors.values()]
        if any(m is None for m in mats):
            return None
        lead = torch.broadcast_shapes(*[m.shape[:-2] for m in mats])  # type: ignore[union-attr]
        return torch.cat([m.expand(*lead, *m.shape[-2:]) for m in mats], -2)  # type: ignore[union-attr]

    def measurement_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        return block_diag(*[s.measurement_noise(x, u) for s in self.sensors.values()])

    @property
    def R(self) -> Tensor:  # noqa: N802 - field notation
        """Block-diagonal noise of all sensors (set each sensor's own ``R``)."""
        return block_diag(*[s.R for s in self.sensors.values()])

    def residual(self, z: Tensor, z_ref: Tensor) -> Tensor:
        return torch.cat([s.residual(a, b) for s, a, b in zip(self.sensors.values(), self._parts(z), self._parts(z_ref), strict=True)], -1)

    def _noise_dims(self) -> list[int]:
        return [int(s.R.shape[-1]) for s in self.sensors.values()]

    def with_noise(self, x: Tensor, v: Tensor, u: Controls = None) -> Tensor:
        parts = torch.split(v, self._noise_dims(), -1)
        return torch.cat([s.with_noise(x, p, u) for s, p in zip(self.sensors.values(), parts, strict=True)], -1)

    def noise_jacobian(self, x: Tensor, u: Controls = None) -> Tensor | None:
        blocks = []
        for s in self.sensors.values():
            if s.additive_noise:
                blocks.append(torch.eye(int(s.measurement_dim), dtype=x.dtype, device=x.device).expand(*x.shape[:-1], -1, -1))
                continue
            jac = s.noise_jacobian(x, u)
            if jac is None:
                return None
            blocks.append(jac.expand(*x.shape[:-1], *jac.shape[-2:]))
        rows = [
            torch.cat([b if i == j else b.new_zeros(*b.shape[:-1], o.shape[-1]) for j, o in enumerate(blocks)], -1)
            for i, b in enumerate(blocks)
        ]
        return torch.cat(rows, -2)

    def component_groups(self) -> list[list[int]]:
        """Measurement components of each sensor (what :class:`SequentialUpdate` updates in turn)."""
        return [list(range(sl.start, sl.stop)) for sl in self.slices.values()]

    def expand_mask(self, reported: Mapping[str, Tensor]) -> Tensor:
        """Component mask ``[B, T, m]`` from per-sensor step masks ``{name: [B, T] bool}`` (a
        missing name: that sensor never reports)."""
        unknown = set(reported) - set(self.slices)
        if unknown:
            raise ValueError(f"unknown sensors {sorted(unknown)}; sensors are {self.names}")
        ref = next(iter(reported.values()))
        out = torch.zeros(*ref.shape, self.measurement_dim, dtype=torch.bool, device=ref.device)
        for name, m in reported.items():
            out[..., self.slices[name]] = m.to(torch.bool)[..., None]
        return out

    def rate_mask(self, steps: int, step_rate: float, *, batch_size: int = 1) -> Tensor:
        """``[B, T, m]`` mask of a uniform grid at ``step_rate`` Hz whose step ``t`` is at time
        ``(t + 1) / step_rate``: a sensor at rate ``r`` reports at the steps whose time is a
        multiple of ``1 / r`` (every step for sensors without a rate)."""
        times = torch.arange(1, steps + 1, dtype=torch.float64) / step_rate
        reported = {}
        for name, rate in self.rates.items():
            if rate is None:
                reported[name] = torch.ones(steps, dtype=torch.bool)
            else:
                phase = times * rate
                reported[name] = (phase - phase.round()).abs() < 1e-6 * torch.clamp(phase, min=1.0)
        return self.expand_mask({k: v.expand(batch_size, steps) for k, v in reported.items()})


@dataclass
class SensorGrid:
    """Per-sensor streams on the filter's step grid.

    Attributes:
        measurements: ``[B, T, m]`` stacked sensor values (NaN where a sensor did not report).
        mask: ``[B, T, m]`` True where the component's sensor reported at that step.
        times: ``[B, T]`` step times.
        dt: ``[B, T]`` time since the previous step (the first: since ``start``), for models that
            take the step length as a control (``controls={"dt": grid.dt[..., None]}``).
        slices: ``{name: slice}`` of each sensor's components.
        dropped: ``{name: count}`` of samples that fell outside every step's tolerance.
        superseded: ``{name: count}`` of samples replaced by a later sample of the same sensor
            in the same step (``on_conflict="last"``).
    """

    measurements: Tensor
    mask: Tensor
    times: Tensor
    dt: Tensor
    slices: dict[str, slice]
    dropped: dict[str, int] = field(default_factory=dict)
    superseded: dict[str, int] = field(default_factory=dict)


def event_times(streams: Mapping[str, Stream]) -> Tensor:
    """Sorted distinct sample times ``[T]`` of all streams with shared (1-D) times: the grid of an
    event-driven filter that steps at every measurement."""
    times = []
    for name, (t, _) in streams.items():
        if t.ndim != 1:
            raise ValueError(f"event_times needs 1-D sample times; stream {name!r} has shape {tuple(t.shape)}")
        times.append(t[torch.isfinite(t)].to(torch.float64))
    return torch.unique(torch.cat(times), sorted=True)


def _check_stream(name: str, times: Tensor, values: Tensor, bsz: int) -> tuple[Tensor, Tensor]:
    if not isinstance(times, Tensor) or not isinstance(values, Tensor):
        raise TypeError(f"stream {name!r} must be a pair (times [K] or [B, K], values [K, m] or [B, K, m]) of tensors")
    if times.ndim == 1:
        times = times.expand(bsz, -1)
    if values.ndim == 2:
        values = values.expand(bsz, *values.shape)
    if times.ndim != 2 or values.ndim != 3 or times.shape != values.shape[:2] or times.shape[0] != bsz:
        raise ValueError(
            f"stream {name!r}: times must be [K] or [B, K] and values [K, m] or [B, K, m] with the same K and B = {bsz}, "
            f"got {tuple(times.shape)} and {tuple(values.shape)}"
        )
    return times.to(torch.float64), values


def align_streams(
    streams: Mapping[str, Stream],
    step_times: Tensor,
    *,
    sensors: MultiSensorMeasurement | Sequence[str] | None = None,
    tolerance: float | None = None,
    start: float | Tensor | None = None,
    on_conflict: str = "error",
) -> SensorGrid:
    """Put per-sensor measurement streams on the filter's step grid.

    Each sample ``(tau, z)`` of sensor ``s`` goes to the step whose time is nearest to ``tau`` if
    it lies within ``tolerance``; steps without a sample of ``s`` get ``mask`` False on ``s``'s
    components.  Streams may differ per trajectory (times ``[B, K]``, NaN times = padding of
    shorter streams) and need not be sorted.

    Args:
        streams: ``{name: (times [K] | [B, K], values [K, m_s] | [B, K, m_s])}``; names missing
            here never report.
        step_times: ``[T]`` or ``[B, T]`` increasing times of the filter's steps (step ``t``
            updates with the measurements taken at ``step_times[t]``).
        sensors: the :class:`MultiSensorMeasurement` (or the sensor names) fixing the component
            order; default: the order of ``streams``.
        tolerance: largest ``|tau - step time|`` accepted (default: half the smallest step).
        start: time of the initial belief, for ``dt`` of the first step (default: one step before
            the first, ``2 t_0 - t_1``).
        on_conflict: two samples of one sensor in one step: ``"error"`` (default) or ``"last"``
            (the latest sample is used; the others are counted in ``superseded``).

    Returns:
        :class:`SensorGrid` (measurements, mask, times, dt, slices, dropped/superseded counts).
    """
    if on_conflict not in ("error", "last"):
        raise ValueError(f"on_conflict must be 'error' or 'last', got {on_conflict!r}")
    if not isinstance(step_times, Tensor) or step_times.ndim not in (1, 2) or step_times.shape[-1] < 1:
        raise ValueError("step_times must be a tensor [T] or [B, T] with T >= 1")
    names = list(sensors.names if isinstance(sensors, MultiSensorMeasurement) else (sensors or list(streams)))
    unknown = set(streams) - set(names)
    if unknown:
        raise ValueError(f"streams name unknown sensors {sorted(unknown)}; sensors are {names}")
    grid = step_times.to(torch.float64)
    if not bool((grid[..., 1:] > grid[..., :-1]).all()):
        raise ValueError("step_times must be strictly increasing")
    bsz = max([grid.shape[0] if grid.ndim == 2 else 1] + [t.shape[0] for t, _ in streams.values() if t.ndim == 2])
    bsz = max([bsz] + [v.shape[0] for _, v in streams.values() if v.ndim == 3])
    grid = grid.expand(bsz, -1)
    steps = grid.shape[1]
    gaps = grid[:, 1:] - grid[:, :-1]
    tol = float(tolerance) if tolerance is not None else (0.5 * float(gaps.min()) if steps > 1 else math.inf)
    dims = {}
    for name in names:
        if isinstance(sensors, MultiSensorMeasurement):
            dims[name] = int(sensors.sensors[name].measurement_dim)
        elif name in streams:
            dims[name] = int(streams[name][1].shape[-1])
        else:
            raise ValueError(f"sensor {name!r} has no stream, so its dimension is unknown: pass sensors=MultiSensorMeasurement")
    dtype = next((v.dtype for _, v in streams.values() if v.is_floating_point()), torch.float64)
    parts, masks, slices, dropped, superseded = [], [], {}, {}, {}
    offset = 0
    for name in names:
        m = dims[name]
        slices[name] = slice(offset, offset + m)
        offset += m
        vals = torch.full((bsz, steps, m), math.nan, dtype=dtype, device=grid.device)
        hit = torch.zeros(bsz, steps, dtype=torch.bool, device=grid.device)
        if name in streams:
            times, values = _check_stream(name, *streams[name], bsz)
            if values.shape[-1] != m:
                raise ValueError(f"stream {name!r} has {values.shape[-1]} components, the sensor {m}")
            idx = torch.searchsorted(grid.contiguous(), torch.nan_to_num(times, nan=-math.inf).contiguous()).clamp(1, max(steps - 1, 1))
            lo = (idx - 1).clamp(min=0)
            near = torch.where((times - grid.gather(1, lo)).abs() <= (times - grid.gather(1, idx)).abs(), lo, idx)
            ok = torch.isfinite(times) & ((times - grid.gather(1, near)).abs() <= tol)
            dropped[name] = int((torch.isfinite(times) & ~ok).sum())
            # latest sample last, so that "last" keeps it when scattering in order
            order = torch.argsort(torch.where(ok, times, -math.inf), dim=1, stable=True)
            near, ok, values = near.gather(1, order), ok.gather(1, order), values.gather(1, order[..., None].expand_as(values))
            b_idx, k_idx = ok.nonzero(as_tuple=True)
            t_idx = near[b_idx, k_idx]
            counts = torch.zeros(bsz, steps, dtype=torch.long, device=grid.device).index_put_(
                (b_idx, t_idx), torch.ones_like(t_idx), accumulate=True
            )
            extra = int((counts - 1).clamp(min=0).sum())
            if extra and on_conflict == "error":
                raise ValueError(
                    f"stream {name!r}: {extra} samples share a step with another sample of the same sensor; "
                    "use a finer step grid or on_conflict='last'"
                )
            superseded[name] = extra
            # nonzero() lists each trajectory's samples in time order: keep each step's last one
            key = b_idx * steps + t_idx
            pos = torch.arange(key.numel(), device=key.device)
            last = torch.zeros(bsz * steps, dtype=torch.long, device=key.device).scatter_reduce(0, key, pos, "amax", include_self=False)
            keep = last[key] == pos
            vals[b_idx[keep], t_idx[keep]] = values[b_idx[keep], k_idx[keep]].to(dtype)
            hit = counts > 0
        parts.append(vals)
        masks.append(hit[..., None].expand(bsz, steps, m))
    if start is None:
        first = grid[:, :1] - (gaps[:, :1] if steps > 1 else torch.ones_like(grid[:, :1]))
    else:
        first = torch.as_tensor(start, dtype=torch.float64, device=grid.device).reshape(-1, 1).expand(bsz, 1)
    dt = torch.diff(grid, dim=1, prepend=first)
    return SensorGrid(torch.cat(parts, -1), torch.cat(masks, -1), grid, dt.to(dtype), slices, dropped, superseded)
