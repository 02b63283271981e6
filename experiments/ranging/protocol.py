"""The real-data protocol for ranging recordings (libRSF format: ``range2`` + odometry, or
``range3`` with ``odom3`` or without odometry): folds, training of the sensor extras, selection on
validation, test rows with paired intervals.  The model is :func:`ranging_model`'s (2-D: position
and heading; 3-D: position and heading with odometry, position and velocity without).

For one fold (train / validation / test pieces, each a recording and a span of its steps):

1. every trajectory the protocol runs (training window, validation piece, test piece) starts at
   the snapshot multilateration fix of its first step (heading from the reference, which
   odometry and ranges alone do not give; every filter gets the same start) with a position
   variance estimated on the **train pieces only** (:func:`start_position_variance`: the
   Gaussian whose 95 % circle matches the 95th percentile of the fixes' errors there);
2. the learned filter is a :class:`~difffilter.filters.GatedEKF` on the model of
   :func:`~difffilter.models.navigation.make_ranging_model`: per anchor range bias, per anchor
   noise scale on the file's variances, odometry scale, process noise, and a smooth learnable
   reject gate on the **normalised innovation** ``|e_j| / sqrt((H P- H^T + R)_jj)``, **all
   learned jointly**; ``seeds`` replicates start from seeded perturbations of the untrained
   values and minimise the mean + RMS position error against the reference on the training
   windows after ``burn_in`` steps (``loss: score``; ``mse``: the squared error) - a loss that
   does not reward a wide gate for its own sake (a gate that lets outliers in moves the
   position), and the smooth counterpart of the validation score;
3. after every epoch the validation pieces (each run whole, warm-started by a lead-in of
   ``eval_lead_in`` unscored steps of the data before it: :func:`eval_tensors`) are scored by
   median + RMS position error over their steps after ``eval_burn_in`` (the start transient of a
   piece is not scored, in validation and in test alike); the filter used on test is the lowest-scoring of every
   (seed, epoch), **the untrained gated filter and the hand-tuned filter**
   (:func:`select_candidate`), so the selection is never worse than either on validation;
4. test rows over the same scored steps: ``hand-tuned`` (the file's variances, no bias, no
   gate), ``learned``, ``untrained-gate`` (the gated filter at its start),
   ``hand-tuned-hard-gate`` (the textbook hard gate on the normalised innovation at the gate's
   threshold), ``snapshot-lsq`` (per-step weighted least-squares multilateration) and every
   factory of :data:`EXTRA_BASELINES` (Sage-Husa and VB adaptive-R filters; the hook for EM),
   with paired block-bootstrap intervals of each row minus hand-tuned and minus the untrained
   gate.
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
from difffilter.filters import EKF, GatedEKF, SageHusa, VBAdaptiveR
from difffilter.models.heteroscedastic import RobustGate
from difffilter.models.navigation.ranging2d import make_ranging_model
from experiments.holdout import error_statistics, paired_error_table

from .pieces import Piece, _fix, ranging_model, start_belief, start_position_variance, state_layout

__all__ = [
    "EXTRA_BASELINES",
    "Piece",
    "ProtocolResult",
    "eval_tensors",
    "fold_pieces",
    "lead_in_start",
    "piece_tensors",
    "ranging_model",
    "run_fold",
    "select_candidate",
    "start_belief",
    "start_position_variance",
    "state_layout",
    "summary_statistics",
]


#: ``{row name: factory(recording) -> filter}``: further baselines evaluated on every test piece.
#: The adaptive filters estimate ``R`` on line from the innovations, started at the file's
#: variances (untrained hyperparameters, the docs' defaults).  No EM-tuned row: ``fit_em`` refuses
#: control-dependent noise, which this model's ``R`` and ``Q`` are.
EXTRA_BASELINES: dict[str, Callable[[RangingRecording], torch.nn.Module]] = {
    "sage-husa": lambda rec: SageHusa(EKF(ranging_model(rec, bias=None, noise=None, gate=None))),
    "vb-adaptive-r": lambda rec: VBAdaptiveR(EKF(ranging_model(rec, bias=None, noise=None, gate=None))),
}


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


def piece_tensors(piece: Piece, *, length: int | None = None, stride: int | None = None, pos_var: float = 4.0) -> dict[str, Any]:
    """Batch-first tensors of a piece cut into windows (``length=None``: one trajectory), each
    started by :func:`start_belief` with ``pos_var``; ``"position"`` holds the position indices
    of the model's state (:func:`state_layout`), which the errors are taken on."""
    r = piece.recording
    t64 = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64)  # noqa: E731
    size = piece.stop - piece.first if length is None else int(length)
    starts = list(range(piece.first, piece.stop - size + 1, size if stride is None else int(stride)))
    if not starts:
        raise ValueError(f"piece [{piece.first}, {piece.stop}) of {r.name} holds no window of {size} steps")
    fix = _fix(r)
    layout = state_layout(r)
    cut = lambda a: torch.stack([a[s : s + size] for s in starts])  # noqa: E731
    u = {"odom": cut(t64(r.odom)), "odom_cov": cut(t64(r.odom_cov)), "dt": cut(t64(r.dt))[..., None]}
    u.update(anchors=cut(t64(r.anchors)), range_var=cut(t64(r.range_var)), z_obs=cut(t64(r.ranges)))
    u["dt"][:, 0] = 0.0  # the window starts at its first step's belief
    beliefs = [start_belief(r, s, fix, pos_var, layout) for s in starts]
    return {
        "z": cut(t64(r.ranges)),
        "mask": cut(torch.as_tensor(r.mask)),
        "u": u,
        "m0": torch.stack([b[0] for b in beliefs]),
        "P0": torch.stack([b[1] for b in beliefs]),
        "truth": cut(t64(r.truth)),
        "fix": cut(fix),
        "position": list(layout.position),
    }


