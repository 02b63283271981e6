"""Glue between the real smartLoc drive and the learning stack (``experiment=smartloc_real``).

The drive is one real trajectory (1,372 epochs, 283 s; :mod:`difffilter.sim.smartloc`), so the
"simulator" of the data module is an adapter that cuts it into segments:
:func:`smartloc_simulator` returns, for the split that the data module asks for (recognised by
its seed, ``split_seeds``), the windows of that split's segment, e.g. training windows of 200
epochs every 50 epochs inside the first 60 % of the drive, and the last 40 % as one continuous
test trajectory.  Each window starts from :func:`~difffilter.sim.smartloc.smartloc_initial_belief`
(snapshot fix of the epoch before it), so train and test never share an epoch when their
segments do not overlap.

Also here:

* :class:`SharedPsiColoredUKF` - p001's coloured-noise UKF with ONE AR(1) coefficient for every
  satellite slot: with one slot per satellite (``slots="satellite"``) per-slot coefficients
  over-fit the few satellites of a 283 s drive;
* :class:`SnapshotWLS` - the single-epoch robust least-squares baseline as a (memoryless)
  :class:`~difffilter.filters.base.GaussianFilter`, so the experiment evaluates it like a filter;
* :func:`smartloc_synthetic_simulator` - synthetic drives on the geometry of one segment
  (:mod:`difffilter.sim.smartloc_synthetic`, error model calibrated on that segment) for the
  training splits, the real held-out segment for the test split;
* :func:`smartloc_model` - :func:`~difffilter.sim.smartloc.make_smartloc_model` for configs;
* :func:`smartloc_learner` - the learner, optionally with a smooth reject gate on the learned
  filter only (the hand-tuned row keeps the model's gate).

Data: CC BY-SA 4.0, TU Chemnitz smartLoc (Reisdorf et al., VEHICULAR 2016), see the data README.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from ..filters.base import FilterResult, GaussianFilter
from ..filters.colored import ColoredNoiseUKF
from ..filters.sigma_points import SigmaPoints
from ..models.base import Controls, StateSpaceModel
from ..params import register_constrained
from ..sim.sampling import as_dtype
from ..sim.smartloc import SmartLocData, WlsSolution, load_smartloc, make_smartloc_model, single_epoch_wls, smartloc_initial_belief
from ..sim.smartloc_synthetic import PseudorangeErrorModel, calibrate_error_model, simulate_smartloc_drives
from .data import SimulatedTrajectories
from .selection import assign_parameters

__all__ = [
    "SharedBounded",
    "SharedPsiColoredUKF",
    "SmartLocTrajectories",
    "SnapshotWLS",
    "smartloc_learner",
    "smartloc_model",
    "smartloc_simulator",
    "smartloc_synthetic_simulator",
]


@functools.lru_cache(maxsize=4)
def _drive(path: str | None, slots: str) -> SmartLocData:
    return load_smartloc(path, slots=slots)


@functools.lru_cache(maxsize=2)
def _snapshot(path: str | None) -> WlsSolution:
    # The initial beliefs use the loader's robust snapshot fixes (Cauchy, c = 1.5: 23.4 m median).
    return single_epoch_wls(_drive(path, "epoch"), robust="cauchy", threshold=1.5)


def smartloc_model(*, path: str | None = None, slots: str = "satellite", dtype: torch.dtype | str = "float64", **options: Any) -> nn.Module:
    """:func:`~difffilter.sim.smartloc.make_smartloc_model` on the (cached) drive; ``options``
    are its keywords (``robust``, ``gate``, ``gate_floor``, ``gate_gradient``, ``gate_softness``,
    ``noise_from_data``, dynamics PSDs)."""
    return make_smartloc_model(_drive(path, slots), dtype=as_dtype(dtype), **options)


def smartloc_learner(
    filter: GaussianFilter,  # noqa: A002 - the field's word
    loss: Any,
    *,
    gate_softness: float | None = None,
    start_params: Mapping[str, Any] | None = None,
    **learner_kwargs: Any,
) -> Any:
    """A :class:`~difffilter.learn.learner.FilterLearner` on ``filter`` (``run_experiment`` hands
    it a copy of the hand-tuned filter) with the pseudorange reject gate of the copy set to
    ``gate_softness`` and ``start_params`` (constrained values by name) applied.

    ``gate_softness=None`` keeps the model's gate (the learner is then exactly
    ``FilterLearner(filter, loss, ...)``); ``0``: the hard gate; ``t > 0``: the smooth gate
    ``R_jj x 1e6 ** sigmoid((n_j - gate) / t)`` in training, validation and the final evaluation
    of the learned filter, with ``t`` a parameter that ``learn: [..., gate_softness]`` may train.
    The hand-tuned row (and every baseline) keeps the model config's gate.
    """
    from .learner import FilterLearner  # Lightning is imported lazily, as in difffilter.learn

    if gate_softness is not None:
        meas = getattr(getattr(filter, "model", None), "measurement", None)
        if meas is None or not hasattr(meas, "set_gate_softness"):
            raise TypeError(f"gate_softness needs a filter whose model.measurement has a reject gate, got {type(filter).__name__}")
        meas.set_gate_softness(gate_softness)
    if start_params:
        assign_parameters(filter, dict(start_params))
    return FilterLearner(filter, loss, **learner_kwargs)


@dataclass
class SmartLocTrajectories(SimulatedTrajectories):
    """Windows of the real drive in the data module's layout.

    Attributes:
        truth: ``[B, T, 3]`` ENU reference (first reference point = origin).
        measurements: ``[B, T, K]`` reduced pseudoranges; ``mask [B, T, K]``.
        controls: ``sat_pos``, ``glonass``, ``pr_var``, ``pr_obs``, ``speed``, ``yaw_rate``, ``dt``.
        initial_mean, initial_cov: ``[B, 7]``, ``[B, 7, 7]`` (snapshot fix + reference yaw/height).
        start: ``[B]`` first epoch of each window.
        data: the loaded drive.
    """

    start: Tensor
    data: SmartLocData
    model_options: Mapping[str, Any] | None = None

    def make_model(self) -> nn.Module:
        """The loader's odometry + pseudorange model for this drive."""
        return make_smartloc_model(self.data, dtype=self.measurements.dtype, **dict(self.model_options or {}))


