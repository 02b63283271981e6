"""Experiment support for p003 (IMM of simplified UKFs, GPS/SINS ultra-tight): builders, simulator
wrapper, empirical transition matrix and the mode-switch report.

* :func:`p003_mode_model` - the 20-state error model of one IMM mode, its ``Q`` (continuous-time PSD)
  and ``R`` learnable as *scales* on the sensor specification (:func:`~difffilter.sim.p003_flight.make_p003_model`,
  ``"scalar"`` structure), or, with ``white_only``, the high mode the simulator really uses (only the
  IMU white noises scaled).
* :func:`p003_imm` / :func:`p003_single` - the IMM of two modes (``filter``: ``"simplified"`` =
  p003's UTCUKF, ``"standard"`` = additive-noise UKF, ``"augmented"`` = augmented UKF) and a
  single-mode filter, from plain config values.
* :func:`p003_learner` - the learner, optionally with each mode's ``Q`` split into two
  log-scaled groups (IMU white noises / everything else) on the learned copy only.
* :func:`simulate` - :func:`~difffilter.sim.p003_flight.simulate_p003` in metres with ``num_steps``
  (what the data module passes for short debug runs) mapped to the duration.
* :func:`empirical_transition` - the maximum-likelihood Markov matrix of a phase schedule's mode
  sequence (the oracle's ``Pi``).
* :class:`ModeSwitchReport` - a Hydra callback (``hydra.callbacks``) that, after the run wrote
  ``results.md``, rebuilds the IMM rows (hand-tuned, learned from the best checkpoint, oracle,
  IMM baselines), reruns them on test trajectories and appends a table of mode-switch delays
  (:func:`~difffilter.learn.metrics.mode_switch_delay`), mode accuracy and time per step; also
  written to ``mode_switch.csv``.
"""

from __future__ import annotations

import copy
import csv
import logging
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra.experimental.callback import Callback
from torch import Tensor
from torch.nn.utils import parametrize

from ..filters import UKF, SimplifiedUKF
from ..filters.base import GaussianFilter
from ..filters.sigma_points import MerweScaled
from ..mixers import IMM
from ..models.sins import SinsErrorDynamics, SinsPseudorangeMeasurement
from ..params import GroupScaledCovariance, register_constrained
from ..sim.p003_flight import PAPER_PHASES, P003Scenario, make_p003_model, manoeuvre_flags, simulate_p003
from ..sim.sampling import as_dtype
from .metrics import mode_switch_delay

__all__ = [
    "PAPER_SWITCH_STEPS",
    "ModeSwitchReport",
    "GroupScaledCovariance",
    "empirical_transition",
    "group_scale_q",
    "p003_learner",
    "model_options",
    "p003_imm",
    "p003_mode_model",
    "p003_single",
    "simulate",
]

log = logging.getLogger(__name__)

#: p003's switching speed (steps): low->high at the 10-20 s acceleration, back to low at 20-60 s.
PAPER_SWITCH_STEPS: dict[str, tuple[float, float]] = {"simplified": (5.0, 5.0), "standard": (7.0, 8.0)}

_WHITE = slice(3, 9)  # accelerometer and gyro white-noise PSD entries of models.sins


def p003_mode_model(
    *,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    white_only: bool = False,
    num_satellites: int = 8,
    linearized: bool = False,
    position_in_metres: bool = True,
    discretization: str = "expm",
    dtype: torch.dtype | str = "float64",
) -> torch.nn.Module:
    """One mode's model: :func:`make_p003_model` at the sensor specification, then

    * ``white_only=False``: ``Q = q_scale Q_spec``, ``R = r_scale R_spec`` with learnable scales
      (``"scalar"`` structure: ``Q``/``R`` values are scale x spec, the scale starts at the given one);
    * ``white_only=True``: only the IMU white-noise PSD entries scaled by ``q_scale`` (the
      simulator's manoeuvre noise), ``"diagonal"`` structure.
    """
    dt = as_dtype(dtype)
    opts = {"num_satellites": int(num_satellites), "linearized": linearized, "position_in_metres": position_in_metres}
    opts["discretization"] = discretization
    model = make_p003_model(Q_structure="diagonal" if white_only else "scalar", dtype=dt, **opts)  # type: ignore[arg-type]
    with torch.no_grad():
        if white_only:
            q = torch.diagonal(model.dynamics.Q).clone()
            q[_WHITE] = q[_WHITE] * q_scale
            model.dynamics.Q = torch.diag(q)
        else:
            model.dynamics.Q = torch.tensor(float(q_scale), dtype=dt)
        model.measurement.R = torch.tensor(float(r_scale), dtype=dt)
    return model


