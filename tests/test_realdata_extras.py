"""The sensor-model extras of the smartLoc real-data model (lever arm, latency, elevation-dependent
bias; experiments.papers.smartloc.extras): configuration, gradients, and recovery on a synthetic drive."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import torch
from torch.func import functional_call

from difffilter.models.navigation.pseudorange import GnssStateLayout, PseudorangeMeasurement
from experiments.papers.smartloc import protocol
from experiments.papers.smartloc.extras import LinearDistancePrior, extras_options, extras_priors, learn_patterns
from experiments.papers.smartloc.model import make_smartloc_model

from .librsf_fixture import HAVE_DATA, write_drive

pytestmark = pytest.mark.skipif(not HAVE_DATA, reason="the smartLoc excerpt tests/assets/librsf/smartlocx_* is missing")

F64 = torch.float64
HAND = {
    "speed_sigma": 0.05,
    "yaw_rate_sigma": 0.002,
    "horizontal_psd": 0.5,
    "vertical_psd": 0.01,
    "yaw_psd": 1.0e-4,
    "clock_bias_psd": 1.0,
    "clock_drift_psd": 1.0,
    "isb_psd": 0.01,
}
GATE = {"threshold": 2.5, "floor": 8.0, "softness": None, "learnable": False, "gradient": False}
EXTRA_NAMES = ("lever_arm", "latency", "elevation_bias")


def _cfg(**extra: object) -> dict:
    return {"gate": GATE, "bound_ratio": 10.0, "hand_tuned": HAND, "learn": ["*noise_model.*"], **extra}


def _drive(tmp_path: Path, start: float = 100.0, stop: float = 140.0) -> protocol.Drive:
    write_drive(tmp_path, "Cut", start=start, stop=stop)
    return protocol.load_drives([{"folder": str(tmp_path), "input_file": None}])[0]


def test_extras_are_on_by_default_and_bad_values_name_the_key() -> None:
    """No ``extras`` entry: all three extras learned, started at 0; ``enabled: false`` none; every bad
    entry is a ValueError naming ``extras.<key>``; the signed prior is a Gaussian on a linear scale."""
    on = extras_options(_cfg(), 2)
    assert on == {"lever_arm": [0.0, 0.0, 0.0], "latency": 0.0, "elevation_bias": [0.0, 0.0]}
    assert learn_patterns(_cfg()) == ["*noise_model.*", *EXTRA_NAMES]
    assert extras_options(_cfg(extras={"enabled": False}), 2) == dict.fromkeys(EXTRA_NAMES)
    assert learn_patterns(_cfg(extras={"enabled": False})) == ["*noise_model.*"]
    assert learn_patterns(_cfg(extras={"latency": None})) == ["*noise_model.*", "lever_arm", "elevation_bias"]
    bad = {
        "lever_arm": [1.0, 2.0],
        "latency": "0.1",
        "elevation_bias": [0.0, 0.0, 0.0],
        "enabled": "yes",
        "prior_sd": {"latency": -1.0},
    }
    for key, value in bad.items():
        cfg = _cfg(extras={key: value})
        with pytest.raises(ValueError, match=f"extras.{key}"):
            extras_options(cfg, 2)
            extras_priors(cfg, ["model.measurement.latency"], {"model.measurement.latency": (None, "latency")})
    with pytest.raises(ValueError, match="unknown keys"):
        extras_options(_cfg(extras={"lever": [0.0, 0.0, 0.0]}), 2)
    prior = LinearDistancePrior(reference=torch.tensor([0.5, -1.0]), scale=2.0)
    v = torch.tensor([1.5, 1.0], dtype=F64)
    assert float(prior.log_prob(v)) == pytest.approx(-0.5 * ((1.0 / 2.0) ** 2 + (2.0 / 2.0) ** 2), rel=1e-12)


def test_the_model_refuses_extras_outside_their_bounds() -> None:
    layout = GnssStateLayout.odometry(isb=True)
    origin = torch.tensor([3.78e6, 0.9e6, 5.04e6], dtype=F64)
    kw = {"num_satellites": 4, "layout": layout, "frame_origin": origin, "frame": "enu"}
    with pytest.raises(ValueError, match="lever_arm"):
        PseudorangeMeasurement(**kw, lever_arm=[7.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="latency"):
        PseudorangeMeasurement(**kw, latency=0.9)
    with pytest.raises(ValueError, match="elevation_bias"):
        PseudorangeMeasurement(**kw, elevation_bias=[12.0, 0.0])


def test_zero_extras_give_the_plain_model_and_their_gradients_match_finite_differences(tmp_path) -> None:
    """Extras started at 0 predict exactly what the model without them predicts (so v3's start is v4's);
    the gradients of the filtered positions with respect to the raw (unconstrained) lever arm,
    latency and elevation bias match central finite differences (``gradcheck``, float64), and the
    analytic Jacobian with every extra set equals autodiff's."""
    drive = _drive(tmp_path, 100.0, 104.0)
    sets = protocol.block_sets([drive], {0: (1, 10)}, elevation_mask_deg=15.0)
    s = sets[0]
    plain = protocol.build_filter(_cfg(extras={"enabled": False}), [drive], "scale", torch.zeros(0), learned=True)
    extra = protocol.build_filter(_cfg(), [drive], "scale", torch.zeros(0), learned=True)
    run = lambda f: f(s.measurements, s.initial_mean, s.initial_cov, mask=s.mask, controls=s.controls).mean  # noqa: E731
    with torch.no_grad():
        assert torch.equal(run(plain), run(extra))
    names = [f"model.measurement.parametrizations.{n}.original" for n in EXTRA_NAMES]
    params = dict(extra.named_parameters())
    gen = torch.Generator().manual_seed(0)
    start = [(params[n].detach() + 0.1 * torch.randn(params[n].shape, generator=gen, dtype=F64)).requires_grad_() for n in names]

    def positions(*raw: torch.Tensor) -> torch.Tensor:
        res = functional_call(
            extra,
            dict(zip(names, raw, strict=True)),
            (s.measurements, s.initial_mean, s.initial_cov),
            {"mask": s.mask, "controls": s.controls},
        )
        return res.mean[..., :2]

    assert torch.autograd.gradcheck(positions, tuple(start), eps=1e-6, atol=1e-5, rtol=1e-4)
    meas = make_smartloc_model(drive.data, robust=None, lever_arm=[1.0, -0.5, 0.3], latency=0.1, elevation_bias=[1.5, -2.0]).measurement
    steps = [2, 5, 8]
    x = s.initial_mean[0].expand(3, 7) + torch.tensor([[1.0, -2.0, 0.5, 0.1, 3.0, 0.2, -1.0]], dtype=F64) * torch.tensor(
        [[1.0], [0.5], [-1.0]], dtype=F64
    )
    u = {k: v[0, steps] for k, v in s.controls.items()}
    auto = torch.autograd.functional.jacobian(lambda xx: meas(xx, u), x, vectorize=True)
    torch.testing.assert_close(meas.jacobian(x, u), torch.stack([auto[i, :, i] for i in range(3)]), rtol=1e-9, atol=1e-6)
    with torch.no_grad():  # the bias term is c_g / sin(el) per slot's constellation
        base = make_smartloc_model(drive.data, robust=None).measurement(x, u)
        el = torch.deg2rad(u["elevation"].clamp_min(5.0))
        want = torch.tensor([1.5, -2.0], dtype=F64)[u["constellation"].long()] / torch.sin(el)
        got = meas(x, u) - make_smartloc_model(drive.data, robust=None, lever_arm=[1.0, -0.5, 0.3], latency=0.1).measurement(x, u)
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9)
        assert not torch.equal(base, meas(x, u))