def _epoch(value: float, total: int) -> int:
    """A segment bound: a fraction of the drive (``0 <= value <= 1``) or an epoch index."""
    v = float(value)
    return int(round(v * total)) if 0.0 <= v <= 1.0 else int(v)


def _split_of(seed: int, split_seeds: Mapping[str, int] | None) -> str | None:
    """The split whose seed (``split_seeds``, default ``{train: 0, val: 1, test: 2}``) is ``seed``."""
    return {int(v): k for k, v in dict(split_seeds or {"train": 0, "val": 1, "test": 2}).items()}.get(int(seed))


def _segment(segments: Mapping[str, Mapping[str, Any]], name: str, total: int) -> tuple[int, int, int, dict[str, Any]]:
    """``(first, stop, length, spec)`` of segment ``name`` (bounds checked; ``length`` defaults to
    the whole segment)."""
    spec = dict(segments[name])
    first, stop = _epoch(spec.get("start", 0.0), total), _epoch(spec.get("stop", 1.0), total)
    if not 0 <= first < stop <= total:
        raise ValueError(f"segment {name!r} must satisfy 0 <= start < stop <= {total} epochs, got [{first}, {stop})")
    length = stop - first if spec.get("length") is None else int(spec["length"])
    return first, stop, length, spec


def smartloc_simulator(
    *,
    batch_size: int,
    seed: int,
    dtype: torch.dtype | str = torch.float64,
    num_steps: int | None = None,
    segments: Mapping[str, Mapping[str, Any]],
    split_seeds: Mapping[str, int] | None = None,
    elevation_mask_deg: float = 15.0,
    slots: str = "satellite",
    path: str | None = None,
    true_params: Any = None,
    initial_mean: Any = None,
    initial_cov: Any = None,
) -> SmartLocTrajectories:
    """Windows of the real drive for the split whose seed is ``seed``.

    Args:
        batch_size: the largest number of windows to return (the first ones in time).
        seed: the data module's seed of the split; ``split_seeds`` (``${data.seeds}``, default
            ``{train: 0, val: 1, test: 2}``) names the split.
        num_steps: cut every window to its first ``num_steps`` epochs (smoke runs).
        segments: ``{split: {start, stop, length, stride}}``; ``start``/``stop`` bound the
            segment (fractions of the drive in ``[0, 1]`` or epoch indices), ``length`` and
            ``stride`` (epochs) cut it into windows (``length: null``: the whole segment as one
            trajectory).
        elevation_mask_deg: satellites below are masked out (the loader's 15 deg).
        slots: ``"satellite"`` (one slot per satellite: what coloured-noise models need) or
            ``"epoch"``.
        path: data folder (default: the loader's).
        true_params, initial_mean, initial_cov: ignored (the in-family scenario's keys, which
            the default experiment writes into whichever scenario is chosen).
    """
    split = _split_of(seed, split_seeds)
    if split is None:
        raise ValueError(f"seed {seed} names no split of split_seeds {dict(split_seeds or {})}")
    if split not in segments:
        raise ValueError(f"no segment for split {split!r}; segments has {sorted(segments)}")
    data = _drive(path, slots)
    first, stop, length, spec = _segment(segments, split, data.num_epochs)
    stride = length if spec.get("stride") is None else int(spec["stride"])
    starts = list(range(first, stop - length + 1, stride))[: int(batch_size)]
    if not starts:
        raise ValueError(f"segment {split!r} [{first}, {stop}) holds no window of {length} epochs")
    steps = length if num_steps is None else min(length, int(num_steps))
    dt = as_dtype(dtype)
    full = data.batch(dt, elevation_mask_deg=elevation_mask_deg)

    def cut(t: Tensor) -> Tensor:
        return torch.cat([t[:, s : s + steps] for s in starts], 0)

    start = torch.tensor(starts, dtype=torch.long)
    mean0, cov0 = smartloc_initial_belief(data, start, wls=_snapshot(path), dtype=dt)
    return SmartLocTrajectories(
        truth=cut(full.truth),
        measurements=cut(full.measurements),
        mask=cut(full.mask),
        controls={k: cut(v) for k, v in full.controls.items()},
        initial_mean=mean0,
        initial_cov=cov0,
        start=start,
        data=data,
    )


