"""Two impossibilities behind p004's (Li, Zhu, Wang & Lyu) EKF/UKF blend, proved numerically on
the project's models and filters instead of being stated.

1. Where the dynamics are linear, the EKF and the UKF are the same filter: both propagate the
   exact mean and covariance (the unscented transform is exact for affine maps, the Jacobian is
   the map), so any blend ``delta x_E + (1 - delta) x_U`` equals either, to rounding.  p004's
   planar IMU prediction is linear in position and velocity once heading and biases are known
   (the trapezoidal step driven by the rotated specific force): the regime p004 assigns to the
   EKF ("constant velocity, constant acceleration").  The full model (uncertain heading) is
   the control case where they differ.
2. p004's eq. (11) as printed, ``P = delta P_E + (1 - delta) P_U + Q`` (both branches already
   contain ``Q``), is the project's blend with ``Q`` doubled: the noise enters both branches
   additively and state-independently, so the extra ``Q`` is a rescaling of the learnable
   noise, not a different filter.  With linear dynamics it is therefore an EKF with ``2 Q``.
"""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.filters import EKF, UKF
from difffilter.filters.sigma_points import MerweScaled
from difffilter.mixers import Blend
from difffilter.models import LinearModel
from difffilter.models.base import DynamicsModel, StateSpaceModel
from experiments.papers.p004 import p004_simulator
from experiments.papers.p004.model import GnssImuModel, PlanarGnssImuDynamics

f64 = torch.float64
STEPS, RUNS = 80, 4
NOISE = ("sigma_accel", "sigma_gyro", "sigma_accel_bias_walk", "sigma_gyro_bias_walk", "sigma_position_step")


def _sigma_points() -> MerweScaled:
    return MerweScaled(alpha=1.0, beta=2.0, kappa=0.0)  # experiments/papers/p004/conf/filter/p004_blend.yaml


def _blend(model: StateSpaceModel, delta: float = 0.85, cls: type[Blend] = Blend) -> Blend:
    return cls(EKF(model), UKF(model, sigma_points=_sigma_points(), redraw_after_predict=True), mode="fixed", delta=delta).to(f64)


class _PaperEq11Blend(Blend):
    """p004 eq. (11) as printed: the blended prior covariance receives ``Q`` once more."""

    def predict(self, belief, u):
        out = super().predict(belief, u)
        q = self.model.dynamics.process_noise(belief["mean"], u)
        out.update(self.ukf.init_belief(out["mean"], out["cov"] + q))
        return out


class _KnownAttitude(DynamicsModel):
    """p004's planar prediction with heading and biases given as inputs (``u["attitude"]``
    ``[psi, b_f, b_l, b_g]``): state ``[p_e, p_n, v_e, v_n]``, ``Q`` the position/velocity block
    of the full model's ``Q`` times ``q_scale``."""

    def __init__(self, full: PlanarGnssImuDynamics, q_scale: float = 1.0) -> None:
        super().__init__()
        self.full, self.q_scale, self.state_dim = full, q_scale, 4

    def _full_state(self, x, u):
        att = u["attitude"]
        return torch.cat([x, att.expand(*x.shape[:-1], 4)], -1)

    def forward(self, x, u=None):
        return self.full(self._full_state(x, u), u)[..., :4]

    def process_noise(self, x, u=None):
        return self.q_scale * self.full.process_noise(self._full_state(x, u), u)[..., :4, :4]


def _data():
    data = p004_simulator(batch_size=RUNS, seed=11, dtype=f64)
    controls = {k: v[:, :STEPS] for k, v in data.controls.items()}
    return data, data.measurements[:, :STEPS], data.mask[:, :STEPS], controls


def _linear_p004(q_scale: float = 1.0):
    data, z, mask, controls = _data()
    full = GnssImuModel(planar=True, dtype=f64)
    # the attitude of step k is the one the step starts from: the belief's at k = 0, the truth's after
    start = data.initial_mean[:, None, 4:8]
    controls["attitude"] = torch.cat([start, data.truth[:, : STEPS - 1, 4:8]], 1)
    lin = LinearModel(F=torch.eye(4, dtype=f64), H=full.measurement.matrix()[:, :4], Q=torch.eye(4, dtype=f64), R=full.R)
    model = StateSpaceModel(_KnownAttitude(full.dynamics, q_scale), lin.measurement)
    return model, z, mask, controls, data.initial_mean[:, :4], data.initial_cov[:4, :4]


