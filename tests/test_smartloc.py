"""Tests for the smartLoc real-data loader, the snapshot baseline and the odometry + pseudorange EKF."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.filters import EKF, UKF
from difffilter.geometry import ecef_to_geodetic
from experiments.papers.smartloc import (
    default_smartloc_path,
    load_smartloc,
    make_smartloc_model,
    single_epoch_wls,
    smartloc_initial_belief,
)

F64 = torch.float64

pytestmark = pytest.mark.skipif(
    not (default_smartloc_path() / "Berlin_Potsdamer_Platz_Input.txt").exists(),
    reason="smartLoc data folder ../shared/data/real not present",
)


@pytest.fixture(scope="module")
def data():  # type: ignore[no-untyped-def]
    return load_smartloc()


@pytest.fixture(scope="module")
def wls(data):  # type: ignore[no-untyped-def]
    return single_epoch_wls(data, robust="cauchy", threshold=1.5)


def test_counts_match_the_readme(data) -> None:  # type: ignore[no-untyped-def]
    assert data.num_epochs == 1372 and data.num_slots == 17
    per_epoch = data.mask.sum(1)
    assert int(per_epoch.min()) == 7 and int(per_epoch.max()) == 17 and int(per_epoch.median()) == 15
    assert int(data.mask.sum()) == 20038
    assert int((data.system == 1).sum()) == 11193 and int((data.system == 4).sum()) == 8845
    assert int(data.glonass.sum()) == 8845
    assert data.times[0] == 0 and data.times[-1].item() == pytest.approx(282.799, abs=1e-3)
    steps = data.dt[1:]
    assert int(((steps - 0.2).abs() < 0.02).sum()) == 1285 and int(((steps - 0.3).abs() < 0.02).sum()) == 86
    var = data.pr_var[data.mask]
    assert var.min() == 25 and var.max() == 196
    norms = data.sat_ecef[data.mask].norm(dim=-1)
    assert 25.4e6 < norms.min() and norms.max() < 26.9e6
    assert data.speed.max().item() == pytest.approx(9.84, abs=0.01) and data.speed.mean().item() == pytest.approx(5.50, abs=0.01)
    assert data.yaw_rate.min().item() == pytest.approx(-0.61, abs=0.01) and data.yaw_rate.max().item() == pytest.approx(0.56, abs=0.01)


def test_frames_and_reference(data) -> None:  # type: ignore[no-untyped-def]
    assert torch.equal(data.truth_enu[0], torch.zeros(3, dtype=F64))
    lat, lon, h = data.origin_llh.tolist()
    assert math.degrees(lat) == pytest.approx(52.50457, abs=1e-5) and math.degrees(lon) == pytest.approx(13.37366, abs=1e-5)
    assert h == pytest.approx(76.0, abs=0.1)
    assert torch.allclose(data.enu_to_ecef(data.truth_enu), data.truth_ecef, atol=1e-6)
    assert torch.allclose(data.ecef_to_enu(data.sat_ecef), data.sat_enu, atol=1e-4)
    assert data.truth_enu[-1, :2].norm() < 15.0  # the loop closes within ~10 m
    # odometry speed agrees with differenced reference positions (README: scale 0.993)
    v_ref = (data.truth_enu[1:] - data.truth_enu[:-1]).norm(dim=-1) / data.dt[1:]
    scale = (v_ref * data.speed[1:]).sum() / (data.speed[1:] ** 2).sum()
    assert scale.item() == pytest.approx(0.993, abs=0.01)
    # empty slots carry a finite dummy satellite far above the origin
    assert bool(torch.isfinite(data.sat_enu).all()) and bool((data.sat_enu[~data.mask][:, 2] > 1e7).all())
    llh = ecef_to_geodetic(data.truth_ecef)
    assert (llh[:, 2] - h).abs().max() < 5.0  # a flat drive


def test_satellite_slots_and_batches(data) -> None:  # type: ignore[no-untyped-def]
    per_sat = load_smartloc(slots="satellite")
    assert int(per_sat.mask.sum()) == 20038 and per_sat.num_slots > 17
    ids = per_sat.sat_id.clone()
    ids[~per_sat.mask] = -1
    for k in range(per_sat.num_slots):
        assert ids[:, k][ids[:, k] >= 0].unique().numel() == 1
    b = data.batch(torch.float32, elevation_mask_deg=15.0)
    assert b.measurements.shape == (1, 1372, 17) and b.measurements.dtype == torch.float32
    assert bool((b.mask[0] <= data.mask).all()) and bool((data.elevation[b.mask[0]] >= 15.0).all())
    ref = data.pseudorange - data.sat_enu.norm(dim=-1)
    assert torch.allclose(b.measurements[0][b.mask[0]].double(), ref[b.mask[0]], atol=0.02)
    w = data.windows(200, stride=150)
    assert w.measurements.shape == (8, 200, 17) and w.start.tolist() == list(range(0, 1051, 150))
    assert torch.equal(w.controls["sat_pos"][2], data.batch().controls["sat_pos"][0, 300:500])
    assert torch.equal(w.truth[1], data.truth_enu[150:350])


def test_snapshot_wls_reproduces_the_readme_baseline(data, wls) -> None:  # type: ignore[no-untyped-def]
    err = (wls.enu[:, :2] - data.truth_enu[:, :2]).norm(dim=-1)
    median = err.median().item()
    print(f"snapshot robust WLS horizontal median {median:.1f} m, p95 {err.quantile(0.95).item():.1f} m")
    assert 15.0 < median < 35.0  # README: 23.6 m (measured here: 23.4 m)
    assert bool(wls.valid.all())
    east_bias = (wls.enu[:, 0] - data.truth_enu[:, 0]).mean().item()
    no_sagnac = single_epoch_wls(data, robust="cauchy", threshold=1.5, sagnac=False)
    east_bias_raw = (no_sagnac.enu[:, 0] - data.truth_enu[:, 0]).mean().item()
    assert abs(east_bias) < 15.0 and east_bias_raw > 25.0  # README: 10.8 m with, 32 m without


def _run(data, wls, filter_cls, start: int, length: int, dtype: torch.dtype = F64):  # type: ignore[no-untyped-def]
    full = data.batch(dtype, elevation_mask_deg=15.0)
    sl = slice(start, start + length)
    controls = {k: v[:, sl] for k, v in full.controls.items()}
    model = make_smartloc_model(data, dtype=dtype)
    mean, cov = smartloc_initial_belief(data, torch.tensor([start]), wls=wls, dtype=dtype)
    with torch.no_grad():
        res = filter_cls(model)(full.measurements[:, sl], mean, cov, mask=full.mask[:, sl], controls=controls)
    return (res.mean[0, :, :2] - full.truth[0, sl, :2]).norm(dim=-1).double(), res


def test_ekf_window_beats_snapshot_fixes(data, wls) -> None:  # type: ignore[no-untyped-def]
    err, res = _run(data, wls, EKF, 300, 250)
    snap = (wls.enu[300:550, :2] - data.truth_enu[300:550, :2]).norm(dim=-1)
    print(f"EKF window 300-550 horizontal median {err.median().item():.1f} m (snapshot {snap.median().item():.1f} m)")
    assert err.median() < 30.0 and err.median() < 0.9 * snap.median()
    err32, _ = _run(data, wls, EKF, 300, 250, torch.float32)
    assert (err32 - err).abs().max() < 1.0


@pytest.mark.slow
@pytest.mark.parametrize("filter_cls", [EKF, UKF])
def test_filter_over_the_whole_drive(data, wls, filter_cls) -> None:  # type: ignore[no-untyped-def]
    err, _ = _run(data, wls, filter_cls, 0, data.num_epochs)
    print(f"{filter_cls.__name__} whole drive: horizontal median {err.median().item():.1f} m, RMS {err.pow(2).mean().sqrt().item():.1f} m")
    assert err.median() < 30.0