def group_scale_q(imm: GaussianFilter, q_groups: str | None) -> GaussianFilter:
    """Re-parametrize every mode's ``Q`` of ``imm`` in place as :func:`p003_learner` describes
    (``q_groups=None``: nothing changes); returns ``imm``."""
    if q_groups is None:
        return imm
    if q_groups != "imu_white":
        raise ValueError(f"q_groups must be None or 'imu_white', got {q_groups!r}")
    modes = getattr(imm, "filters", None)
    if modes is None:
        raise TypeError(f"q_groups needs an IMM of SINS mode filters, got {type(imm).__name__}")
    for mode in modes:
        dyn = mode.model.dynamics
        if not isinstance(dyn, SinsErrorDynamics):
            raise TypeError(f"q_groups needs SinsErrorDynamics modes, got {type(dyn).__name__}")
        if not parametrize.is_parametrized(dyn, "Q"):
            raise TypeError("q_groups needs a learnable Q (a parametrized SinsErrorDynamics.Q)")
        q = dyn.Q.detach().clone()
        white = torch.zeros(q.shape[-1], dtype=q.dtype, device=q.device)
        white[_WHITE] = 1.0
        register_constrained(dyn, "Q", torch.ones((), dtype=q.dtype), GroupScaledCovariance(q, torch.stack([white, 1.0 - white])))
    return imm


def p003_learner(
    filter: GaussianFilter,  # noqa: A002 - the field's word
    loss: Any,
    *,
    q_groups: str | None = None,
    **learner_kwargs: Any,
) -> Any:
    """A :class:`~difffilter.learn.learner.FilterLearner` on ``filter`` (``run_experiment`` hands
    it a copy of the hand-tuned IMM).

    ``q_groups=None``: exactly ``FilterLearner(filter, loss, ...)``.  ``q_groups="imu_white"``:
    every mode's ``Q`` becomes a :class:`GroupScaledCovariance` on its current (hand-tuned)
    value with two log-scaled groups, the IMU white-noise PSD entries (accelerometer and gyro)
    and all other entries (position floors, sensor-bias drivers, clock), both starting at 1; the
    parameter keeps the name ``Q``.  This is the family that contains the simulator's manoeuvre
    noise (only the IMU white noises grow), which one scalar per mode cannot express.
    """
    from .learner import FilterLearner  # Lightning is imported lazily, as in difffilter.learn

    group_scale_q(filter, q_groups)
    return FilterLearner(filter, loss, **learner_kwargs)


def _mode_filter(kind: str, model: torch.nn.Module, alpha: float, beta: float, kappa: float) -> GaussianFilter:
    points = MerweScaled(alpha=alpha, beta=beta, kappa=kappa)
    if kind == "simplified":
        return SimplifiedUKF(model, sigma_points=points)  # type: ignore[arg-type]
    if kind == "standard":
        return UKF(model, sigma_points=points, redraw_after_predict=True)  # type: ignore[arg-type]
    if kind == "augmented":
        return UKF(model, sigma_points=points, redraw_after_predict=True, noise="augmented")  # type: ignore[arg-type]
    raise ValueError(f"filter must be 'simplified', 'standard' or 'augmented', got {kind!r}")


ModelOptions = Mapping[str, Any] | torch.nn.Module | None


