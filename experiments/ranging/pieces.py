"""Pieces of ranging recordings and how the protocol (:mod:`.protocol`) starts a trajectory on one:
the snapshot multilateration fix, the reference heading (recordings with odometry) or velocity
(3-D without odometry), and the start position variance estimated on the train pieces."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from difffilter.datasets.ranging import RangingRecording
from difffilter.models.navigation.ranging2d import multilateration

__all__ = ["CHI2_2_95", "CHI2_3_95", "Piece", "start_belief", "start_position_variance"]


@dataclass(frozen=True)
class Piece:
    """Steps ``[first, stop)`` of a recording."""

    recording: RangingRecording
    first: int
    stop: int


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
    """Reference heading at step ``k``: the truth file's ``angle`` record, else the direction of
    the reference motion over the next step minus the direction of the body-frame odometry
    velocity that produced it (a robot may drive backwards or sideways in its body frame)."""
    if rec.heading is not None and math.isfinite(float(rec.heading[k])):
        return float(rec.heading[k])
    if k == 0 and rec.heading0 is not None:
        return rec.heading0
    t = rec.truth
    for j in range(k, min(k + 20, rec.num_steps - 1)):
        d = t[j + 1, :2] - t[j, :2]
        v = rec.odom[j + 1, :2]
        if np.all(np.isfinite(d)) and np.hypot(*d) > 1e-6 and np.hypot(*v) > 1e-6:
            return float(np.arctan2(d[1], d[0]) - np.arctan2(v[1], v[0]))
    return 0.0


def _velocity(rec: RangingRecording, k: int) -> list[float]:
    """Reference velocity at step ``k`` (the motion to the next step with a reference; 0 without one)."""
    t = rec.truth
    for j in range(k, min(k + 20, rec.num_steps - 1)):
        dt = float(rec.times[j + 1] - rec.times[j])
        if np.all(np.isfinite(t[j : j + 2])) and dt > 0:
            return [float(v) for v in (t[j + 1] - t[j]) / dt]
    return [0.0] * rec.dim


def start_belief(rec: RangingRecording, k: int, fix: Tensor, pos_var: float = 4.0) -> tuple[Tensor, Tensor]:
    """Initial mean and covariance at step ``k``: the snapshot fix (``pos_var`` m^2 per position
    axis) and, from the reference, the heading (0.01 rad^2; recordings with odometry) or the
    velocity (0.25 m^2/s^2; 3-D without odometry).  2-D ``[3]``: ``[x, y, heading]``; 3-D
    ``[4]`` ``[x, y, z, heading]`` or ``[6]`` ``[x, y, z, v_x, v_y, v_z]``."""
    pos = [float(v) for v in fix[k, : rec.dim]]
    extra, var = ([_heading(rec, k)], [0.01]) if rec.odometry else (_velocity(rec, k), [0.25] * rec.dim)
    m = torch.tensor(pos + extra, dtype=torch.float64)
    return m, torch.diag(torch.tensor([float(pos_var)] * rec.dim + var, dtype=torch.float64))


#: chi-square quantile, 2 degrees of freedom, 0.95: a 2-D Gaussian N(0, s^2 I) puts 95 % of its
#: mass within radius sqrt(CHI2_2_95) s.
CHI2_2_95 = -2.0 * math.log(0.05)
#: the same for 3 degrees of freedom (a 3-D Gaussian's 95 % sphere).
CHI2_3_95 = 7.814727903251178


def _fix(r: RangingRecording) -> Tensor:
    t64 = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64)  # noqa: E731
    return _hold(multilateration(t64(r.ranges), t64(r.range_var), torch.as_tensor(r.mask), t64(r.anchors)))


def start_position_variance(pieces: Sequence[Piece], *, floor: float = 0.25) -> float:
    """Start variance (m^2 per axis) from the snapshot fixes' errors on ``pieces`` (the train
    pieces: the reference is used where training may use it): ``q95(|error|)^2 / CHI2_2_95``,
    the isotropic Gaussian whose 95 % circle is the fixes' 95th percentile error (a mean square
    would follow the rare catastrophic fixes instead of the typical start), at least ``floor``."""
    errs = []
    for p in pieces:
        r = p.recording
        e = (_fix(r)[p.first : p.stop] - torch.as_tensor(r.truth[p.first : p.stop])).norm(dim=-1)
        errs.append(e[torch.isfinite(e)])
    e = torch.cat(errs)
    if not len(e):
        raise ValueError("the train pieces hold no step with a reference position: no start variance")
    chi2 = CHI2_2_95 if pieces[0].recording.dim == 2 else CHI2_3_95
    return max(float(floor), float(torch.quantile(e, 0.95)) ** 2 / chi2)