@functools.lru_cache(maxsize=8)
def _calibrated(path: str | None, slots: str, first: int, stop: int, elevation_mask_deg: float) -> PseudorangeErrorModel:
    return calibrate_error_model(_drive(path, slots), first, stop, elevation_mask_deg=elevation_mask_deg)


def smartloc_synthetic_simulator(
    *,
    batch_size: int,
    seed: int,
    dtype: torch.dtype | str = torch.float64,
    num_steps: int | None = None,
    segments: Mapping[str, Mapping[str, Any]],
    synthetic: Sequence[str] = ("train", "val"),
    calibration: str = "train",
    error_model: Mapping[str, Any] | None = None,
    split_seeds: Mapping[str, int] | None = None,
    elevation_mask_deg: float = 15.0,
    slots: str = "satellite",
    path: str | None = None,
    true_params: Any = None,
    initial_mean: Any = None,
    initial_cov: Any = None,
) -> SmartLocTrajectories:
    """Synthetic drives for the splits in ``synthetic``, the real drive for the others.

    A synthetic split's segment ``{start, stop, length}`` bounds the real epochs whose geometry
    (reference track, satellites, visibility, receiver variances, C/N0, odometry) is used:
    ``batch_size`` windows of ``length`` epochs start at epochs drawn uniformly in the segment
    (seeded by the split's seed), and their pseudoranges and clock are drawn from a
    :class:`~difffilter.sim.smartloc_synthetic.PseudorangeErrorModel`.  That model is estimated
    by :func:`~difffilter.sim.smartloc_synthetic.calibrate_error_model` on the real epochs of the
    segment named ``calibration`` (with the reference track), then overridden field by field by
    ``error_model``.  Initial beliefs: centred on a draw from ``N(truth, P0)`` with the real
    windows' ``P0``.  Other splits are :func:`smartloc_simulator`'s real windows.  The remaining
    arguments are :func:`smartloc_simulator`'s.
    """
    split = _split_of(seed, split_seeds)
    bad = sorted(set(synthetic) - set(segments))
    if bad:
        raise ValueError(f"synthetic names splits without a segment: {bad}; segments has {sorted(segments)}")
    if calibration not in segments:
        raise ValueError(f"calibration must name a segment, got {calibration!r}; segments has {sorted(segments)}")
    if split not in synthetic:
        return smartloc_simulator(
            batch_size=batch_size,
            seed=seed,
            dtype=dtype,
            num_steps=num_steps,
            segments=segments,
            split_seeds=split_seeds,
            elevation_mask_deg=elevation_mask_deg,
            slots=slots,
            path=path,
        )
    data = _drive(path, slots)
    total = data.num_epochs
    c0, c1, _, _ = _segment(segments, calibration, total)
    model = _calibrated(path, slots, c0, c1, float(elevation_mask_deg))
    if error_model:
        unknown = sorted(set(error_model) - set(PseudorangeErrorModel.__dataclass_fields__))
        if unknown:
            raise ValueError(f"error_model has unknown fields {unknown}; known: {sorted(PseudorangeErrorModel.__dataclass_fields__)}")
        model = dataclasses.replace(model, **dict(error_model))
    first, stop, length, _ = _segment(segments, split, total)
    if length < 2 or first + length > stop:
        raise ValueError(f"segment {split!r} [{first}, {stop}) holds no window of {length} >= 2 epochs")
    gen = torch.Generator().manual_seed(int(seed))
    starts = torch.randint(first, stop - length + 1, (int(batch_size),), generator=gen).tolist()
    steps = length if num_steps is None else min(length, int(num_steps))
    batch, mean0, cov0, _ = simulate_smartloc_drives(
        data, starts, steps, model, seed=int(seed) + 1, dtype=as_dtype(dtype), elevation_mask_deg=elevation_mask_deg
    )
    return SmartLocTrajectories(
        truth=batch.truth,
        measurements=batch.measurements,
        mask=batch.mask,
        controls=batch.controls,
        initial_mean=mean0,
        initial_cov=cov0,
        start=batch.start,
        data=data,
    )