def model_options(model: ModelOptions) -> dict[str, Any]:
    """Structure options of :func:`p003_mode_model` (``num_satellites``, ``linearized``,
    ``position_in_metres``, ``discretization``) from a mapping (returned as is, ``_target_``/
    ``q_scale``/``r_scale``/``dtype`` dropped) or read off a SINS model built by it (its noise
    levels are not options: every mode is the specification times its scales)."""
    if model is None:
        return {}
    if isinstance(model, Mapping):
        return {k: v for k, v in model.items() if k not in ("_target_", "q_scale", "r_scale", "white_only", "dtype")}
    meas, dyn = getattr(model, "measurement", None), getattr(model, "dynamics", None)
    if not isinstance(meas, SinsPseudorangeMeasurement) or not isinstance(dyn, SinsErrorDynamics):
        raise TypeError(f"model must be p003 options or a SINS StateSpaceModel (p003_mode_model), got {type(model).__name__}")
    return {
        "num_satellites": meas.num_satellites,
        "linearized": meas.linearized,
        "position_in_metres": meas.position_in_metres,
        "discretization": dyn.discretization,
    }


def empirical_transition(phases: Sequence[tuple[float, float, str, float]] = PAPER_PHASES, duration: float = 1800.0) -> list[list[float]]:
    """Maximum-likelihood ``Pi [2, 2]`` (mode 0 = level/static, 1 = manoeuvre) of the 1 Hz mode
    sequence of ``phases`` (the flags of :func:`simulate_p003`: step ``k`` in a manoeuvre when
    ``k - 0.5 s`` lies inside one)."""
    flags = manoeuvre_flags(list(phases), np.arange(1, int(round(duration)) + 1) - 0.5).astype(int)
    counts = np.zeros((2, 2))
    np.add.at(counts, (flags[:-1], flags[1:]), 1.0)
    rows = counts.sum(1, keepdims=True)
    if (rows == 0).any():
        raise ValueError("the schedule never visits one of the two modes")
    return (counts / rows).tolist()


def p003_imm(
    *,
    filter: str = "simplified",  # noqa: A002 - config key
    model: ModelOptions = None,
    q_scales: Sequence[float] = (1.0, 1.0e4),
    r_scales: Sequence[float] = (1.0, 100.0),
    white_only_high: bool = False,
    transition: Sequence[Sequence[float]] | str = ((0.95, 0.05), (0.05, 0.95)),
    initial_probs: Sequence[float] = (0.9, 0.1),
    alpha: float = 1.0,
    beta: float = 2.0,
    kappa: float = 0.0,
    prob_floor: float = 1.0e-6,
    dtype: torch.dtype | str = "float64",
) -> IMM:
    """p003's two-mode IMM (mode 0 low noise, mode 1 high noise) of ``filter`` mode filters.

    Args:
        model: options of :func:`p003_mode_model` shared by the modes (``num_satellites``,
            ``linearized``, ``position_in_metres``, ``discretization``), or a model built by it
            whose options are used (:func:`model_options`).
        q_scales, r_scales: per-mode scales on the spec ``Q`` (PSD, i.e. ``sigma_Q^2``) and ``R``.
        white_only_high: the high mode scales only the IMU white noises (the simulator's truth).
        transition: ``[2, 2]`` ``Pi`` or ``"paper"`` (:func:`empirical_transition` of the paper profile).
    """
    dt = as_dtype(dtype)
    opts = model_options(model)
    modes = []
    for j, (qs, rs) in enumerate(zip(q_scales, r_scales, strict=True)):
        m = p003_mode_model(q_scale=qs, r_scale=rs, white_only=white_only_high and j > 0, dtype=dt, **opts)
        modes.append(_mode_filter(filter, m, alpha, beta, kappa))
    pi = empirical_transition() if isinstance(transition, str) and transition == "paper" else transition
    if isinstance(pi, str):
        raise ValueError(f"transition must be a [2, 2] matrix or 'paper', got {pi!r}")
    imm = IMM(
        modes, transition=torch.tensor(pi, dtype=dt), initial_probs=torch.tensor(list(initial_probs), dtype=dt), prob_floor=prob_floor
    )
    return imm.to(dt)