ARM, TAU, SIGMA = (1.2, -0.8, 0.0), 0.15, 0.5


def _synthetic(drive: protocol.Drive, steps: int, seed: int) -> tuple[object, torch.Tensor]:
    """The cut drive's geometry and odometry with pseudoranges of a known antenna (``ARM``, ``TAU``)
    plus N(0, SIGMA^2) noise, the receiver variances set to SIGMA^2; the heading is the odometry's
    integrated yaw rate from the reference heading (what the filter's yaw follows)."""
    data = drive.data
    head0 = math.atan2(*(data.truth_enu[5] - data.truth_enu[0])[[1, 0]].tolist())
    yaw = head0 + torch.cat([torch.zeros(1, dtype=F64), torch.cumsum(data.yaw_rate[1:] * data.dt[1:], 0)])
    state = torch.zeros(data.num_epochs, 7, dtype=F64)
    state[:, :3], state[:, 3], state[:, 4], state[:, 6] = data.truth_enu, yaw, 20.0, 3.0
    with torch.no_grad():
        h = make_smartloc_model(data, robust=None, lever_arm=list(ARM), latency=TAU).measurement
        b = data.batch(F64, elevation_mask_deg=15.0)
        z = h(state[None], b.controls)[0]
        z = z + SIGMA * torch.randn(z.shape, generator=torch.Generator().manual_seed(seed), dtype=F64)
        rho = torch.where(b.mask[0], z + torch.linalg.vector_norm(data.sat_enu, dim=-1), 0.0)
    out = dataclasses.replace(data, pseudorange=rho, pr_var=torch.full_like(data.pr_var, SIGMA**2))
    cut = lambda t: t[:steps]  # noqa: E731
    fields = ("times", "dt", "truth_ecef", "truth_enu", "pseudorange", "pr_var", "sat_ecef", "sat_enu", "sat_id", "system")
    fields += ("glonass", "mask", "elevation", "cn0", "speed", "yaw_rate")
    return dataclasses.replace(out, **{f: cut(getattr(out, f)) for f in fields}), state[:steps]