class SharedBounded(nn.Module):
    """``value = (lower + (upper - lower) sigmoid(raw)) * ones(size)``: one bounded scalar shared
    by ``size`` components (a constraint for ``register_constrained``; ``right_inverse`` takes the
    scalar or ``size`` equal values)."""

    def __init__(self, lower: float, upper: float, size: int) -> None:
        super().__init__()
        if not upper > lower:
            raise ValueError(f"upper must exceed lower, got ({lower}, {upper})")
        self.lower, self.upper, self.size = float(lower), float(upper), int(size)

    def forward(self, raw: Tensor) -> Tensor:
        return (self.lower + (self.upper - self.lower) * torch.sigmoid(raw)).expand(self.size)

    def right_inverse(self, value: Tensor) -> Tensor:
        v = value.reshape(-1)
        if not bool(torch.allclose(v, v[:1].expand_as(v))):
            raise ValueError(f"a shared parameter needs equal components, got {v.tolist()}")
        u = (v[0] - self.lower) / (self.upper - self.lower)
        if not 0.0 <= float(u) <= 1.0:
            raise ValueError(f"shared parameter must lie in [{self.lower}, {self.upper}], got {float(v[0])}")
        eps = 1e-15 if v.dtype == torch.float64 else 1e-7
        return torch.logit(u.clamp(eps, 1 - eps))


class SharedPsiColoredUKF(ColoredNoiseUKF):
    """:class:`~difffilter.filters.colored.ColoredNoiseUKF` (p001) with one AR(1) coefficient
    ``Psi`` for every measurement component: ``v_{k,j} = Psi v_{k-1,j} + eta_{k,j}``.

    ``psi`` still reads as ``[m]`` (all equal); setting it takes a scalar.  Learnable: ``psi``
    (one ``Bounded(-1, 1)`` scalar) and the model's parameters.
    """

    def __init__(self, model: StateSpaceModel, *, psi: float = 0.0, sigma_points: SigmaPoints | None = None) -> None:
        super().__init__(model, psi=psi, sigma_points=sigma_points)
        current = self.psi.detach()
        register_constrained(self, "psi", current[0].clone(), SharedBounded(-1.0, 1.0, current.shape[0]))


class _Epochs:
    """The fields of :class:`~difffilter.sim.smartloc.SmartLocData` that
    :func:`~difffilter.sim.smartloc.single_epoch_wls` reads, for ``E`` epochs of a batch."""

    def __init__(self, z: Tensor, mask: Tensor, u: Mapping[str, Tensor], origin: Tensor) -> None:
        f64 = torch.float64
        self._z = z.to(f64)
        self.mask = mask
        self.sat_enu = u["sat_pos"].to(f64)
        self.glonass = u["glonass"].to(f64) > 0.5
        self.pr_var = torch.where(mask, u["pr_var"].to(f64), 1.0)
        self.elevation = torch.full_like(self._z, 90.0)  # the batch mask already holds the elevation mask
        self.origin_ecef = origin.to(f64)
        self.num_slots, self.num_epochs = int(z.shape[-1]), int(z.shape[0])

    def reduced_pseudorange(self) -> Tensor:
        return torch.where(self.mask, self._z, 0.0)


