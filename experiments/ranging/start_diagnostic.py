"""Start transients of the ranging filters on a fold's **training** block only (the reference is
used where training may use it): median position error by steps since a window's start, for the
untrained filters, with the start heading of the previous protocol (direction of the reference
motion) and of the current one (the truth file's angle), and with the gate on ``R + floor^2``
(the previous untrained gate) and on the normalised innovation (:class:`~difffilter.filters.GatedEKF`).

    python -m experiments.ranging.start_diagnostic            # W3500 sets, fold A's training block

What ``results/librsf_w3500_predeclaration.md`` and the reading of ``results/librsf_w3500.md`` refer to.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import yaml

from difffilter.datasets import find_recordings, load_ranging, locate
from difffilter.filters import EKF
from difffilter.models.navigation import make_ranging_model

from .protocol import _filters, fold_pieces, piece_tensors, start_position_variance

__all__ = ["main"]

ROOT = Path(__file__).resolve().parents[2]
BINS = ((0, 5), (5, 10), (10, 20), (20, 40), (40, 80), (80, 200))


def _motion_heading(truth: np.ndarray, k: int) -> float:
    d = truth[k + 1] - truth[k]
    return float(np.arctan2(d[1], d[0]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--fold", default="A")
    ap.add_argument("--window", type=int, default=200)
    args = ap.parse_args()
    torch.set_num_threads(1)
    cfg = yaml.safe_load((ROOT / "conf" / "realdata_ranging" / "default.yaml").read_text())
    old_gate = {"gate": "soft", "gate_threshold": 3.0, "gate_floor": 3.0, "gate_softness": 0.5}
    print(f"median position error (m) by steps since the start {list(BINS)}; fold {args.fold} training block")
    for name, inp, gt in find_recordings(locate("librsf_w3500_skewed")):
        rec = load_ranging(inp, gt)
        train = fold_pieces([rec], cfg["folds"][args.fold])["train"]
        pos_var = start_position_variance(train)
        data = piece_tensors(train[0], length=args.window, stride=args.window, pos_var=pos_var)
        starts = range(train[0].first, train[0].stop - args.window + 1, args.window)
        motion = data["m0"].clone()
        motion[:, 2] = torch.tensor([_motion_heading(rec.truth, k) for k in starts], dtype=motion.dtype)
        rows = {
            "R-only gate (previous untrained)": EKF(make_ranging_model(num_anchors=rec.num_anchors, **old_gate)),  # type: ignore[arg-type]
            "innovation gate (current untrained)": _filters(rec.num_anchors, cfg)["untrained-gate"],
            "hand-tuned (no gate)": _filters(rec.num_anchors, cfg)["hand-tuned"],
        }
        for heading, m0 in (("motion heading (previous)", motion), ("angle record (current)", data["m0"])):
            for row, filt in rows.items():
                with torch.no_grad():
                    res = filt(data["z"], m0, data["P0"], mask=data["mask"], controls=data["u"])
                e = (res.mean[..., data["position"]] - data["truth"]).norm(dim=-1)
                prof = " ".join(f"{float(e[:, a:b].median()):6.2f}" for a, b in BINS)
                print(f"{name:20s} {heading:26s} {row:36s} {prof}", flush=True)


if __name__ == "__main__":
    main()