def _horizontal_errors(filt: torch.nn.Module, data: object, state: torch.Tensor) -> torch.Tensor:
    b = data.batch(F64, elevation_mask_deg=15.0)
    cov0 = torch.diag(torch.tensor([1.0, 1.0, 1.0, 1e-3, 4.0, 0.1, 4.0], dtype=F64))[None]
    res = filt(b.measurements, state[:1].clone(), cov0, mask=b.mask, controls=b.controls)
    return (res.mean[0, :, :2] - data.truth_enu[:, :2]).norm(dim=-1)


@pytest.mark.slow
def test_a_known_lever_arm_and_latency_are_recovered_and_beat_the_model_without_them(tmp_path) -> None:
    """Synthetic drive (real geometry of a 40-s cut: 194 epochs, speeds 0-7.4 m/s, ~2 rad of turning)
    with lever arm (1.2, -0.8, 0) m and latency 0.15 s: the protocol's learned filter (extras on,
    started at 0) trained on the horizontal position error recovers the horizontal arm within
    0.3 m and the latency within 0.05 s, and on an independent noise draw it is at least twice as
    accurate (RMS) as the same filter with the extras off.

    Tolerances: the forward arm and ``latency x speed`` move the antenna along the same axis,
    separated only by the speed changing, so they trade off (0.3 m ~ 0.05 s x 6 m/s); the up arm
    is not checked - the horizontal loss does not see it and the U state absorbs it."""
    drive = _drive(tmp_path)
    train, state = _synthetic(drive, drive.data.num_epochs, seed=1)
    test, _ = _synthetic(drive, drive.data.num_epochs, seed=2)
    cfg = _cfg()
    filt = protocol.build_filter(cfg, [protocol.Drive(train, drive.wls)], "scale", torch.zeros(0), learned=True)
    raw = [p for n, p in filt.named_parameters() if any(f"parametrizations.{k}." in n for k in EXTRA_NAMES)]
    assert len(raw) == 3
    opt = torch.optim.Adam(raw, lr=0.1)
    for _ in range(40):
        opt.zero_grad()
        _horizontal_errors(filt, train, state).pow(2).mean().backward()
        opt.step()
    meas = filt.model.measurement
    arm, tau = meas.lever_arm.detach(), float(meas.latency.detach())
    assert abs(float(arm[0]) - ARM[0]) < 0.3 and abs(float(arm[1]) - ARM[1]) < 0.3, arm
    assert abs(tau - TAU) < 0.05, tau
    assert bool((meas.elevation_bias.detach().abs() < 1.0).all())  # no bias was simulated
    plain = protocol.build_filter(_cfg(extras={"enabled": False}), [protocol.Drive(test, drive.wls)], "scale", torch.zeros(0), learned=True)
    with torch.no_grad():
        rms_with = float(_horizontal_errors(filt, test, state).pow(2).mean().sqrt())
        rms_without = float(_horizontal_errors(plain, test, state).pow(2).mean().sqrt())
    assert rms_with < 0.5 * rms_without, (rms_with, rms_without)
