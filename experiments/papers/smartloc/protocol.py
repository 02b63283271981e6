"""The real-data protocol on libRSF drives (``python experiments/realdata.py``; configuration in
``conf/realdata.yaml`` + ``conf/realdata/<name>.yaml``).

For every fold (an assignment of contiguous blocks of each drive to train / validation / test,
:func:`~experiments.holdout.contiguous_blocks`) and every learned variant (a pseudorange noise
model, :mod:`experiments.papers.smartloc.variants`):

1. training data: windows of the train blocks of all drives (one batch; each window starts from the
   snapshot fix of the epoch before it); validation: windows of the validation blocks, likewise
   (``val_windows``; ``length: null`` runs each block as one trajectory); test: each drive's test
   block run as one trajectory;
2. the learned filter (EKF on the odometry + pseudorange model with the variant's noise model and a
   learnable smooth reject gate) starts from the hand-tuned values; every positive parameter is
   bounded to ``[start / bound_ratio, start x bound_ratio]`` and pulled back to its start by a
   :class:`~experiments.holdout.LogDistancePrior`; ``seeds`` replicates (seeded log-normal
   perturbations of the start) train by innovation likelihood (no reference positions) or, with
   ``loss: position``, by a Huber loss of the horizontal error against the train block's
   reference track (:func:`training_loss`);
3. after every epoch the validation blocks' horizontal median + RMS error is recorded
   (:class:`~experiments.holdout.EpochSnapshots`); the model used on test is the
   (seed, epoch) - or the unperturbed start - with the lowest validation score
   (:func:`~experiments.holdout.select_candidate`), within ``epochs x h`` epochs for each
   stability horizon ``h``;
4. on every test block: the hand-tuned filter (the gated EKF with the loader's values), the
   selected learned filters, the EKF without gate and the single-epoch WLS, with paired
   block-bootstrap intervals of learned - hand-tuned (:mod:`experiments.papers.smartloc.report`).

The jobs (fold x variant x seed) run in ``workers`` processes, one thread each.
"""

from __future__ import annotations

import functools
import json
import math
import os
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytorch_lightning as pl
import torch
from pytorch_lightning.loggers import TensorBoardLogger
from torch import Tensor

from difffilter.filters import EKF
from difffilter.filters.protocol import Filter
from difffilter.learn.data import TrajectorySet, WindowedTrajectories
from difffilter.learn.learner import FilterLearner, LearnerOptions
from difffilter.learn.losses import FilterLoss, HuberLoss, LogPrior
from difffilter.learn.replicates import perturb_initial_values
from difffilter.selection import assign_parameters, match_parameters, parameter_owners
from experiments.holdout import (
    EpochSnapshots,
    LogDistancePrior,
    bound_parameters,
    contiguous_blocks,
    restore_snapshot,
    select_candidate,
)

from .data import SmartLocData, find_drives, load_drive
from .extras import extras_options, extras_priors, learn_patterns
from .model import make_smartloc_model, smartloc_initial_belief
from .variants import noise_model, start_coefficients
from .wls import WlsSolution, single_epoch_wls

__all__ = [
    "DYNAMICS",
    "Drive",
    "block_sets",
    "build_filter",
    "cached_drives",
    "fold_coefficients",
    "fold_data",
    "hand_tuned_filter",
    "horizontal_errors",
    "learned_filter",
    "learned_names",
    "load_drives",
    "select_with_fallbacks",
    "selected_filter",
    "start_candidate",
    "train_jobs",
    "training_loss",
    "validation_score",
]

#: Positive dynamics parameters of the odometry model (bounded and decayed like the noise model).
DYNAMICS = ("speed_sigma", "yaw_rate_sigma", "horizontal_psd", "vertical_psd", "yaw_psd", "clock_bias_psd", "clock_drift_psd", "isb_psd")


@dataclass
class Drive:
    """A loaded drive with its robust snapshot fixes (the windows' initial beliefs)."""

    data: SmartLocData
    wls: WlsSolution