def lead_in_start(piece: Piece, lead_in: int | None, avoid: Sequence[Piece] = ()) -> int:
    """First step of the trajectory that warm-starts ``piece``: ``lead_in`` steps before it
    (``None``: the recording's step 0), never before step 0 and never inside a piece of ``avoid``
    of the same recording that ends at or before the piece's start (a validation piece never
    runs over test steps)."""
    if lead_in is not None and int(lead_in) < 0:
        raise ValueError(f"eval_lead_in must be None or >= 0, got {lead_in}")
    lo = 0 if lead_in is None else max(0, piece.first - int(lead_in))
    for q in avoid:
        if q.recording is piece.recording and q.first < piece.first:
            lo = max(lo, min(q.stop, piece.first))
    return lo


def eval_tensors(piece: Piece, *, pos_var: float, lead_in: int | None = 0, avoid: Sequence[Piece] = ()) -> dict[str, Any]:
    """One trajectory for scoring ``piece``, warm-started: it starts (:func:`start_belief`) at
    :func:`lead_in_start` and runs through the lead-in into the piece; ``"skip"`` holds the
    number of lead-in steps, which :func:`_errors` never scores."""
    lo = lead_in_start(piece, lead_in, avoid)
    data = piece_tensors(Piece(piece.recording, lo, piece.stop), pos_var=pos_var)
    data["skip"] = piece.first - lo
    return data


def _scored(e: Tensor, truth: Tensor, burn_in: int) -> Tensor:
    """Errors ``[B, T]`` of the steps after ``burn_in`` that have a reference, flattened."""
    ok = torch.isfinite(truth).all(-1)
    return e[:, burn_in:][ok[:, burn_in:]].reshape(-1)


def _errors(filt: torch.nn.Module, data: Mapping[str, Any], burn_in: int = 0) -> Tensor:
    """Scored errors of ``filt`` on ``data``: the steps after its lead-in (``data["skip"]``) and
    then ``burn_in`` more."""
    with torch.no_grad():
        res = filt(data["z"], data["m0"], data["P0"], mask=data["mask"], controls=data["u"])
    return _scored((res.mean[..., data["position"]] - data["truth"]).norm(dim=-1), data["truth"], int(data.get("skip", 0)) + burn_in)


