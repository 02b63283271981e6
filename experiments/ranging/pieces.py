"""Pieces of ranging recordings and how the protocol (:mod:`.protocol`) starts a trajectory on one:
the model of a recording's kind and its state layout, the snapshot multilateration fix, the
reference heading (recordings with odometry) or velocity (3-D without odometry), and the start
position variance estimated on the train pieces."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from difffilter.datasets.ranging import RangingRecording
from difffilter.models.layout import StateLayout, model_defaults
from difffilter.models.navigation.ranging2d import make_ranging_model, multilateration
from difffilter.models.navigation.ranging3d import make_ranging3d_model

__all__ = ["CHI2_2_95", "CHI2_3_95", "Piece", "ranging_model", "start_belief", "start_position_variance", "state_layout"]


def ranging_model(rec: RangingRecording, **kwargs: Any) -> torch.nn.Module:
    """The range model of ``rec``'s kind: :func:`~difffilter.models.navigation.make_ranging_model`
    (2-D) or :func:`~difffilter.models.navigation.make_ranging3d_model` (3-D, with odometry when
    the recording has it); ``kwargs`` go to it."""
    if rec.dim == 2:
        return make_ranging_model(num_anchors=rec.num_anchors, **kwargs)
    return make_ranging3d_model(num_anchors=rec.num_anchors, odometry=rec.odometry, **kwargs)


def state_layout(rec: RangingRecording) -> StateLayout:
    """The state layout of :func:`ranging_model`'s model for ``rec`` (its ``defaults.layout``:
    which state components are the position, the heading, the velocity)."""
    defaults = model_defaults(ranging_model(rec, gate=None))
    if defaults is None:  # pragma: no cover - both factories describe their models
        raise ValueError(f"the range model of {rec.name} carries no state layout (model.defaults)")
    return defaults.layout


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


def start_belief(
    rec: RangingRecording, k: int, fix: Tensor, pos_var: float = 4.0, layout: StateLayout | None = None
) -> tuple[Tensor, Tensor]:
    """Initial mean ``[n]`` and covariance ``[n, n]`` at step ``k`` in the state layout of the
    recording's model (``layout``; default :func:`state_layout`): the snapshot fix at the position
    indices (``pos_var`` m^2 per axis) and, from the reference, the heading at the angle index
    (0.01 rad^2; recordings with odometry) or the velocity at the components named ``v<axis>``
    (0.25 m^2/s^2; 3-D without odometry).  2-D ``[x, y, heading]``; 3-D ``[x, y, z, heading]``
    or ``[x, v_x, y, v_y, z, v_z]``."""
    layout = state_layout(rec) if layout is None else layout
    pos = list(layout.position)
    if len(pos) != rec.dim:
        raise ValueError(f"layout has {len(pos)} position components, the recording {rec.name} is {rec.dim}-D")
    m = torch.zeros(layout.dim, dtype=torch.float64)
    var = torch.zeros(layout.dim, dtype=torch.float64)
    m[pos], var[pos] = fix[k, : rec.dim].to(torch.float64), float(pos_var)
    if rec.odometry:
        if len(layout.angles) != 1:
            raise ValueError(f"a recording with odometry needs one heading in the layout, got angles {list(layout.angles)}")
        m[layout.angles[0]], var[layout.angles[0]] = _heading(rec, k), 0.01
    else:
        vel = layout.index(*(f"v{layout.names[i]}" for i in pos))
        m[vel], var[vel] = torch.tensor(_velocity(rec, k), dtype=torch.float64), 0.25
    if not bool((var > 0).all()):
        raise ValueError(f"the start belief leaves state components {[layout.names[i] for i in range(layout.dim) if var[i] <= 0]} unset")
    return m, torch.diag(var)


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