def load_drives(specs: Sequence[Mapping[str, Any]], *, slots: str = "epoch", min_satellites: int = 4) -> list[Drive]:
    """Drives named by ``specs``: ``{folder, input_file, truth_file}`` each; ``input_file: null``
    takes every drive of the folder (:func:`~experiments.papers.smartloc.data.find_drives`)."""
    out = []
    for spec in specs:
        folder = Path(str(spec["folder"]))
        pairs = find_drives(folder) if spec.get("input_file") is None else [(str(spec["input_file"]), str(spec["truth_file"]))]
        for inp, gt in pairs:
            data = load_drive(folder, input_file=inp, truth_file=gt, slots=slots, min_satellites=min_satellites)
            out.append(Drive(data, single_epoch_wls(data, robust="cauchy", threshold=1.5)))
    if not out:
        raise ValueError("no drive to load: give at least one {folder: ...}")
    names = [d.data.name for d in out]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:  # the test rows of each drive are found by its name
        raise ValueError(f"drives of the same name {twice} in {[str(s['folder']) for s in specs]}; rename one (<name>_Input.txt)")
    return out


def _controls(drive: Drive, elevation_mask_deg: float, slots: int) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
    """The whole drive as ``[1, T, slots]`` tensors (padded slots masked, dummy satellite far
    above the origin) with its ENU frame as per-step controls."""
    full = drive.data.batch(torch.float64, elevation_mask_deg=elevation_mask_deg)
    k = full.measurements.shape[-1]
    pad = slots - k
    z, mask, u = full.measurements, full.mask, dict(full.controls)
    if pad > 0:
        z = torch.nn.functional.pad(z, (0, pad))
        mask = torch.nn.functional.pad(mask, (0, pad), value=False)
        for key in ("glonass", "pr_obs", "elevation", "cn0", "constellation"):
            u[key] = torch.nn.functional.pad(u[key], (0, pad))
        u["pr_var"] = torch.nn.functional.pad(u["pr_var"], (0, pad), value=1.0)
        dummy = torch.tensor([0.0, 0.0, 2.0e7], dtype=torch.float64).expand(1, z.shape[1], pad, 3)
        u["sat_pos"] = torch.cat([u["sat_pos"], dummy], -2)
    steps = z.shape[1]
    u["frame_origin"] = drive.data.origin_ecef.expand(1, steps, 3).clone()
    u["frame_rotation"] = drive.data.rotation.expand(1, steps, 3, 3).clone()
    return z, mask, u


def block_sets(
    drives: Sequence[Drive],
    spans: Mapping[int, tuple[int, int]],
    *,
    length: int | None = None,
    stride: int | None = None,
    elevation_mask_deg: float = 15.0,
    slots: int | None = None,
) -> list[TrajectorySet]:
    """Trajectory sets of blocks ``spans = {drive index: (first, stop)}``: windows of ``length``
    epochs every ``stride`` pooled into one set (``length=None``: each block whole, one set per
    drive).  Each window starts from the snapshot fix of the epoch before it."""
    k = slots or max(d.data.num_slots for d in drives)
    pieces: list[tuple[Tensor, ...]] = []
    sets = []
    for i, (first, stop) in spans.items():
        drive = drives[i]
        z, mask, u = _controls(drive, elevation_mask_deg, k)
        size = stop - first if length is None else int(length)
        starts = list(range(first, stop - size + 1, size if stride is None else int(stride)))
        if not starts:
            raise ValueError(f"block [{first}, {stop}) of drive {drive.data.name} holds no window of {size} epochs")
        cut = lambda t, s0=starts, n=size: torch.cat([t[:, s : s + n] for s in s0], 0)  # noqa: E731
        mean0, cov0 = smartloc_initial_belief(drive.data, torch.tensor(starts), wls=drive.wls)
        piece = (cut(z), cut(mask), {key: cut(v) for key, v in u.items()}, cut(drive.data.truth_enu[None]), mean0, cov0)
        if length is None:
            sets.append(_trajectory_set(*piece, source=drive.data.name))
        else:
            pieces.append(piece)
    if pieces:
        u = {key: torch.cat([p[2][key] for p in pieces]) for key in pieces[0][2]}
        cat = lambda j: torch.cat([p[j] for p in pieces])  # noqa: E731
        sets.append(_trajectory_set(cat(0), cat(1), u, cat(3), cat(4), cat(5), source="train"))
    return sets


