"""The real-data protocol for 2-D ranging recordings (``range2`` + odometry, libRSF format):
folds, training of the sensor extras, selection on validation, test rows with paired intervals.

For one fold (train / validation / test pieces, each a recording and a span of its steps):

1. training windows (``length`` steps every ``stride``) of the train pieces, each started from the
   snapshot multilateration fix of its first step (heading from the reference, which odometry and
   ranges alone do not give; every filter gets the same start);
2. the learned filter is the EKF of :func:`~difffilter.models.navigation.make_ranging_model`: per
   anchor range bias, per anchor noise scale on the file's variances, a smooth learnable reject
   gate, odometry scale and process noise, **all learned jointly**; ``seeds`` replicates start
   from seeded perturbations of the untrained values and minimise the mean + RMS position error
   against the reference on the training windows (``loss: score``; ``mse``: the squared error) -
   a loss that does not reward a wide gate (a gate that lets outliers in moves the position), and
   the smooth counterpart of the validation score;
3. after every epoch the validation pieces (each run whole) are scored by median + RMS position
   error; the filter used on test is the lowest-scoring of every (seed, epoch), **the untrained
   gated filter and the hand-tuned filter**, so the selection is never worse than either on
   validation;
4. test rows: ``hand-tuned`` (the file's variances, no bias, no gate), ``learned``,
   ``untrained-gate`` (the gated filter at its start), ``hand-tuned-hard-gate`` (a 3-sigma reject
   gate), ``snapshot-lsq`` (per-step weighted least-squares multilateration) and every factory of
   :data:`EXTRA_BASELINES` (Sage-Husa and VB adaptive-R filters; the hook for EM), with paired block-bootstrap
   intervals of each row minus hand-tuned.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from difffilter.datasets.ranging import RangingRecording
from difffilter.filters import EKF, SageHusa, VBAdaptiveR
from difffilter.models.navigation.ranging2d import make_ranging_model, multilateration
from experiments.holdout import error_statistics, paired_error_table

__all__ = [
    "EXTRA_BASELINES",
    "Piece",
    "ProtocolResult",
    "fold_pieces",
    "piece_tensors",
    "run_fold",
    "start_belief",
    "summary_statistics",
]

#: ``{row name: factory(recording) -> filter}``: further baselines evaluated on every test piece.
#: The adaptive filters estimate ``R`` on line from the innovations, started at the file's
#: variances (untrained hyperparameters, the docs' defaults).  No EM-tuned row: ``fit_em`` refuses
#: control-dependent noise, which this model's ``R`` and ``Q`` are.
EXTRA_BASELINES: dict[str, Callable[[RangingRecording], torch.nn.Module]] = {
    "sage-husa": lambda rec: SageHusa(EKF(make_ranging_model(num_anchors=rec.num_anchors, bias=None, noise=None, gate=None))),
    "vb-adaptive-r": lambda rec: VBAdaptiveR(EKF(make_ranging_model(num_anchors=rec.num_anchors, bias=None, noise=None, gate=None))),
}


@dataclass(frozen=True)
class Piece:
    """Steps ``[first, stop)`` of a recording."""

    recording: RangingRecording
    first: int
    stop: int


def fold_pieces(recordings: Sequence[RangingRecording], spec: Mapping[str, Any]) -> dict[str, list[Piece]]:
    """``{"train", "val", "test"}`` pieces of a fold: ``spec`` is either block fractions
    ``{train: [a, b], val: [c, d], test: [e, f]}`` applied to every recording, or a data-set
    fold ``{train_sets: [names], test_sets: [names], val_fraction: v}`` (the train sets' last
    ``v`` of steps validate, the test sets are tested whole)."""
    if "test_sets" in spec:
        byname = {r.name: r for r in recordings}
        v = float(spec.get("val_fraction", 0.2))
        train = [byname[n] for n in spec["train_sets"]]
        cut = lambda r: int(round(r.num_steps * (1 - v)))  # noqa: E731
        return {
            "train": [Piece(r, 0, cut(r)) for r in train],
            "val": [Piece(r, cut(r), r.num_steps) for r in train],
            "test": [Piece(byname[n], 0, byname[n].num_steps) for n in spec["test_sets"]],
        }
    out: dict[str, list[Piece]] = {}
    for role in ("train", "val", "test"):
        a, b = (float(x) for x in spec[role])
        out[role] = [Piece(r, int(round(a * r.num_steps)), int(round(b * r.num_steps))) for r in recordings]
    return out


def _hold(x: Tensor) -> Tensor:
    """NaN rows ``[T, 2]`` replaced by the previous finite row (the first finite one before it)."""
    ok = torch.isfinite(x).all(-1)
    if not bool(ok.any()):
        raise ValueError("no step with 3 or more ranges: the snapshot fix is undefined")
    idx = torch.arange(len(x))
    src = torch.where(ok, idx, torch.zeros_like(idx))
    src = torch.cummax(src, 0).values
    first = int(torch.nonzero(ok)[0])
    src = torch.where(idx < first, torch.full_like(idx, first), src)
    return x[src]


def _heading(rec: RangingRecording, k: int) -> float:
    if k == 0 and rec.heading0 is not None:
        return rec.heading0
    t = rec.truth
    for j in range(k, min(k + 20, rec.num_steps - 1)):
        d = t[j + 1] - t[j]
        if np.all(np.isfinite(d)) and np.hypot(*d) > 1e-6:
            return float(np.arctan2(d[1], d[0]))
    return 0.0


def start_belief(rec: RangingRecording, k: int, fix: Tensor) -> tuple[Tensor, Tensor]:
    """Initial mean ``[3]`` (snapshot fix at step ``k``, reference heading) and covariance ``[3, 3]``."""
    m = torch.tensor([float(fix[k, 0]), float(fix[k, 1]), _heading(rec, k)], dtype=torch.float64)
    return m, torch.diag(torch.tensor([4.0, 4.0, 0.01], dtype=torch.float64))


def piece_tensors(piece: Piece, *, length: int | None = None, stride: int | None = None) -> dict[str, Any]:
    """Batch-first tensors of a piece cut into windows (``length=None``: one trajectory)."""
    r = piece.recording
    t64 = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64)  # noqa: E731
    size = piece.stop - piece.first if length is None else int(length)
    starts = list(range(piece.first, piece.stop - size + 1, size if stride is None else int(stride)))
    if not starts:
        raise ValueError(f"piece [{piece.first}, {piece.stop}) of {r.name} holds no window of {size} steps")
    fix = _hold(multilateration(t64(r.ranges), t64(r.range_var), torch.as_tensor(r.mask), t64(r.anchors)))
    cut = lambda a: torch.stack([a[s : s + size] for s in starts])  # noqa: E731
    u = {"odom": cut(t64(r.odom)), "odom_cov": cut(t64(r.odom_cov)), "dt": cut(t64(r.dt))[..., None]}
    u.update(anchors=cut(t64(r.anchors)), range_var=cut(t64(r.range_var)), z_obs=cut(t64(r.ranges)))
    u["dt"][:, 0] = 0.0  # the window starts at its first step's belief
    beliefs = [start_belief(r, s, fix) for s in starts]
    return {
        "z": cut(t64(r.ranges)),
        "mask": cut(torch.as_tensor(r.mask)),
        "u": u,
        "m0": torch.stack([b[0] for b in beliefs]),
        "P0": torch.stack([b[1] for b in beliefs]),
        "truth": cut(t64(r.truth)),
        "fix": cut(fix),
    }


def _errors(filt: torch.nn.Module, data: Mapping[str, Any]) -> Tensor:
    with torch.no_grad():
        res = filt(data["z"], data["m0"], data["P0"], mask=data["mask"], controls=data["u"])
    e = (res.mean[..., :2] - data["truth"]).norm(dim=-1)
    return e[torch.isfinite(data["truth"]).all(-1)].reshape(-1)


def _score(filt: torch.nn.Module, val: Sequence[Mapping[str, Any]]) -> float:
    e = torch.cat([_errors(filt, d) for d in val])
    if not bool(torch.isfinite(e).all()):
        return math.inf
    return float(e.median() + e.pow(2).mean().sqrt())


def _filters(num_anchors: int, cfg: Mapping[str, Any]) -> dict[str, torch.nn.Module]:
    g = dict(cfg["gate"])
    kw = {"num_anchors": num_anchors}
    return {
        "hand-tuned": EKF(make_ranging_model(**kw, bias=None, noise=None, gate=None)),
        "hand-tuned-hard-gate": EKF(
            make_ranging_model(**kw, bias=None, noise=None, gate="hard", gate_threshold=float(g["threshold"]), gate_floor=float(g["floor"]))
        ),
        "untrained-gate": EKF(
            make_ranging_model(
                **kw,
                bias=cfg["bias"],
                noise=cfg["noise"],
                gate="soft",
                gate_threshold=float(g["threshold"]),
                gate_floor=float(g["floor"]),
                gate_softness=float(g["softness"]),
            )
        ),
    }


@dataclass
class ProtocolResult:
    """One fold's outcome: the test table, the selection, the learned filter and the training record."""

    rows: list[dict[str, Any]]
    selected: dict[str, Any]
    learned: torch.nn.Module
    start: torch.nn.Module
    history: list[dict[str, Any]]
    errors: dict[str, Tensor]
    seconds: float