class SnapshotWLS(GaussianFilter):
    """Single-epoch robust weighted least squares as a memoryless filter (smartLoc baseline).

    Each epoch is solved on its own by :func:`~difffilter.sim.smartloc.single_epoch_wls`
    (Gauss-Newton for ``[E, N, U, b, beta]``, Sagnac term, weights ``1 / pr_var``, robust
    reweighting) on the observed pseudoranges of the batch.  Output in the odometry layout
    ``[E, N, U, yaw, b, d, beta]`` with yaw and drift 0; covariance = the nominal WLS covariance
    ``(J^T W J + prior)^{-1}`` (robust weights not included) and ``unknown_var`` for yaw and
    drift.  No innovations: ``log_likelihood`` and ``nis`` are NaN.  Nothing is learnable.

    Args:
        model: the odometry + pseudorange model (gives the ENU frame origin and ``K``).
        robust, threshold: as :func:`single_epoch_wls` (default Cauchy, ``c = 1.5``).
    """

    def __init__(self, model: StateSpaceModel, *, robust: str | None = "cauchy", threshold: float = 1.5, unknown_var: float = 1e6) -> None:
        super().__init__(model)
        self.robust, self.threshold, self.unknown_var = robust, float(threshold), float(unknown_var)

    def forward(  # type: ignore[override]
        self,
        measurements: Tensor,
        initial_mean: Tensor | None = None,
        initial_cov: Tensor | None = None,
        mask: Tensor | None = None,
        controls: Controls = None,
        *,
        belief: dict[str, Tensor] | None = None,
    ) -> FilterResult:
        z, mask, _, _ = self.check_inputs(measurements, initial_mean, initial_cov, mask, controls)
        if not isinstance(controls, dict):
            raise TypeError("SnapshotWLS needs the smartLoc controls dict (sat_pos, glonass, pr_var)")
        bsz, steps, k = z.shape
        obs = torch.ones_like(z, dtype=torch.bool) if mask is None else mask
        flat = {key: v.reshape(bsz * steps, *v.shape[2:]) for key, v in controls.items()}
        epochs = _Epochs(z.reshape(-1, k), obs.reshape(-1, k), flat, self.model.measurement.frame_origin)
        sol = single_epoch_wls(epochs, elevation_mask_deg=0.0, robust=self.robust, threshold=self.threshold)  # type: ignore[arg-type]
        x5 = torch.cat([sol.enu, sol.clock[:, None], sol.isb[:, None]], -1)
        valid = torch.isfinite(x5).all(-1)
        x5 = torch.where(valid[:, None], x5, 0.0)
        meas = self.model.measurement
        lay = meas.layout
        state = x5.new_zeros(bsz * steps, self.state_dim)
        cols = [*lay.position, lay.clock_bias, lay.isb]
        state[:, cols] = x5
        jac = meas.jacobian(state, {"sat_pos": epochs.sat_enu, "glonass": epochs.glonass.to(torch.float64)})[..., cols]
        w = torch.where(sol.used, 1.0 / epochs.pr_var, 0.0)
        normal = jac.mT @ (w[..., None] * jac)
        normal[:, 4, 4] = normal[:, 4, 4] + 1e-4  # the loader's 100 m ISB prior
        cov5 = torch.linalg.inv(normal)
        cov5 = torch.where(valid[:, None, None], cov5, torch.eye(5, dtype=cov5.dtype) * self.unknown_var)
        cov = torch.eye(self.state_dim, dtype=cov5.dtype).repeat(bsz * steps, 1, 1) * self.unknown_var
        idx = torch.tensor(cols)
        cov[:, idx[:, None], idx] = cov5
        dtype = measurements.dtype
        mean, cov = state.reshape(bsz, steps, -1).to(dtype), cov.reshape(bsz, steps, self.state_dim, self.state_dim).to(dtype)
        nan = torch.full((bsz, steps), math.nan, dtype=dtype, device=z.device)
        used = sol.used.reshape(bsz, steps, k).sum(-1).to(dtype)
        final = {"mean": mean[:, -1], "cov": cov[:, -1]}
        return FilterResult(mean, cov, mean, cov, nan, nan.clone(), used, final)