def _trajectory_set(
    z: Tensor, mask: Tensor, u: dict[str, Tensor], truth: Tensor, mean0: Tensor, cov0: Tensor, source: str
) -> TrajectorySet:
    return TrajectorySet(measurements=z, mask=mask, controls=u, truth=truth, initial_mean=mean0, initial_cov=cov0, source=source)


def build_filter(cfg: Mapping[str, Any], drives: Sequence[Drive], variant: str, coefficients: Tensor, *, learned: bool) -> Filter:
    """The EKF on the odometry + pseudorange model: ``learned=False`` gives the hand-tuned filter
    (receiver variances, the loader's hard 2.5-sigma gate with its 8 m floor); ``learned=True`` the
    variant's noise model and the gate of ``cfg["gate"]`` (smooth and learnable, or with
    ``softness: null, learnable: false`` the hard gate at the configured threshold and floor;
    ``gradient: false`` detaches a rejected range's inflated variance, so rejected ranges do not
    pull ``R`` during likelihood training), every positive parameter bounded."""
    hand = dict(cfg["hand_tuned"])
    gate = dict(cfg["gate"])
    model = make_smartloc_model(
        drives[0].data,
        noise_model=noise_model(variant, coefficients, bound=float(cfg["bound_ratio"])) if learned else None,
        robust="reject",
        gate=float(gate["threshold"]),
        gate_floor=float(gate["floor"]),
        gate_softness=float(gate["softness"]) if learned and gate.get("softness") else None,
        gate_learnable=bool(learned and gate.get("learnable")),
        gate_gradient=bool(gate.get("gradient", True)) if learned else True,
        **(extras_options(cfg, len(drives[0].data.systems)) if learned else {}),
        **{k: float(hand[k]) for k in DYNAMICS},
    )
    filt = EKF(model)
    if learned:
        names = [n for n in ("gate_threshold", "gate_floor", "gate_softness", *DYNAMICS) if _has(filt, n)]
        bound_parameters(filt, names, ratio=float(cfg["bound_ratio"]))
    return filt


def _has(filt: torch.nn.Module, name: str) -> bool:
    try:
        match_parameters(filt, [name])
    except ValueError:
        return False
    return True


def horizontal_errors(filt: Filter, sets: Sequence[TrajectorySet]) -> Tensor:
    """Horizontal position errors ``[sum T]`` of ``filt`` on every trajectory of ``sets``."""
    out = []
    with torch.no_grad():
        for s in sets:
            res = filt(s.measurements, s.initial_mean, s.initial_cov, mask=s.mask, controls=s.controls)
            out.append((res.mean[..., :2] - s.truth[..., :2]).norm(dim=-1).reshape(-1))
    return torch.cat(out)


def validation_score(filt: Filter, sets: Sequence[TrajectorySet]) -> tuple[float, dict[str, float]]:
    """Median + RMS of the horizontal error over every epoch of the validation sets (lower is better)."""
    e = horizontal_errors(filt, sets)
    if not bool(torch.isfinite(e).all()):
        return math.inf, {"median": math.inf, "rms": math.inf}
    med, rms = float(e.median()), float(e.pow(2).mean().sqrt())
    return med + rms, {"median": med, "rms": rms}


@functools.lru_cache(maxsize=2)
def cached_drives(key: str) -> tuple[Any, list[Drive]]:
    """``(configuration, drives)`` for a configuration given as JSON text (cached per process)."""
    cfg = json.loads(key)  # the cache key is the configuration's JSON text
    return cfg, load_drives(cfg["drives"], min_satellites=int(cfg.get("min_satellites", 4)))


