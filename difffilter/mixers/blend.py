"""EKF/UKF prediction blending and switching (p004)."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from ..filters.base import Belief, RecursiveFilter, StepInfo
from ..filters.diffuse import DIFFUSE_COV
from ..filters.ekf import EKF
from ..filters.ukf import UKF
from ..linalg import symmetrize
from ..models.base import Controls, StateSpaceModel
from ..params import Bounded, Positive, register_constrained

__all__ = ["Blend", "Statistics"]

Statistics = Callable[[Controls], tuple[Tensor, Tensor]]


class Blend(RecursiveFilter):
    """Blend of an EKF and a UKF prediction followed by the UKF update (p004).

    From the same posterior ``(x, P)`` both filters predict, and

    .. math::
        x^- = \\delta x^-_E + (1 - \\delta) x^-_U, \\qquad
        P^- = \\delta P^-_E + (1 - \\delta) P^-_U \\; [+ \\delta (1 - \\delta) d d^T], \\quad d = x^-_E - x^-_U

    then the UKF's standard update (points redrawn from ``(x^-, P^-)``).  Each branch already
    contains ``Q`` once, so the convex combination contains it exactly once (p004 adds it a
    second time, which is a misprint).  ``spread=True`` adds the mixture-spread term, making
    ``P^-`` the covariance of the two-component mixture; the default (False) is the paper's
    formula.

    The weight ``delta_k`` (recorded per step as ``result.blend_weight [B, T]``):

    * ``mode="fixed"``: a learnable constant, ``Bounded(0, 1)`` (p004: 0.85).
    * ``mode="switch"``: ``delta = 1`` (EKF) when the motion is near-linear, i.e.
      ``gamma <= gamma_th`` and ``mu <= mu_th``, else ``0`` (UKF); not differentiable in the
      thresholds.
    * ``mode="gate"``: the smooth version
      ``delta = sigmoid((gamma_th - gamma) / t_gamma) * sigmoid((mu_th - mu) / t_mu)``,
      differentiable in the thresholds and temperatures (learnable, ``Positive``), which tends
      to the switch as the temperatures go to zero.

    ``(gamma, mu) = statistics(u_k)`` come from the step's controls, e.g. eqs. (1), (2) of p004
    (:class:`experiments.papers.p004.ImuSwitchingStatistics`: ``gamma`` compares the IMU motion
    noise with the observation noise, ``mu`` the IMU's own accelerations and rates with gravity
    and pi).

    Args:
        ekf: an :class:`~difffilter.filters.EKF` (or a model, to build one).
        ukf: a :class:`~difffilter.filters.UKF` (including SquareRootUKF; or a model, to build
            a default UKF).  Its update is used; its prediction extras for point reuse are
            dropped, since the update's points must come from the blended prior.
        mode: ``"fixed"``, ``"switch"`` or ``"gate"``.
        delta: initial blend weight (``mode="fixed"``), in ``[0, 1]``.
        statistics: ``u -> (gamma [B], mu [B])``, required for switch/gate.
        thresholds: ``(gamma_th, mu_th)`` initial values (positive).
        temperature: gate temperatures, a float for both or ``(t_gamma, t_mu)``.
        spread: add the spread term to the blended covariance.

    Learnable: the models' parameters and ``delta`` or ``gamma_threshold``, ``mu_threshold``,
    ``gamma_temperature``, ``mu_temperature``.
    """

    record_keys = ("blend_weight",)

    def __init__(
        self,
        ekf: EKF | StateSpaceModel,
        ukf: UKF | StateSpaceModel,
        *,
        mode: str = "fixed",
        delta: float = 0.85,
        statistics: Statistics | None = None,
        thresholds: tuple[float, float] = (3.0, 0.1),
        temperature: float | tuple[float, float] = 0.1,
        spread: bool = False,
    ) -> None:
        ekf = EKF(ekf) if isinstance(ekf, StateSpaceModel) else ekf
        ukf = UKF(ukf) if isinstance(ukf, StateSpaceModel) else ukf
        if not isinstance(ekf, EKF):
            raise TypeError(f"ekf must be an EKF or a StateSpaceModel, got {type(ekf).__name__}")
        if not isinstance(ukf, UKF):
            raise TypeError(f"ukf must be a UKF or a StateSpaceModel, got {type(ukf).__name__}")
        if ekf.state_dim != ukf.state_dim or ekf.measurement_dim != ukf.measurement_dim:
            raise ValueError("ekf and ukf must have the same state and measurement dimensions")
        super().__init__(ukf.model)
        if mode not in ("fixed", "switch", "gate"):
            raise ValueError(f"mode must be 'fixed', 'switch' or 'gate', got {mode!r}")
        self.ekf, self.ukf = ekf, ukf
        self.mode = mode
        self.spread = bool(spread)
        self.statistics = statistics
        dtype = ukf._param_dtype() or torch.get_default_dtype()

        def scalar(v: float) -> Tensor:
            return torch.tensor(float(v), dtype=dtype)

        if mode == "fixed":
            if not 0.0 <= delta <= 1.0:
                raise ValueError(f"delta must lie in [0, 1], got {delta}")
            register_constrained(self, "delta", scalar(delta), Bounded(0.0, 1.0))
            return
        if statistics is None or not callable(statistics):
            raise ValueError(f"mode={mode!r} needs statistics: a callable u -> (gamma [B], mu [B])")
        temps = (temperature, temperature) if isinstance(temperature, (int, float)) else tuple(temperature)
        if len(thresholds) != 2 or len(temps) != 2 or min(*thresholds, *temps) <= 0:
            raise ValueError(f"thresholds and temperature must be positive pairs, got {thresholds}, {temperature}")
        register_constrained(self, "gamma_threshold", scalar(thresholds[0]), Positive())
        register_constrained(self, "mu_threshold", scalar(thresholds[1]), Positive())
        register_constrained(self, "gamma_temperature", scalar(temps[0]), Positive())
        register_constrained(self, "mu_temperature", scalar(temps[1]), Positive())

    def blend_weight(self, u: Controls, like: Tensor) -> Tensor:
        """``delta_k [B]`` for the step's controls ``u`` (``like``: a ``[B, n]`` tensor)."""
        bsz = like.shape[0]
        if self.mode == "fixed":
            return self.delta.expand(bsz)
        assert self.statistics is not None
        gamma, mu = self.statistics(u)
        gamma, mu = torch.broadcast_to(gamma, (bsz,)), torch.broadcast_to(mu, (bsz,))
        if self.mode == "switch":
            linear = (gamma <= self.gamma_threshold) & (mu <= self.mu_threshold)
            return linear.to(like.dtype)
        return torch.sigmoid((self.gamma_threshold - gamma) / self.gamma_temperature) * torch.sigmoid(
            (self.mu_threshold - mu) / self.mu_temperature
        )

    def init_belief(self, mean: Tensor, cov: Tensor) -> Belief:
        return self.ukf.init_belief(mean, cov)

    def predict(self, belief: Belief, u: Controls) -> Belief:
        pe = self.ekf.predict(belief, u)
        pu = self.ukf.predict(belief, u)
        d = self.blend_weight(u, belief["mean"])
        xe, xu = pe["mean"], pu["mean"]
        dyn = self.ukf.model.dynamics
        if dyn.angular:  # blend angles along the short arc
            mean = dyn.add(xu, d[:, None] * dyn.residual(xe, xu))
        else:
            mean = d[:, None] * xe + (1.0 - d[:, None]) * xu
        cov = d[:, None, None] * pe["cov"] + (1.0 - d[:, None, None]) * pu["cov"]
        if self.spread:
            dev = dyn.residual(xe, xu)
            cov = cov + (d * (1.0 - d))[:, None, None] * dev[:, :, None] * dev[:, None, :]
        out = {k: v for k, v in pu.items() if not k.startswith("sigma_")}
        out.update(self.ukf.init_belief(mean, symmetrize(cov)))
        if DIFFUSE_COV in pu:
            out[DIFFUSE_COV] = symmetrize(d[:, None, None] * pe[DIFFUSE_COV] + (1.0 - d[:, None, None]) * pu[DIFFUSE_COV])
        out["blend_weight"] = d
        return out

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        return self.ukf.update(belief, z, mask, u)