def p003_single(
    *,
    filter: str = "simplified",  # noqa: A002 - config key
    model: ModelOptions = None,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    alpha: float = 1.0,
    beta: float = 2.0,
    kappa: float = 0.0,
    dtype: torch.dtype | str = "float64",
) -> GaussianFilter:
    """A single-mode filter with the given noise scales (p003's single-model comparison)."""
    dt = as_dtype(dtype)
    m = p003_mode_model(q_scale=q_scale, r_scale=r_scale, dtype=dt, **model_options(model))
    return _mode_filter(filter, m, alpha, beta, kappa).to(dt)


def simulate(
    batch_size: int = 1,
    seed: int | torch.Generator | None = 0,
    dtype: torch.dtype = torch.float64,
    *,
    num_steps: int | None = None,
    duration: float = 1800.0,
    profile: str = "paper",
    position_in_metres: bool = True,
    **kwargs: Any,
) -> P003Scenario:
    """:func:`simulate_p003` with ``num_steps`` (1 Hz steps) overriding ``duration``; metres by default."""
    dur = float(num_steps) if num_steps is not None else float(duration)
    return simulate_p003(batch_size, seed, dtype, profile=profile, duration=dur, position_in_metres=position_in_metres, **kwargs)


# --- mode-switch report -------------------------------------------------------------------------
def _switch_stats(mode_probs: Tensor, modes: Tensor, threshold: float) -> dict[str, float]:
    d = mode_switch_delay(mode_probs, modes, threshold)
    out: dict[str, float] = {}
    for name, target in (("to_high", 1), ("to_low", 0)):
        sel = d.mode == target
        vals = d.delay[sel]
        ok = torch.isfinite(vals)
        out[f"{name}_delay"] = float(vals[ok].mean()) if bool(ok.any()) else math.nan
        out[f"{name}_detected"] = float(ok.to(torch.float64).mean()) if vals.numel() else math.nan
    # the paper's two numbers: the first manoeuvre's onset and its end
    for name, target in (("first_to_high", 1), ("first_to_low", 0)):
        sel = d.mode == target
        starts = d.start[sel]
        if starts.numel():
            s0 = int(starts.min())
            v = d.delay[sel & (d.start == s0)]
            out[name] = float(v[torch.isfinite(v)].mean()) if bool(torch.isfinite(v).any()) else math.nan
        else:
            out[name] = math.nan
    out["mode_accuracy"] = float((mode_probs.argmax(-1) == modes).to(torch.float64).mean())
    return out


@torch.no_grad()
def _noise_levels(imm: IMM, spec: torch.nn.Module) -> dict[str, str]:
    """Per-mode levels relative to the specification ``spec``: the gyro white-noise PSD entry
    (``Q_scale``), the clock-drift PSD entry (``Q_clock``, 1 when only the IMU white noise is
    scaled) and the pseudorange variance (``R_scale``); and ``diag(Pi)``."""
    q_ref, r_ref = torch.diagonal(spec.dynamics.Q), torch.diagonal(spec.measurement.R)
    qs, qc, rs = [], [], []
    for f in imm.filters:
        q, r = torch.diagonal(f.model.dynamics.Q), torch.diagonal(f.model.measurement.R)
        qs.append(float(q[6] / q_ref[6]))
        qc.append(float(q[19] / q_ref[19]))
        rs.append(float(r[0] / r_ref[0]))
    join = lambda v: ", ".join(f"{x:.3g}" for x in v)  # noqa: E731
    return {"Q_scale": join(qs), "Q_clock": join(qc), "R_scale": join(rs), "Pi_diag": join(torch.diagonal(imm.transition).tolist())}


