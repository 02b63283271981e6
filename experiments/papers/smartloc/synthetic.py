"""Synthetic pseudoranges on the smartLoc drive's geometry (training data for ``smartloc_sim``).

The real drive (:mod:`experiments.papers.smartloc.data`) is one trajectory, so learning on it means
learning on windows of one 165 s stretch.  This module makes as many *semi-synthetic* drives as
wanted from a segment of it: the geometry is real (reference track, satellite positions and
visibility, the receiver's reported variances, the car's odometry with its real errors), while
the receiver clock and the pseudorange errors are drawn from an explicit error model:

* line-of-sight error of slot ``j`` at epoch ``k``: ``los_scale * sqrt(pr_var_kj) * a_kj`` with
  ``a`` a unit-variance AR(1) process, ``a_k = psi a_{k-1} + sqrt(1 - psi^2) w_k`` (multipath is
  correlated in time);
* non-line-of-sight episodes: a two-state Markov chain per slot that leaves an episode with
  probability ``nlos_leave`` per epoch and enters one with the probability that makes its share
  of epochs ``nlos_share[c]``, ``c`` the bin of the range's real C/N0 (``cn0_edges``; on this
  drive the share falls from ~0.7 below 30 dB-Hz to ~0.15 above 40 dB-Hz, so the canyon
  stretches of the real drive stay hard in the synthetic ones); an episode adds one bias, drawn
  at its start, of sign ``+`` with probability ``nlos_positive`` and magnitude resampled from
  ``nlos_magnitudes`` (reflected signals travel further, so most biases are positive);
* clock: bias and drift random walks with PSDs ``clock_bias_psd`` / ``clock_drift_psd``
  (``b' = d + w_b``, ``d' = w_d``) started at ``clock_drift0`` m/s; a constant GLONASS
  inter-system bias ``N(0, isb_sigma^2)`` per drive.

:func:`calibrate_error_model` estimates the model's numbers from a segment of the real drive
with the reference track (moment estimates; see its docstring), so a simulator calibrated on the
training part of the drive uses nothing from the held-out part.  The measurement function is the
filter's own (:func:`~experiments.papers.smartloc.model.make_smartloc_model`: Sagnac term, reduced
pseudoranges), so the synthetic ranges differ from the real ones only by their errors and clock.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from .data import SmartLocBatch, SmartLocData
from .model import make_smartloc_model

__all__ = ["PseudorangeErrorModel", "calibrate_error_model", "simulate_smartloc_drives", "synthetic_drive"]


@dataclass
class PseudorangeErrorModel:
    """Numbers of the synthetic error model (see the module docstring); per epoch of 0.2 s."""

    los_scale: float = 1.0
    psi: float = 0.9
    nlos_leave: float = 0.15
    cn0_edges: tuple[float, ...] = (25.0, 30.0, 35.0, 40.0)
    nlos_share: tuple[float, ...] = (0.7, 0.6, 0.45, 0.25, 0.15)
    nlos_positive: float = 0.8
    nlos_magnitudes: Tensor = field(default_factory=lambda: torch.tensor([45.0], dtype=torch.float64))
    clock_bias_psd: float = 1.0
    clock_drift_psd: float = 1.0
    clock_drift0: float = 0.0
    isb_sigma: float = 5.0

    def __post_init__(self) -> None:
        for name in ("los_scale", "clock_bias_psd", "clock_drift_psd", "isb_sigma"):
            if not float(getattr(self, name)) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if not -1.0 < float(self.psi) < 1.0:
            raise ValueError(f"psi must lie in (-1, 1), got {self.psi!r}")
        for name in ("nlos_leave", "nlos_positive"):
            if not 0.0 <= float(getattr(self, name)) <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {getattr(self, name)!r}")
        self.cn0_edges = tuple(float(v) for v in self.cn0_edges)
        self.nlos_share = tuple(float(v) for v in self.nlos_share)
        if len(self.nlos_share) != len(self.cn0_edges) + 1:
            raise ValueError(f"nlos_share needs len(cn0_edges) + 1 = {len(self.cn0_edges) + 1} values, got {len(self.nlos_share)}")
        if list(self.cn0_edges) != sorted(self.cn0_edges):
            raise ValueError(f"cn0_edges must be increasing, got {self.cn0_edges}")
        if not all(0.0 <= v < 1.0 for v in self.nlos_share):
            raise ValueError(f"nlos_share values must lie in [0, 1), got {self.nlos_share}")
        mags = torch.as_tensor(self.nlos_magnitudes, dtype=torch.float64).reshape(-1)
        if mags.numel() == 0 or not bool(torch.isfinite(mags).all()) or bool((mags < 0).any()):
            raise ValueError("nlos_magnitudes must be a non-empty set of finite values >= 0 (m)")
        self.nlos_magnitudes = mags

    def share(self, cn0: Tensor) -> Tensor:
        """Stationary NLOS share of ranges with C/N0 ``cn0`` (dB-Hz), same shape."""
        bins = torch.bucketize(cn0.to(torch.float64).contiguous(), torch.tensor(self.cn0_edges, dtype=torch.float64), right=True)
        return torch.tensor(self.nlos_share, dtype=torch.float64)[bins]

    def enter(self, cn0: Tensor) -> Tensor:
        """Per-epoch probability of entering an episode that gives :meth:`share` (clipped to 1)."""
        p = self.share(cn0)
        return (p / (1.0 - p) * self.nlos_leave).clamp_max(1.0)

    def summary(self) -> dict[str, float]:
        """The scalar numbers (for logs and results tables)."""
        return {
            "los_scale": float(self.los_scale),
            "psi": float(self.psi),
            "nlos_leave": float(self.nlos_leave),
            **{f"nlos_share_{i}": v for i, v in enumerate(self.nlos_share)},
            "nlos_positive": float(self.nlos_positive),
            "nlos_magnitude_median": float(self.nlos_magnitudes.median()),
            "clock_drift0": float(self.clock_drift0),
        }


def _truncated_normal_sd(c: float) -> float:
    """Standard deviation of a standard normal truncated to ``|x| < c``."""
    phi = math.exp(-0.5 * c * c) / math.sqrt(2.0 * math.pi)
    return math.sqrt(max(1.0 - 2.0 * c * phi / math.erf(c / math.sqrt(2.0)), 1e-12))


def _truncated_scale(values: Tensor, cut: float) -> float:
    """Scale ``s`` of a zero-mean normal from the values kept by ``|x| < cut``: the fixed point of
    ``sd(values) = s * sd_trunc(cut / s)``."""
    sd_obs = float(values.std())
    s = sd_obs
    for _ in range(50):
        s = sd_obs / _truncated_normal_sd(cut / s)
    return s


def _truncated_correlation(x0: Tensor, x1: Tensor, c: float) -> float:
    """Correlation ``rho`` of a standard bivariate normal whose pairs ``(x0, x1)`` were kept when
    both ``|x0|, |x1| < c``: inverts the truncated correlation, computed on a fixed Monte-Carlo
    sample (200,000 pairs) over a grid of ``rho``, by linear interpolation."""
    r_obs = float(torch.corrcoef(torch.stack([x0, x1]))[0, 1])
    gen = torch.Generator().manual_seed(0)
    u, v = torch.randn(2, 200_000, generator=gen, dtype=torch.float64)
    grid = torch.linspace(-0.99, 0.99, 199, dtype=torch.float64)
    seen = []
    for rho in grid.tolist():
        w = rho * u + math.sqrt(1.0 - rho * rho) * v
        keep = (u.abs() < c) & (w.abs() < c)
        seen.append(float(torch.corrcoef(torch.stack([u[keep], w[keep]]))[0, 1]))
    i = min(
        max(int(torch.searchsorted(torch.tensor(seen, dtype=torch.float64), torch.tensor([r_obs], dtype=torch.float64))), 1), len(seen) - 1
    )
    lo, hi = seen[i - 1], seen[i]
    t = 0.0 if hi == lo else min(max((r_obs - lo) / (hi - lo), 0.0), 1.0)
    return float(grid[i - 1]) + t * float(grid[i] - grid[i - 1])


def _cauchy_clock(r: Tensor, mask: Tensor, clock: Tensor, *, scale: float = 5.0, iterations: int = 10) -> Tensor:
    """Per-epoch common offset of the residuals ``r [T, K]`` over ``mask``: a Cauchy-weighted mean
    (``w = 1 / (1 + ((r - c) / scale)^2)``) iterated from ``clock [T]``."""
    for _ in range(iterations):
        w = torch.where(mask, 1.0 / (1.0 + ((r - clock[:, None]) / scale) ** 2), 0.0)
        clock = (w * torch.nan_to_num(r)).sum(1) / w.sum(1).clamp_min(1e-12)
    return clock


def _range_model(data: SmartLocData) -> torch.nn.Module:
    # The filter's measurement function without gate and with the receiver's variances.
    return make_smartloc_model(data, robust=None).measurement


def _truth_states(data: SmartLocData, first: int, stop: int) -> Tensor:
    x = torch.zeros(stop - first, 7, dtype=torch.float64)
    x[:, :3] = data.truth_enu[first:stop]
    return x


def calibrate_error_model(
    data: SmartLocData,
    first: int,
    stop: int,
    *,
    elevation_mask_deg: float = 15.0,
    los_threshold: float = 2.5,
    cn0_edges: tuple[float, ...] = (25.0, 30.0, 35.0, 40.0),
    clock_bias_psd: float = 1.0,
    clock_drift_psd: float = 1.0,
) -> PseudorangeErrorModel:
    """Moment estimates of :class:`PseudorangeErrorModel` on epochs ``[first, stop)``.

    With the reference track, ``r_kj = z_kj - h_j(truth_k)`` is clock + ISB + error.  The clock
    of each epoch is a Cauchy-weighted mean of ``r`` (:func:`_cauchy_clock`: scale 5 m, 10 iterations
    from the median);
    the ISB is the median over the segment of the GLONASS ranges' offset from it.  A range is
    line-of-sight when ``|e| < los_threshold * los_scale * sqrt(pr_var)`` (``los_scale`` and the
    split are iterated from ``los_scale = 1``); then:

    * ``los_scale`` and ``psi``: scale and lag-1 correlation of ``e / sqrt(pr_var)`` over LOS
      ranges (pairs of consecutive LOS epochs for ``psi``), corrected for the truncation at
      ``los_threshold`` (a normal AR(1) model; :func:`_truncated_scale`, :func:`_truncated_correlation`);
    * ``nlos_leave``: ``1 / (mean length of the NLOS runs of >= 2 epochs - 1)`` (for geometric
      run lengths this is unbiased and ignores the one-epoch runs that LOS tails make);
      ``nlos_share[c]``: share of NLOS ranges among those with C/N0 in bin ``c`` of
      ``cn0_edges`` (a bin without ranges gets the overall share), minus the LOS tail beyond the
      threshold;
    * ``nlos_positive``: share of positive NLOS errors; ``nlos_magnitudes``: their ``|e|``;
    * ``clock_drift0``: median of the clock's epoch-to-epoch rate.

    The clock PSDs are inputs (default the loader's 1.0; second differences of 10 s clock rates on
    either 60 % of the drive give a drift PSD of 0.9-1.1 m^2/s^3, an upper bound, as the epoch
    clocks carry noise).
    """
    total = data.num_epochs
    if not 0 <= first < stop <= total:
        raise ValueError(f"need 0 <= first < stop <= {total}, got [{first}, {stop})")
    if stop - first < 10:
        raise ValueError(f"calibration needs at least 10 epochs, got {stop - first}")
    h = _range_model(data)
    sl = slice(first, stop)
    x = _truth_states(data, first, stop)
    u = {"sat_pos": data.sat_enu[sl], "glonass": data.glonass[sl].to(torch.float64)}
    mask = data.mask[sl] & (data.elevation[sl] >= elevation_mask_deg)
    z = data.reduced_pseudorange()[sl]
    r = torch.where(mask, z - h(x, u), torch.nan)
    glo = data.glonass[sl]
    clock = _cauchy_clock(r, mask, torch.nanmedian(r, 1).values)
    isb_all = torch.where(mask & glo, r - clock[:, None], torch.nan)
    isb = float(torch.nanmedian(isb_all)) if bool((mask & glo).any()) else 0.0
    clock = _cauchy_clock(r - torch.where(glo, isb, 0.0), mask, clock)  # again, with the ISB removed
    e = r - torch.where(glo, isb, 0.0) - clock[:, None]
    en = e / data.pr_var[sl].sqrt()
    x0, x1 = en[:-1], en[1:]
    los_scale = 1.0
    for _ in range(6):  # classify at los_threshold x the current scale, re-estimate the scale
        cut = float(los_threshold) * los_scale
        los = mask & (en.abs() < cut)
        if int(los.sum()) < 10:
            raise ValueError(f"segment [{first}, {stop}) has too few line-of-sight ranges to calibrate ({int(los.sum())})")
        los_scale = _truncated_scale(en[los], cut)
    pair = los[1:] & los[:-1]
    psi = _truncated_correlation(x0[pair] / los_scale, x1[pair] / los_scale, cut / los_scale)
    nlos = mask & ~los
    # LOS ranges beyond the cut (share p_tail) were counted as NLOS: a share too high by
    # p_tail (1 - share), undone below.
    p_tail = math.erfc(cut / los_scale / math.sqrt(2.0))
    runs: list[int] = []
    for j in range(nlos.shape[1]):
        col = nlos[:, j].to(torch.int8)
        edges = torch.diff(torch.cat([col.new_zeros(1), col, col.new_zeros(1)]))
        starts, ends = torch.nonzero(edges == 1)[:, 0], torch.nonzero(edges == -1)[:, 0]
        runs.extend((ends - starts).tolist())
    long_runs = [n for n in runs if n >= 2]
    # geometric run lengths: L - 1 given L >= 2 has the law of L, so mean(L | L >= 2) - 1 = 1 / q
    leave = 1.0 / max(sum(long_runs) / len(long_runs) - 1.0, 1.0) if long_runs else 1.0

    def unmix(share: float) -> float:
        return min(max((share - p_tail) / (1.0 - p_tail), 0.0), 0.99)

    overall = float(nlos.sum()) / float(mask.sum())
    bins = torch.bucketize(data.cn0[sl].contiguous(), torch.tensor(cn0_edges, dtype=torch.float64), right=True)
    shares = []
    for c in range(len(cn0_edges) + 1):
        inbin = mask & (bins == c)
        shares.append(unmix(float((nlos & inbin).sum()) / float(inbin.sum()) if bool(inbin.any()) else overall))
    drift = torch.diff(clock) / data.dt[first + 1 : stop].clamp_min(1e-3)
    return PseudorangeErrorModel(
        los_scale=los_scale,
        psi=min(max(psi, -0.99), 0.99),
        nlos_leave=leave,
        cn0_edges=tuple(cn0_edges),
        nlos_share=tuple(shares),
        nlos_positive=float((e[nlos] > 0).double().mean()) if bool(nlos.any()) else 0.5,
        nlos_magnitudes=e[nlos].abs().clone() if bool(nlos.any()) else torch.zeros(1, dtype=torch.float64),
        clock_bias_psd=clock_bias_psd,
        clock_drift_psd=clock_drift_psd,
        clock_drift0=float(torch.median(drift)),
    )


def _ar1(steps: int, shape: tuple[int, ...], psi: float, gen: torch.Generator) -> Tensor:
    w = torch.randn(steps, *shape, generator=gen, dtype=torch.float64)
    out = torch.empty_like(w)
    out[0] = w[0]
    c = math.sqrt(1.0 - psi * psi)
    for k in range(1, steps):
        out[k] = psi * out[k - 1] + c * w[k]
    return out


def _nlos_bias(cn0: Tensor, model: PseudorangeErrorModel, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Markov NLOS states (bool) and the bias of each epoch (0 when LOS), both shaped like
    ``cn0 [T, ...]`` (the C/N0 that sets each epoch's entry probability)."""
    steps, shape = int(cn0.shape[0]), tuple(cn0.shape[1:])
    enter_p = model.enter(cn0)
    state = torch.rand(shape, generator=gen, dtype=torch.float64) < model.share(cn0[0])
    mags = model.nlos_magnitudes

    def draw() -> Tensor:
        idx = torch.randint(0, mags.numel(), shape, generator=gen)
        sign = torch.where(torch.rand(shape, generator=gen, dtype=torch.float64) < model.nlos_positive, 1.0, -1.0)
        return sign * mags[idx]

    bias = draw()
    states, biases = [], []
    for k in range(steps):
        if k > 0:
            u = torch.rand(shape, generator=gen, dtype=torch.float64)
            enter = ~state & (u < enter_p[k])
            leave = state & (u < model.nlos_leave)
            bias = torch.where(enter, draw(), bias)
            state = (state | enter) & ~leave
        states.append(state)
        biases.append(torch.where(state, bias, 0.0))
    return torch.stack(states), torch.stack(biases)