def _score(filt: torch.nn.Module, val: Sequence[Mapping[str, Any]], burn_in: int = 0) -> float:
    e = torch.cat([_errors(filt, d, burn_in) for d in val])
    if not len(e) or not bool(torch.isfinite(e).all()):
        return math.inf
    return float(e.median() + e.pow(2).mean().sqrt())


def select_candidate(scores: Sequence[float]) -> int:
    """Index of the lowest validation score; non-finite scores never win, ties keep the earlier
    candidate.  The protocol lists the untrained start first and hand-tuned second, so the
    selection is never worse on validation than its start (and keeps the start unless a trained
    candidate is strictly better)."""
    if not len(scores):
        raise ValueError("scores must hold at least one candidate (the untrained start)")
    return min(range(len(scores)), key=lambda i: (scores[i] if math.isfinite(scores[i]) else math.inf, i))


def _filters(rec: RangingRecording | int, cfg: Mapping[str, Any]) -> dict[str, torch.nn.Module]:
    """The non-learned rows and the untrained gated filter of ``rec``'s kind (an ``int``: a 2-D
    recording with that many anchors)."""
    g = dict(cfg["gate"])
    if isinstance(rec, int):
        num = rec
        model = lambda **kw: make_ranging_model(num_anchors=num, **kw)  # noqa: E731
    else:
        model = lambda **kw: ranging_model(rec, **kw)  # type: ignore[arg-type]  # noqa: E731
    soft = RobustGate(
        kind="reject", threshold=float(g["threshold"]), floor=float(g["floor"]), softness=float(g["softness"]), learnable=True
    )
    return {
        "hand-tuned": EKF(model(bias=None, noise=None, gate=None)),
        "hand-tuned-hard-gate": GatedEKF(
            model(bias=None, noise=None, gate=None),
            gate=RobustGate(kind="reject", threshold=float(g["threshold"]), floor=float(g["floor"])),
        ),
        "untrained-gate": GatedEKF(model(bias=cfg["bias"], noise=cfg["noise"], gate=None), gate=soft),
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
    eval_burn = int(cfg.get("eval_burn_in", 0))
    scores, snaps = [_score(filt, val, eval_burn)], [copy.deepcopy(filt.state_dict())]
    for epoch in range(int(cfg["epochs"])):
        order = torch.randperm(n, generator=gen)
        total = 0.0
        for chunk in order.chunk(batches):
            u = {k: v[chunk] for k, v in train["u"].items()}
            res = filt(train["z"][chunk], train["m0"][chunk], train["P0"][chunk], mask=train["mask"][chunk], controls=u)
            sq = (res.mean[:, burn:, train["position"]] - train["truth"][chunk, burn:]).pow(2).sum(-1)
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
        scores.append(_score(filt, val, eval_burn))
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
    ``lr``, ``batches``, ``burn_in``, ``eval_burn_in`` (steps of each validation and test piece
    not scored; default 0), ``eval_lead_in`` (unscored steps of the preceding data each validation
    and test piece is run from, a warm start; ``None``: from step 0; default 0: a cold start; a
    validation piece's lead-in never enters a test piece), ``init_perturbation``, ``loss`` (``score`` or ``mse``),
    ``bootstrap`` {block, draws, seed}."""
    t0 = time.time()
    num_a = {p.recording.num_anchors for ps in pieces.values() for p in ps}
    if len(num_a) != 1:
        raise ValueError(f"the recordings of one fold must have the same anchors, got counts {sorted(num_a)}")
    kinds = {(p.recording.dim, p.recording.odometry) for ps in pieces.values() for p in ps}
    if len(kinds) != 1:
        raise ValueError(f"the recordings of one fold must be of one kind, got (dimension, odometry) {sorted(kinds)}")
    rep = pieces["train"][0].recording
    win = dict(cfg["windows"])
    burn = int(cfg.get("eval_burn_in", 0))
    for p in (*pieces["val"], *pieces["test"]):
        if p.stop - p.first <= burn:
            raise ValueError(f"eval_burn_in={burn} leaves no scored step of piece [{p.first}, {p.stop}) of {p.recording.name}")
    pos_var = start_position_variance(pieces["train"])
    parts = [piece_tensors(p, length=int(win["length"]), stride=int(win["stride"]), pos_var=pos_var) for p in pieces["train"]]
    train = {k: torch.cat([d[k] for d in parts]) for k in ("z", "mask", "m0", "P0", "truth")}
    train["u"] = {k: torch.cat([d["u"][k] for d in parts]) for k in parts[0]["u"]}
    train["position"] = parts[0]["position"]
    lead = cfg.get("eval_lead_in", 0)
    val = [eval_tensors(p, pos_var=pos_var, lead_in=lead, avoid=pieces["test"]) for p in pieces["val"]]
    base = _filters(rep, cfg)
    start = base["untrained-gate"]
    runs = [_train_seed(start, train, val, cfg, s, log) for s in range(int(cfg["seeds"]))]
    candidates = [
        ("untrained-gate", 0, _score(start, val, burn), start.state_dict()),
        ("hand-tuned", 0, _score(base["hand-tuned"], val, burn), None),
    ]
    for r in runs:
        candidates += [(f"seed{r['seed']}", e, s, sd) for e, (s, sd) in enumerate(zip(r["scores"], r["snapshots"], strict=True))]
    name, epoch, score, state = candidates[select_candidate([c[2] for c in candidates])]
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
        "start_pos_var": pos_var,
        "eval_burn_in": burn,
    }
    rows_f: dict[str, torch.nn.Module] = {
        "hand-tuned": base["hand-tuned"],
        "learned": learned,
        "untrained-gate": start,
        "hand-tuned-hard-gate": base["hand-tuned-hard-gate"],
    }
    errors: dict[str, list[Tensor]] = {}
    for p in pieces["test"]:
        data = eval_tensors(p, pos_var=pos_var, lead_in=lead)
        for row, f in rows_f.items():
            errors.setdefault(row, []).append(_errors(f, data, burn))
        for row, factory in EXTRA_BASELINES.items():
            errors.setdefault(row, []).append(_errors(factory(p.recording), data, burn))
        fix_err = (data["fix"] - data["truth"]).norm(dim=-1)
        errors.setdefault("snapshot-lsq", []).append(_scored(fix_err, data["truth"], int(data["skip"]) + burn))
    cat = {k: torch.cat(v) for k, v in errors.items()}
    boot = dict(cfg["bootstrap"])
    kw = {"block": int(boot["block"]), "draws": int(boot["draws"]), "seed": int(boot["seed"])}
    table = paired_error_table(cat, "hand-tuned", **kw)
    vs_start = {r["filter"]: r for r in paired_error_table(cat, "untrained-gate", **kw)}
    rows = []
    for r in table:
        row = {"filter": r.pop("filter"), "pos_err_p50": r.pop("median"), "rmse_pos": r.pop("rms"), "pos_err_p95": r.pop("p95"), **r}
        # the same resamples against the untrained gated filter (its own row has none)
        row.update({f"u_{k[2:]}": v for k, v in vs_start[row["filter"]].items() if k.startswith("d_")})
        rows.append(row)
    history = [{"seed": r["seed"], "scores": r["scores"]} for r in runs]
    return ProtocolResult(rows, selected, learned, start, history, cat, time.time() - t0)


def summary_statistics(errors: Tensor) -> dict[str, float]:
    """``pos_err_p50``, ``rmse_pos``, ``pos_err_p95`` of per-step errors ``[T]``."""
    s = error_statistics(errors)
    return {"pos_err_p50": s["median"], "rmse_pos": s["rms"], "pos_err_p95": s["p95"]}