def _train_seed(
    start: torch.nn.Module,
    train: Mapping[str, Any],
    val: Sequence[Mapping[str, Any]],
    cfg: Mapping[str, Any],
    seed: int,
    log: Callable[[str, float, int], None] | None,
) -> dict[str, Any]:
    filt = copy.deepcopy(start)
    gen = torch.Generator().manual_seed(int(seed))
    with torch.no_grad():
        for p in filt.parameters():
            p.add_(float(cfg["init_perturbation"]) * torch.randn(p.shape, generator=gen, dtype=p.dtype))
    opt = torch.optim.Adam(filt.parameters(), lr=float(cfg["lr"]))
    burn = int(cfg["burn_in"])
    n = train["z"].shape[0]
    batches = max(1, int(cfg["batches"]))
    scores, snaps = [_score(filt, val)], [copy.deepcopy(filt.state_dict())]
    for epoch in range(int(cfg["epochs"])):
        order = torch.randperm(n, generator=gen)
        total = 0.0
        for chunk in order.chunk(batches):
            u = {k: v[chunk] for k, v in train["u"].items()}
            res = filt(train["z"][chunk], train["m0"][chunk], train["P0"][chunk], mask=train["mask"][chunk], controls=u)
            sq = (res.mean[:, burn:, :2] - train["truth"][chunk, burn:]).pow(2).sum(-1)
            ok = torch.isfinite(sq)
            sq = torch.where(ok, sq, torch.zeros_like(sq))
            count = ok.sum().clamp(min=1)
            mse = sq.sum() / count
            if cfg.get("loss", "score") == "mse":
                loss = mse
            else:  # mean error + RMS error: a smooth stand-in for the validation score (median + RMS)
                loss = torch.sqrt(sq + 1e-6).sum() / count + torch.sqrt(mse)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(filt.parameters(), 10.0)
            opt.step()
            total += float(loss.detach())
        scores.append(_score(filt, val))
        snaps.append(copy.deepcopy(filt.state_dict()))
        if log is not None:
            log(f"seed{seed}/train_loss", total / batches, epoch + 1)
            log(f"seed{seed}/val_score", scores[-1], epoch + 1)
    return {"seed": seed, "scores": scores, "snapshots": snaps}


