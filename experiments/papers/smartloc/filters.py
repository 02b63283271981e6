"""The filters of the smartLoc experiment.

* :class:`SharedPsiColoredUKF` - p001's coloured-noise UKF with ONE AR(1) coefficient for every
  satellite slot: with one slot per satellite (``slots="satellite"``) per-slot coefficients
  over-fit the few satellites of a 283 s drive;
* :class:`SnapshotWLS` - the single-epoch robust least-squares baseline as a (memoryless)
  :class:`~difffilter.filters.protocol.Filter`, so the experiment evaluates it like a filter.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor, nn

from difffilter.filters.colored import ColoredNoiseUKF
from difffilter.filters.protocol import Filter, FilterResult
from difffilter.filters.sigma_points import SigmaPoints
from difffilter.models.base import Controls, StateSpaceModel
from difffilter.params import Bounded, register_constrained

from .wls import single_epoch_wls

__all__ = ["Shared", "SharedPsiColoredUKF", "SnapshotWLS"]


class Shared(nn.Module):
    """One constrained scalar shared by ``size`` components: ``value = inner(raw) * ones(size)``
    (a constraint for ``register_constrained``; ``right_inverse`` takes the scalar or ``size``
    equal values and inverts ``inner`` on it)."""

    def __init__(self, *, inner: nn.Module, size: int) -> None:
        super().__init__()
        self.inner, self.size = inner, int(size)

    def forward(self, raw: Tensor) -> Tensor:
        return self.inner(raw).expand(self.size)

    def right_inverse(self, value: Tensor) -> Tensor:
        v = value.reshape(-1)
        if not bool(torch.allclose(v, v[:1].expand_as(v))):
            raise ValueError(f"a shared parameter needs equal components, got {v.tolist()}")
        return self.inner.right_inverse(v[0])


class SharedPsiColoredUKF(ColoredNoiseUKF):
    """:class:`~difffilter.filters.colored.ColoredNoiseUKF` (p001) with one AR(1) coefficient
    ``Psi`` for every measurement component: ``v_{k,j} = Psi v_{k-1,j} + eta_{k,j}``.

    ``psi`` still reads as ``[m]`` (all equal); setting it takes a scalar.  Learnable: ``psi``
    (one :class:`~difffilter.params.Bounded` ``(-1, 1)`` scalar, :class:`Shared` by the
    components) and the model's parameters.
    """

    def __init__(self, model: StateSpaceModel, *, psi: float = 0.0, sigma_points: SigmaPoints | None = None) -> None:
        super().__init__(model, psi=psi, sigma_points=sigma_points)
        current = self.psi.detach()
        register_constrained(self, "psi", current[0].clone(), Shared(inner=Bounded(-1.0, 1.0), size=current.shape[0]))


class _Epochs:
    """The fields of :class:`~experiments.papers.smartloc.data.SmartLocData` that
    :func:`~experiments.papers.smartloc.wls.single_epoch_wls` reads, for ``E`` epochs of a batch."""

    def __init__(self, z: Tensor, mask: Tensor, u: Mapping[str, Tensor], origin: Tensor) -> None:
        f64 = torch.float64
        self._z = z.to(f64)
        self.mask = mask
        self.sat_enu = u["sat_pos"].to(f64)
        self.glonass = u["glonass"].to(f64) > 0.5
        self.pr_var = torch.where(mask, u["pr_var"].to(f64), 1.0)
        self.elevation = torch.full_like(self._z, 90.0)  # the batch mask already holds the elevation mask
        self.origin_ecef = origin.to(f64)
        self.num_slots, self.num_epochs = int(z.shape[-1]), int(z.shape[0])

    def reduced_pseudorange(self) -> Tensor:
        return torch.where(self.mask, self._z, 0.0)


class SnapshotWLS(Filter):
    """Single-epoch robust weighted least squares as a memoryless estimator (smartLoc baseline).

    Each epoch is solved on its own by :func:`~experiments.papers.smartloc.wls.single_epoch_wls`
    (Gauss-Newton for ``[E, N, U, b, beta]``, Sagnac term, weights ``1 / pr_var``, robust
    reweighting) on the observed pseudoranges of the batch.  Output in the odometry layout
    ``[E, N, U, yaw, b, d, beta]`` with yaw and drift 0; covariance = the nominal WLS covariance
    ``(J^T W J + prior)^{-1}`` (robust weights not included) and ``unknown_var`` for yaw and
    drift.  No innovations: ``log_likelihood`` and ``nis`` are NaN.  Nothing is learnable.

    Args:
        model: the odometry + pseudorange model (gives the ENU frame origin and ``K``).
        robust, threshold: as :func:`single_epoch_wls` (default Cauchy, ``c = 1.5``).
    """

    carries_belief = False

    def __init__(self, model: StateSpaceModel, *, robust: str | None = "cauchy", threshold: float = 1.5, unknown_var: float = 1e6) -> None:
        super().__init__(model)
        self.robust, self.threshold, self.unknown_var = robust, float(threshold), float(unknown_var)

    def forward(  # type: ignore[override]
        self,
        measurements: Tensor,
        initial_mean: Tensor | None = None,
        initial_cov: Tensor | None = None,
        mask: Tensor | None = None,
        controls: Controls = None,
        *,
        belief: dict[str, Tensor] | None = None,
    ) -> FilterResult:
        z, mask, _, _ = self.check_inputs(measurements, initial_mean, initial_cov, mask, controls)
        if not isinstance(controls, dict):
            raise TypeError("SnapshotWLS needs the smartLoc controls dict (sat_pos, glonass, pr_var)")
        bsz, steps, k = z.shape
        obs = torch.ones_like(z, dtype=torch.bool) if mask is None else mask
        flat = {key: v.reshape(bsz * steps, *v.shape[2:]) for key, v in controls.items()}
        epochs = _Epochs(z.reshape(-1, k), obs.reshape(-1, k), flat, self.model.measurement.frame_origin)
        sol = single_epoch_wls(epochs, elevation_mask_deg=0.0, robust=self.robust, threshold=self.threshold)  # type: ignore[arg-type]
        x5 = torch.cat([sol.enu, sol.clock[:, None], sol.isb[:, None]], -1)
        valid = torch.isfinite(x5).all(-1)
        x5 = torch.where(valid[:, None], x5, 0.0)
        meas = self.model.measurement
        lay = meas.layout
        state = x5.new_zeros(bsz * steps, self.state_dim)
        cols = [*lay.position, lay.clock_bias, lay.isb]
        state[:, cols] = x5
        jac = meas.jacobian(state, {"sat_pos": epochs.sat_enu, "glonass": epochs.glonass.to(torch.float64)})[..., cols]
        w = torch.where(sol.used, 1.0 / epochs.pr_var, 0.0)
        normal = jac.mT @ (w[..., None] * jac)
        normal[:, 4, 4] = normal[:, 4, 4] + 1e-4  # the loader's 100 m ISB prior
        cov5 = torch.linalg.inv(normal)
        cov5 = torch.where(valid[:, None, None], cov5, torch.eye(5, dtype=cov5.dtype) * self.unknown_var)
        cov = torch.eye(self.state_dim, dtype=cov5.dtype).repeat(bsz * steps, 1, 1) * self.unknown_var
        idx = torch.tensor(cols)
        cov[:, idx[:, None], idx] = cov5
        dtype = measurements.dtype
        mean, cov = state.reshape(bsz, steps, -1).to(dtype), cov.reshape(bsz, steps, self.state_dim, self.state_dim).to(dtype)
        nan = torch.full((bsz, steps), math.nan, dtype=dtype, device=z.device)
        used = sol.used.reshape(bsz, steps, k).sum(-1).to(dtype)
        final = {"mean": mean[:, -1], "cov": cov[:, -1]}
        return FilterResult(mean, cov, mean, cov, nan, nan.clone(), used, final)