def fold_data(cfg: Mapping[str, Any], drives: Sequence[Drive], fold: str) -> dict[str, list[TrajectorySet]]:
    """``{"train": [one pooled set], "val": [per drive], "test": [per drive]}`` of a fold."""
    spans = {name: tuple(v) for name, v in dict(cfg["folds"][fold]).items()}
    blocks = [contiguous_blocks(d.data.num_epochs, spans) for d in drives]
    win = dict(cfg["windows"])
    mask_deg = float(cfg["elevation_mask_deg"])
    train = {i: b["train"] for i, b in enumerate(blocks)}
    out = {"train": block_sets(drives, train, length=int(win["length"]), stride=int(win["stride"]), elevation_mask_deg=mask_deg)}
    vwin = dict(cfg.get("val_windows") or {"length": None, "stride": None})
    val = {i: b["val"] for i, b in enumerate(blocks)}
    out["val"] = block_sets(drives, val, length=vwin["length"], stride=vwin["stride"], elevation_mask_deg=mask_deg)
    out["test"] = block_sets(drives, {i: b["test"] for i, b in enumerate(blocks)}, elevation_mask_deg=mask_deg)
    return out


def fold_coefficients(cfg: Mapping[str, Any], drives: Sequence[Drive], fold: str, variant: str) -> Tensor:
    """The variant's starting coefficients, fitted on the fold's training blocks."""
    spans = {name: tuple(v) for name, v in dict(cfg["folds"][fold]).items()}
    train = [(d.data, *contiguous_blocks(d.data.num_epochs, spans)["train"]) for d in drives]
    return start_coefficients(variant, train, elevation_mask_deg=float(cfg["elevation_mask_deg"]))


def learned_names(filt: Filter, patterns: Sequence[str]) -> list[str]:
    """Dotted names of the parameters ``patterns`` match (patterns matching nothing are skipped:
    a variant without that parameter)."""
    out: list[str] = []
    for p in patterns:
        if _has(filt, p):
            out += match_parameters(filt, [p])[p]
    return sorted(set(out))


def training_loss(cfg: Mapping[str, Any]) -> FilterLoss | str:
    """The training loss of ``cfg["loss"]``: ``"nll"`` (default) the innovation likelihood (no
    reference positions); ``"position"`` the mean over epochs of a Huber function of the horizontal
    (E, N) error against the training block's reference track, quadratic up to
    ``position_loss.huber_delta`` metres and linear beyond (so lock-loss stretches with errors of
    50-100 m do not dominate the gradient)."""
    kind = str(cfg.get("loss", "nll"))
    if kind == "nll":
        return "nll"
    if kind == "position":
        delta = float(dict(cfg.get("position_loss") or {}).get("huber_delta", 10.0))
        return HuberLoss(state_index=[0, 1], truth_index=[0, 1], delta=delta)
    raise ValueError(f"loss must be 'nll' or 'position', got {kind!r}")


def select_with_fallbacks(
    learned: Sequence[Sequence[float]], *, start: float | None, hand: float | None, horizon: int | None = None
) -> tuple[str, int, int]:
    """The validation choice among the learned ``(replicate, epoch)`` scores and the non-learned
    candidates (the untrained start's score ``start`` and the hand-tuned filter's ``hand``; ``None``:
    not a candidate).  A learned model is chosen only if its score is strictly below every
    non-learned candidate's; otherwise the best non-learned one (the hand-tuned filter on a tie).
    Returns ``("learned", replicate, epoch)``, ``("start", 0, 0)`` or ``("hand-tuned", 0, 0)``."""
    rep, ep = select_candidate(learned, horizon)
    best = float(learned[rep][ep])
    others = [(float(v), k) for k, v in (("hand-tuned", hand), ("start", start)) if v is not None and math.isfinite(float(v))]
    if not others or all(best < v for v, _ in others):
        return "learned", rep, ep
    low = min(v for v, _ in others)
    return next(k for v, k in others if v == low), 0, 0  # "hand-tuned" first: it wins a tie with the start