class ModeSwitchReport(Callback):
    """Hydra callback: append p003's mode-switch table to the run's ``results.md`` (see the module
    docstring).  Configure as ``hydra.callbacks.<name>: {_target_: ..., threshold: 0.5, num_trajectories: 2}``.

    Args:
        threshold: mode probability that counts as a switch (0.5: the more likely of two modes).
        num_trajectories: test trajectories to rerun (``None``: all).
        timing_steps: length of the segment (first steps of the selected trajectories) used to time
            each filter; the filters are timed in turn, ``timing_repeats`` rounds, and the fastest
            round is kept (robust to other processes on a shared machine).
        timing_repeats: rounds of timing.
    """

    def __init__(
        self, *, threshold: float = 0.5, num_trajectories: int | None = 2, timing_steps: int = 200, timing_repeats: int = 3
    ) -> None:
        self.threshold = float(threshold)
        self.num_trajectories = num_trajectories
        self.timing_steps = int(timing_steps)
        self.timing_repeats = int(timing_repeats)

    def on_job_end(self, config: Any, job_return: Any, **kwargs: Any) -> None:
        from hydra.core.utils import JobStatus

        if getattr(job_return, "status", None) != JobStatus.COMPLETED:
            return
        try:
            from hydra.core.hydra_config import HydraConfig

            out_dir = Path(HydraConfig.get().runtime.output_dir)
        except ValueError:
            out_dir = Path(config.paths.output_dir)
        self.report(config, out_dir)

    def report(self, cfg: Any, out_dir: Path) -> list[dict[str, Any]]:
        """Rebuild, rerun and append the table (callable without Hydra, e.g. from tests)."""
        from hydra.utils import instantiate
        from omegaconf import OmegaConf

        from .experiment import build_filter

        if cfg.get("threads"):
            torch.set_num_threads(int(cfg.threads))
        dtype = as_dtype(cfg.dtype)
        plain = lambda node: OmegaConf.to_container(node, resolve=True) if node is not None else None  # noqa: E731
        data = instantiate(cfg.data, _convert_="all")
        test = data.dataset("test")
        k = len(test) if self.num_trajectories is None else min(int(self.num_trajectories), len(test))
        batch = test.batch(torch.arange(k))
        modes = test.source.manoeuvre[:k, : batch["measurements"].shape[1]].long()
        exp = cfg.experiment
        hand = build_filter(cfg.filter, dtype=dtype, params=plain(exp.get("hand_tuned")))
        filters: dict[str, GaussianFilter] = {"hand-tuned": hand}
        learned = self._learned(hand, out_dir, cfg.learner.get("q_groups"))
        if learned is not None:
            filters["learned"] = learned
        oracle = exp.get("oracle")
        if oracle is not None and oracle.get("filter") is not None:
            filters["oracle"] = build_filter(oracle.filter, dtype=dtype, params=plain(oracle.get("params")))
        for name, spec in (plain(exp.get("baselines")) or {}).items():
            filt = build_filter(spec.get("filter") or cfg.filter, dtype=dtype, params=spec.get("params"))
            if isinstance(filt, IMM):
                filters[name] = filt
        spec = p003_mode_model(dtype=dtype, **model_options(plain(cfg.get("model"))))
        imms = {name: filt.to(dtype).eval() for name, filt in filters.items() if isinstance(filt, IMM)}
        timing = self._time(imms, batch)
        rows = []
        for name, filt in imms.items():
            rows.append(
                {"filter": name, **self._evaluate(filt, batch, modes), "time_per_step_ms": timing[name], **_noise_levels(filt, spec)}
            )
        self._write(rows, out_dir, k, int(batch["measurements"].shape[1]))
        return rows

    @staticmethod
    def _learned(hand: GaussianFilter, out_dir: Path, q_groups: str | None = None) -> GaussianFilter | None:
        ckpts = sorted((out_dir / "checkpoints").glob("*.ckpt"))
        if not ckpts:
            log.warning("ModeSwitchReport: no checkpoint under %s; the learned row is left out", out_dir)
            return None
        state = torch.load(ckpts[-1], map_location="cpu", weights_only=False)["state_dict"]
        return ModeSwitchReport._learned_from_state(hand, state, q_groups)

    @staticmethod
    def _learned_from_state(hand: GaussianFilter, state: Mapping[str, Tensor], q_groups: str | None = None) -> GaussianFilter:
        """A copy of ``hand`` in the learner's layout (``q_groups``, see :func:`p003_learner`)
        with the ``filter.*`` entries of a learner's ``state``."""
        learned = group_scale_q(copy.deepcopy(hand), q_groups)
        learned.load_state_dict({k.removeprefix("filter."): v for k, v in state.items() if k.startswith("filter.")})
        return learned

    @torch.no_grad()
    def _time(self, filters: Mapping[str, GaussianFilter], batch: dict[str, Any]) -> dict[str, float]:
        """Fastest of ``timing_repeats`` rounds (filters interleaved) of ms per step on the first
        ``timing_steps`` steps, after one untimed warm-up round."""
        steps = min(self.timing_steps, batch["measurements"].shape[1])
        z, mask = batch["measurements"][:, :steps], batch["mask"]
        mask = None if mask is None else mask[:, :steps]
        ctrl = {k: v[:, :steps] for k, v in batch["controls"].items()}
        best = {name: math.inf for name in filters}
        for rnd in range(self.timing_repeats + 1):
            for name, filt in filters.items():
                tic = time.perf_counter()
                filt(z, batch["initial_mean"], batch["initial_cov"], mask=mask, controls=ctrl)
                if rnd > 0:
                    best[name] = min(best[name], 1e3 * (time.perf_counter() - tic) / steps)
        return best

    @torch.no_grad()
    def _evaluate(self, filt: GaussianFilter, batch: dict[str, Any], modes: Tensor) -> dict[str, float]:
        res = filt(batch["measurements"], batch["initial_mean"], batch["initial_cov"], mask=batch["mask"], controls=batch["controls"])
        stats = _switch_stats(res.mode_probs, modes, self.threshold)
        stats["mean_high_prob_level"] = float(res.mode_probs[..., 1][modes == 0].mean())
        return stats

    def _write(self, rows: list[dict[str, Any]], out_dir: Path, k: int, steps: int) -> None:
        cols = ["filter", "to_high_delay", "to_low_delay", "first_to_high", "first_to_low", "to_high_detected", "to_low_detected"]
        cols += ["mode_accuracy", "mean_high_prob_level", "time_per_step_ms", "Q_scale", "Q_clock", "R_scale", "Pi_diag"]
        out_dir.mkdir(parents=True, exist_ok=True)
        with (out_dir / "mode_switch.csv").open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)
        fmt = lambda v: v if isinstance(v, str) else ("nan" if v is None or math.isnan(v) else f"{v:.3g}")  # noqa: E731
        lines = [
            "",
            "## IMM mode switching (ModeSwitchReport)",
            "",
            f"{k} test trajectories x {steps} steps, rerun after training; delay = steps from a true mode change until the "
            f"matching mode's probability exceeds {self.threshold} (0 = at the first step of the new mode); *_delay = mean "
            "over all switches, first_* = the first manoeuvre (p003: the 10-20 s acceleration, low->high and back); detected = "
            "fraction of switches found before the next one; mean_high_prob_level = mean high-mode probability in level flight; "
            f"time_per_step_ms = fastest of {self.timing_repeats} interleaved timing rounds on the first {self.timing_steps} steps "
            "of the batch; Q_scale / Q_clock / R_scale = (low, high) mode gyro-white PSD, "
            "clock-drift PSD and pseudorange variance over the specification.  p003: standard-UKF IMM 7 / 8 steps, simplified 5 / 5.",
            "",
            "| " + " | ".join(cols) + " |",
            "|" + "---|" * len(cols),
        ]
        lines += ["| " + " | ".join(fmt(r.get(c, math.nan)) for c in cols) + " |" for r in rows]
        md = out_dir / "results.md"
        with md.open("a") as fh:
            fh.write("\n".join(lines) + "\n")
        print("\n".join(lines))