def simulate_smartloc_drives(
    data: SmartLocData,
    starts: list[int],
    length: int,
    model: PseudorangeErrorModel,
    *,
    seed: int,
    dtype: torch.dtype = torch.float64,
    elevation_mask_deg: float = 15.0,
    initial_sd: tuple[float, ...] = (30.0, 30.0, 2.0, math.radians(10.0), 30.0, 2.0, 10.0),
) -> tuple[SmartLocBatch, Tensor, Tensor, dict[str, Tensor]]:
    """Synthetic drives on windows ``[s, s + length)`` of the real drive, one per entry of ``starts``.

    Returns ``(batch, initial_mean [B, 7], initial_cov [B, 7, 7], extra)``: ``batch`` is the
    real windows' :class:`SmartLocBatch` with synthetic ``measurements`` (and ``pr_obs``), the
    initial belief is centred on a draw from ``N(true state, diag(initial_sd^2))`` (the spread of
    the real drive's snapshot-fix starts; yaw from the reference heading), and ``extra`` holds
    the full true states ``state [B, T, 7]`` (position, heading, clock bias, drift, ISB), the
    NLOS flags ``nlos [B, T, K]`` and the errors ``error [B, T, K]``.  Each drive's clock
    starts at a bias drawn from ``N(0, 100^2)`` m and a drift from ``N(clock_drift0, 2^2)`` m/s.
    """
    if length < 2:
        raise ValueError(f"length must be >= 2 epochs, got {length}")
    if not starts:
        raise ValueError("starts must name at least one window")
    if min(starts) < 0 or max(starts) + length > data.num_epochs:
        raise ValueError(
            f"windows [s, s + {length}) must lie in the drive's {data.num_epochs} epochs, got starts {min(starts)}..{max(starts)}"
        )
    if len(initial_sd) != 7:
        raise ValueError(f"initial_sd needs 7 standard deviations (E, N, U, yaw, b, d, isb), got {len(initial_sd)}")
    gen = torch.Generator().manual_seed(int(seed))
    full = data.batch(torch.float64, elevation_mask_deg=elevation_mask_deg)
    idx = torch.tensor(starts)[:, None] + torch.arange(length)[None]  # [B, T]
    bsz, k = len(starts), data.num_slots
    mask = full.mask[0][idx]
    controls = {key: v[0][idx] for key, v in full.controls.items()}
    dt = controls["dt"][..., 0].clone()
    dt[:, 0] = 0.0
    # clock: drift random walk around clock_drift0, bias integrates it
    drift = model.clock_drift0 + 2.0 * torch.randn(bsz, 1, generator=gen, dtype=torch.float64)
    wd = torch.randn(bsz, length, generator=gen, dtype=torch.float64) * torch.sqrt(model.clock_drift_psd * dt)
    drift = drift + torch.cumsum(wd, 1)
    wb = torch.randn(bsz, length, generator=gen, dtype=torch.float64) * torch.sqrt(model.clock_bias_psd * dt)
    bias = 100.0 * torch.randn(bsz, 1, generator=gen, dtype=torch.float64) + torch.cumsum(drift * dt + wb, 1)
    isb = model.isb_sigma * torch.randn(bsz, 1, generator=gen, dtype=torch.float64)
    heading = torch.atan2(*(data.truth_enu[(idx + 5).clamp_max(data.num_epochs - 1)] - data.truth_enu[idx])[..., [1, 0]].unbind(-1))
    state = torch.stack([*data.truth_enu[idx].unbind(-1), heading, bias, drift, isb.expand(bsz, length)], -1)
    h = _range_model(data)
    clean = h(state, {"sat_pos": controls["sat_pos"], "glonass": controls["glonass"]})
    a = _ar1(length, (bsz, k), model.psi, gen).transpose(0, 1)
    cn0 = data.cn0[idx]  # [B, T, K] real C/N0 (0 in empty slots)
    nlos, nb = _nlos_bias(cn0.transpose(0, 1), model, gen)
    error = model.los_scale * controls["pr_var"].sqrt() * a + nb.transpose(0, 1)
    z = torch.where(mask, clean + error, 0.0)
    controls["pr_obs"] = z
    sd = torch.tensor(initial_sd, dtype=torch.float64)
    mean0 = state[:, 0] + sd * torch.randn(bsz, 7, generator=gen, dtype=torch.float64)
    cov0 = torch.diag(sd * sd).expand(bsz, 7, 7).clone()
    batch = SmartLocBatch(
        measurements=z.to(dtype),
        mask=mask,
        controls={key: v.to(dtype) for key, v in controls.items()},
        truth=data.truth_enu[idx].to(dtype),
        times=data.times[idx].to(dtype),
        start=torch.tensor(starts, dtype=torch.long),
        reduced=True,
    )
    extra = {"state": state.to(dtype), "nlos": nlos.transpose(0, 1) & mask, "error": torch.where(mask, error, 0.0).to(dtype)}
    return batch, mean0.to(dtype), cov0.to(dtype), extra


def synthetic_drive(
    data: SmartLocData, model: PseudorangeErrorModel, *, seed: int, elevation_mask_deg: float = 15.0
) -> tuple[SmartLocData, dict[str, Tensor]]:
    """The whole drive with synthetic pseudoranges (ranges below ``elevation_mask_deg`` are
    dropped from ``mask``) and the ``extra`` truth of :func:`simulate_smartloc_drives`
    (``state``, ``nlos``, ``error``) without the batch dimension."""
    batch, _, _, extra = simulate_smartloc_drives(data, [0], data.num_epochs, model, seed=seed, elevation_mask_deg=elevation_mask_deg)
    mask = batch.mask[0]
    rho = torch.where(mask, batch.measurements[0] + torch.linalg.vector_norm(data.sat_enu, dim=-1), 0.0)
    return dataclasses.replace(data, pseudorange=rho, mask=mask), {k: v[0] for k, v in extra.items()}