def _run(filt, z, mask, controls, mean0, cov0):
    with torch.no_grad():
        return filt(z, mean0, cov0, mask=mask, controls=controls)


def _assert_same(a, b, rel: float = 1e-10) -> None:
    # "to rounding": measured ~1e-12 of each quantity's largest entry after 80 steps (float64)
    for name in ("mean", "cov", "prior_mean", "prior_cov"):
        x, y = getattr(a, name), getattr(b, name)
        scale = y.abs().amax(dim=tuple(range(1, y.ndim)), keepdim=True)
        assert float(((x - y).abs() / scale).max()) < rel, name
    torch.testing.assert_close(a.log_likelihood, b.log_likelihood, rtol=rel, atol=rel)


def test_ekf_equals_ukf_and_every_blend_where_p004_dynamics_are_linear():
    model, z, mask, controls, mean0, cov0 = _linear_p004()
    ekf = _run(EKF(model), z, mask, controls, mean0, cov0)
    ukf = _run(UKF(model, sigma_points=_sigma_points(), redraw_after_predict=True), z, mask, controls, mean0, cov0)
    _assert_same(ukf, ekf)
    for delta in (0.0, 0.85, 1.0):
        _assert_same(_run(_blend(model, delta), z, mask, controls, mean0, cov0), ekf)
    # the filters did filter (GNSS fixes pulled the position covariance down from its prior)
    assert float(ekf.cov[:, -1, 0, 0].max()) < float(cov0[0, 0])


def test_ekf_and_ukf_differ_on_the_full_p004_model():
    # control case: with an uncertain heading the prediction is nonlinear and the two filters differ
    data, z, mask, controls = _data()
    cov0 = data.initial_cov.clone()
    cov0[4, 4] = math.radians(30.0) ** 2  # p004_blend's "unknown heading" option
    model = GnssImuModel(planar=True, dtype=f64)
    ekf = _run(EKF(model), z, mask, controls, data.initial_mean, cov0)
    ukf = _run(UKF(model, sigma_points=_sigma_points(), redraw_after_predict=True), z, mask, controls, data.initial_mean, cov0)
    gap = (ekf.mean[..., :2] - ukf.mean[..., :2]).norm(dim=-1).max()
    assert float(gap) > 1e-3  # millimetres and more, not rounding


@pytest.mark.parametrize("delta", [0.85, 0.3])
def test_paper_eq11_blend_is_the_blend_with_q_doubled(delta):
    data, z, mask, controls = _data()
    model = GnssImuModel(planar=True, dtype=f64)
    doubled = GnssImuModel(planar=True, dtype=f64, **{k: math.sqrt(2.0) * v for k, v in _noise(model).items()})
    torch.testing.assert_close(doubled.dynamics.Q, 2.0 * model.dynamics.Q, rtol=1e-14, atol=0.0)
    paper = _run(_blend(model, delta, _PaperEq11Blend), z, mask, controls, data.initial_mean, data.initial_cov)
    ours = _run(_blend(doubled, delta), z, mask, controls, data.initial_mean, data.initial_cov)
    _assert_same(paper, ours)
    # and it is a different filter from the blend with Q once (the printed formula is not harmless)
    once = _run(_blend(model, delta), z, mask, controls, data.initial_mean, data.initial_cov)
    assert float((once.prior_cov - paper.prior_cov).abs().max()) > 1e-4 * float(paper.prior_cov.abs().max())


def test_paper_eq11_blend_is_an_ekf_with_q_doubled_where_dynamics_are_linear():
    model, z, mask, controls, mean0, cov0 = _linear_p004()
    doubled, *_ = _linear_p004(q_scale=2.0)
    paper = _run(_blend(model, 0.85, _PaperEq11Blend), z, mask, controls, mean0, cov0)
    ekf_2q = _run(EKF(doubled), z, mask, controls, mean0, cov0)
    _assert_same(paper, ekf_2q)


def _noise(model: GnssImuModel) -> dict[str, float]:
    dyn = model.dynamics
    out = {k: float(getattr(dyn, k).detach()) for k in NOISE if k != "sigma_position_step"}
    out["sigma_position_step"] = math.sqrt(float(dyn.position_step_var))
    return out