def _train_job(job: Mapping[str, Any]) -> dict[str, Any]:
    """One replicate: train, recording validation scores and parameter snapshots every epoch."""
    torch.set_num_threads(1)
    cfg, drives = cached_drives(json.dumps(job["cfg"], sort_keys=True))
    sets = fold_data(cfg, drives, job["fold"])
    coef = torch.tensor(job["coefficients"], dtype=torch.float64)
    filt = build_filter(cfg, drives, job["variant"], coef, learned=True)
    names = learned_names(filt, learn_patterns(cfg))
    owners = parameter_owners(filt)
    prior = dict(cfg["prior"])
    signed = extras_priors(cfg, names, owners)
    priors = {
        n: LogDistancePrior(reference=getattr(owners[n][0], owners[n][1]).detach(), scale=float(prior["scale"]))
        for n in names
        if n not in signed
    }
    priors.update(signed)
    snaps = EpochSnapshots(lambda f: validation_score(f, sets["val"]), names)
    learner = FilterLearner(
        filt.double(),
        training_loss(cfg),
        learn=names,
        optimizer=functools.partial(torch.optim.Adam, lr=float(cfg["lr"])),
        prior=LogPrior(priors, weight=float(prior["weight"])),
        options=LearnerOptions(position_index=[0, 1]),
    )
    perturb_initial_values(learner.filter, learner.learned_names, float(cfg["init_perturbation"]), seed=int(job["seed"]))
    pl.seed_everything(int(job["seed"]), workers=False, verbose=False)
    logger = TensorBoardLogger(
        job["log_dir"], name=f"{job['fold']}_{job['variant']}", version=f"seed{job['seed']}", default_hp_metric=False
    )
    trainer = pl.Trainer(
        max_epochs=int(job["epochs"]),
        logger=logger,
        callbacks=[snaps],
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=0,
        num_sanity_val_steps=0,
        log_every_n_steps=1,
        accelerator="cpu",
        devices=1,
    )
    train = sets["train"][0]
    trainer.fit(learner, train_dataloaders=WindowedTrajectories(train, batch_size=len(train)))  # a ready-made loader
    return {
        **{k: job[k] for k in ("fold", "variant", "seed")},
        "scores": snaps.scores,
        "extras": snaps.extras,
        "snapshots": snaps.snapshots,
    }


def train_jobs(jobs: Sequence[Mapping[str, Any]], *, workers: int = 1) -> list[dict[str, Any]]:
    """Run :func:`_train_job` for every job, in ``workers`` processes (1: in this process)."""
    if workers <= 1:
        return [_train_job(j) for j in jobs]
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    with ProcessPoolExecutor(max_workers=int(workers)) as pool:
        return list(pool.map(_train_job, jobs))


def start_candidate(cfg: Mapping[str, Any], drives: Sequence[Drive], fold: str, variant: str, coefficients: Tensor) -> dict[str, Any]:
    """The unperturbed start as a candidate (its validation score and snapshot)."""
    sets = fold_data(cfg, drives, fold)
    filt = build_filter(cfg, drives, variant, coefficients, learned=True)
    snaps = EpochSnapshots(lambda f: validation_score(f, sets["val"]), learned_names(filt, learn_patterns(cfg)))
    snaps.record(filt)
    return {"fold": fold, "variant": variant, "seed": "start", "scores": snaps.scores, "extras": snaps.extras, "snapshots": snaps.snapshots}


def learned_filter(
    cfg: Mapping[str, Any], drives: Sequence[Drive], variant: str, coefficients: Tensor, snapshot: Mapping[str, Tensor]
) -> Filter:
    """The learned filter of ``variant`` with a snapshot's raw values."""
    filt = build_filter(cfg, drives, variant, coefficients, learned=True)
    restore_snapshot(filt, snapshot)
    return filt


def selected_filter(cfg: Mapping[str, Any], drives: Sequence[Drive], variant: str, selection: Mapping[str, Any]) -> Filter:
    """The filter a run selected for ``variant`` (an entry of its ``selected.pt``): the learned
    filter with the saved snapshot, or the hand-tuned filter when the selection fell back to it
    (``{"hand_tuned": True}``, see ``selection.hand_tuned_candidate``)."""
    if selection.get("hand_tuned"):
        return hand_tuned_filter(cfg, drives)
    return learned_filter(cfg, drives, variant, selection["coefficients"], selection["snapshot"])


def hand_tuned_filter(cfg: Mapping[str, Any], drives: Sequence[Drive]) -> Filter:
    """The gated EKF with the loader's values."""
    filt = build_filter(cfg, drives, "receiver", torch.zeros(0), learned=False)
    assign_parameters(filt, {k: float(v) for k, v in dict(cfg["hand_tuned"]).items() if k in DYNAMICS})
    return filt