def run_fold(
    pieces: Mapping[str, Sequence[Piece]], cfg: Mapping[str, Any], *, log: Callable[[str, float, int], None] | None = None
) -> ProtocolResult:
    """Train, select and test one fold (module docstring).  ``cfg`` keys: ``windows`` {length,
    stride}, ``gate`` {threshold, floor, softness}, ``bias``, ``noise``, ``seeds``, ``epochs``,
    ``lr``, ``batches``, ``burn_in``, ``init_perturbation``, ``loss`` (``score`` or ``mse``),
    ``bootstrap`` {block, draws, seed}."""
    t0 = time.time()
    num_a = {p.recording.num_anchors for ps in pieces.values() for p in ps}
    if len(num_a) != 1:
        raise ValueError(f"the recordings of one fold must have the same anchors, got counts {sorted(num_a)}")
    a = num_a.pop()
    win = dict(cfg["windows"])
    parts = [piece_tensors(p, length=int(win["length"]), stride=int(win["stride"])) for p in pieces["train"]]
    train = {k: torch.cat([d[k] for d in parts]) for k in ("z", "mask", "m0", "P0", "truth")}
    train["u"] = {k: torch.cat([d["u"][k] for d in parts]) for k in parts[0]["u"]}
    val = [piece_tensors(p) for p in pieces["val"]]
    base = _filters(a, cfg)
    start = base["untrained-gate"]
    runs = [_train_seed(start, train, val, cfg, s, log) for s in range(int(cfg["seeds"]))]
    candidates = [("untrained-gate", 0, _score(start, val), start.state_dict()), ("hand-tuned", 0, _score(base["hand-tuned"], val), None)]
    for r in runs:
        candidates += [(f"seed{r['seed']}", e, s, sd) for e, (s, sd) in enumerate(zip(r["scores"], r["snapshots"], strict=True))]
    # lowest score; ties keep the earlier candidate (the untrained start first, then hand-tuned)
    best = min(range(len(candidates)), key=lambda i: (candidates[i][2] if math.isfinite(candidates[i][2]) else math.inf, i))
    name, epoch, score, state = candidates[best]
    if state is None:
        learned = copy.deepcopy(base["hand-tuned"])
    else:
        learned = copy.deepcopy(start)
        learned.load_state_dict(state)
    selected = {
        "candidate": name,
        "epoch": epoch,
        "val_score": score,
        "val_untrained": candidates[0][2],
        "val_hand_tuned": candidates[1][2],
    }
    rows_f: dict[str, torch.nn.Module] = {
        "hand-tuned": base["hand-tuned"],
        "learned": learned,
        "untrained-gate": start,
        "hand-tuned-hard-gate": base["hand-tuned-hard-gate"],
    }
    errors: dict[str, list[Tensor]] = {}
    for p in pieces["test"]:
        data = piece_tensors(p)
        for row, f in rows_f.items():
            errors.setdefault(row, []).append(_errors(f, data))
        for row, factory in EXTRA_BASELINES.items():
            errors.setdefault(row, []).append(_errors(factory(p.recording), data))
        fixe = (data["fix"] - data["truth"]).norm(dim=-1)
        errors.setdefault("snapshot-lsq", []).append(fixe[torch.isfinite(data["truth"]).all(-1)].reshape(-1))
    cat = {k: torch.cat(v) for k, v in errors.items()}
    boot = dict(cfg["bootstrap"])
    table = paired_error_table(cat, "hand-tuned", block=int(boot["block"]), draws=int(boot["draws"]), seed=int(boot["seed"]))
    rows = []
    for r in table:
        row = {"filter": r.pop("filter"), "pos_err_p50": r.pop("median"), "rmse_pos": r.pop("rms"), "pos_err_p95": r.pop("p95"), **r}
        rows.append(row)
    history = [{"seed": r["seed"], "scores": r["scores"]} for r in runs]
    return ProtocolResult(rows, selected, learned, start, history, cat, time.time() - t0)


def summary_statistics(errors: Tensor) -> dict[str, float]:
    """``pos_err_p50``, ``rmse_pos``, ``pos_err_p95`` of per-step errors ``[T]``."""
    s = error_statistics(errors)
    return {"pos_err_p50": s["median"], "rmse_pos": s["rms"], "pos_err_p95": s["p95"]}
