"""Planar walking tracks made of straight lines, circular arcs and corner turns.

A track is a chain of segments, each entered after an optional instantaneous turn (a corner
node), in the azimuth convention used by :mod:`experiments.papers.p002.model`: heading ``psi`` measured
from north, clockwise positive (east = +pi/2), so a unit step moves ``(dE, dN) = (sin psi,
cos psi)``.  An arc of signed curvature ``kappa = dpsi/ds`` (``> 0`` turns right) has the closed
form

.. math::
    psi(d) = psi_0 + kappa d, \\quad
    E(d) = E_0 + (\\cos psi_0 - \\cos psi(d)) / kappa, \\quad
    N(d) = N_0 + (\\sin psi(d) - \\sin psi_0) / kappa.

Headings are *unwrapped* (cumulative): a closed loop of four right turns ends at ``psi_0 +
2 pi``.  Beyond its end a track continues straight along its final heading, so a walker that
takes a few more steps than the nominal length stays well defined.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

__all__ = ["Track", "TrackSegment", "p002_track"]


@dataclass(frozen=True)
class TrackSegment:
    """One piece of a track.

    Attributes:
        length: arc length of the piece (m), ``>= 0``.
        curvature: signed curvature ``dpsi/ds`` (1/m), ``0`` for a straight line, ``+1/r`` for a
            right (clockwise) arc of radius ``r``, ``-1/r`` for a left arc.
        turn: instantaneous heading change (rad, clockwise positive) applied at the segment's
            start, i.e. a corner node.
        name: label of the node at the segment's start (``""`` if none).
    """

    length: float
    curvature: float = 0.0
    turn: float = 0.0
    name: str = ""


@dataclass
class Track:
    """A chain of :class:`TrackSegment` starting at ``start`` with heading ``start_heading``.

    The segment table (start arc length, start point and start heading of every piece) is
    computed once in double precision; :meth:`sample` evaluates any batch of arc lengths.
    """

    segments: tuple[TrackSegment, ...]
    start: tuple[float, float] = (0.0, 0.0)
    start_heading: float = 0.0
    _table: list[tuple[float, float, float, float, float]] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.segments:
            raise ValueError("a track needs at least one segment")
        table = []
        s, e, n, psi = 0.0, float(self.start[0]), float(self.start[1]), float(self.start_heading)
        for seg in self.segments:
            if seg.length < 0:
                raise ValueError(f"segment lengths must be >= 0, got {seg.length}")
            psi += seg.turn
            table.append((s, e, n, psi, seg.curvature))
            e, n, psi = _advance(e, n, psi, seg.curvature, seg.length)
            s += seg.length
        # Continue straight after the end (see module docstring).
        table.append((s, e, n, psi, 0.0))
        self._table = table

    @property
    def length(self) -> float:
        """Total arc length (m)."""
        return float(sum(seg.length for seg in self.segments))

    @property
    def end(self) -> tuple[float, float, float]:
        """``(E, N, psi)`` at the end of the last segment."""
        _, e, n, psi, _ = self._table[-1]
        return e, n, psi

    def nodes(self) -> dict[str, tuple[float, float]]:
        """Positions ``(E, N)`` of the named corner nodes."""
        return {seg.name: (row[1], row[2]) for seg, row in zip(self.segments, self._table[:-1], strict=True) if seg.name}

    def sample(self, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """East, north and unwrapped heading at arc lengths ``s [...]`` (any shape, s >= 0).

        Returns three tensors shaped like ``s`` (and of its dtype).  At a corner node the
        heading after the turn is returned.
        """
        kw = {"dtype": s.dtype, "device": s.device}
        starts = torch.tensor([r[0] for r in self._table], **kw)
        e0 = torch.tensor([r[1] for r in self._table], **kw)
        n0 = torch.tensor([r[2] for r in self._table], **kw)
        psi0 = torch.tensor([r[3] for r in self._table], **kw)
        kappa = torch.tensor([r[4] for r in self._table], **kw)
        idx = (torch.searchsorted(starts, s.contiguous(), right=True) - 1).clamp(0, len(self._table) - 1)
        d = s - starts[idx]
        k, p0 = kappa[idx], psi0[idx]
        psi = p0 + k * d
        straight = k == 0
        # The arc formula divides by kappa; the straight-line branch is selected where kappa = 0.
        k_safe = torch.where(straight, torch.ones_like(k), k)
        de = torch.where(straight, d * torch.sin(p0), (torch.cos(p0) - torch.cos(psi)) / k_safe)
        dn = torch.where(straight, d * torch.cos(p0), (torch.sin(psi) - torch.sin(p0)) / k_safe)
        return e0[idx] + de, n0[idx] + dn, psi


def _advance(e: float, n: float, psi: float, kappa: float, d: float) -> tuple[float, float, float]:
    if kappa == 0.0:
        return e + d * math.sin(psi), n + d * math.cos(psi), psi
    psi1 = psi + kappa * d
    return e + (math.cos(psi) - math.cos(psi1)) / kappa, n + (math.sin(psi1) - math.sin(psi)) / kappa, psi1


def p002_track() -> Track:
    """The 360 m test path of p002 (Niu & Lian 2017, section 3.1), rebuilt to be consistent.

    The paper gives only the lengths: straight long side 110 m, short side 70 m, a curved
    section of 90 m with radius 37 m, right-angle turns at nodes A, B, C, D, total 360 m.  These
    leave 90 m of straight walking unassigned; we split it into the two remaining sides so that
    the path almost closes:

    ``S (0, 0)`` north 45.5 m to ``A`` -> right turn, east 110 m (long side) to ``B`` -> right
    turn, south 70 m (short side) to ``C`` -> right turn, west 44.5 m to ``D`` -> right turn,
    then a 90 m left arc of radius 37 m (139.4 deg) that ends 0.59 m from ``S``.

    Total length ``45.5 + 110 + 70 + 44.5 + 90 = 360 m``; start heading 0 (north).
    """
    right = math.pi / 2
    return Track(
        segments=(
            TrackSegment(45.5, name="S"),
            TrackSegment(110.0, turn=right, name="A"),
            TrackSegment(70.0, turn=right, name="B"),
            TrackSegment(44.5, turn=right, name="C"),
            TrackSegment(90.0, curvature=-1.0 / 37.0, turn=right, name="D"),
        ),
    )
