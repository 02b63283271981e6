"""Elevation-dependent coloured pseudorange noise: p001's mis-specified family and the filter
family that can learn it.

A satellite seen at elevation ``el`` has AR(1) noise ``v_k = Psi(el) v_{k-1} + eta_k`` whose
stationary standard deviation and correlation time grow towards the horizon (longer paths through
the atmosphere and more multipath; the law below, with ``s = 1 / sin(el)``):

.. math::
    \\sigma_v(el) = \\sigma_z\\, s^{\\lambda}, \\qquad \\tau(el) = \\tau_z\\, s^{\\kappa}, \\qquad
    \\Psi(el) = e^{-\\Delta t / \\tau(el)}, \\qquad R_\\eta(el) = \\sigma_v(el)^2 (1 - \\Psi(el)^2).

``lambda = kappa = 0`` is p001's filter (one ``Psi`` and one ``R`` for every satellite):
``sigma_z^2 = R / (1 - Psi^2)`` and ``tau_z = -dt / ln Psi`` give the same filter to rounding
(tested), so the paper's hand-tuned filter is a member of the learnable family.
:func:`elevation_noise` is the law, used by the simulator (the truth) and by
:class:`ElevationPseudorange` (the filter's measurement model, read by
:class:`~difffilter.filters.ColoredNoiseUKF` built with ``psi=None``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from difffilter._util import control
from difffilter.models.base import Controls
from difffilter.models.navigation.pseudorange import GnssStateLayout, PseudorangeMeasurement
from difffilter.params import Bounded, Positive, register_constrained

__all__ = ["EXPONENT_BOUND", "ElevationPseudorange", "elevation_noise", "paper_law"]

#: The exponents ``lambda``, ``kappa`` are learnable inside ``(-EXPONENT_BOUND, EXPONENT_BOUND)``.
EXPONENT_BOUND = 4.0
_MIN_SIN = 1e-3  # elevations below ~0.06 deg are clamped (satellites are masked far above that)


def elevation_noise(
    elevation: Tensor,
    dt: float | Tensor,
    *,
    sigma_zenith: float | Tensor,
    sigma_exponent: float | Tensor,
    tau_zenith: float | Tensor,
    tau_exponent: float | Tensor,
) -> tuple[Tensor, Tensor]:
    """``(Psi, R_eta)`` of satellites at ``elevation`` (rad, any shape) for the epoch interval ``dt`` (s).

    Args:
        sigma_zenith: stationary standard deviation of the noise at the zenith (m).
        sigma_exponent: ``lambda`` (``sigma_v = sigma_z / sin(el)^lambda``).
        tau_zenith: correlation time at the zenith (s).
        tau_exponent: ``kappa`` (``tau = tau_z / sin(el)^kappa``).
    """
    csc_log = -torch.log(torch.sin(elevation).clamp(min=_MIN_SIN))  # ln(1 / sin el) >= 0
    var = sigma_zenith**2 * torch.exp(2.0 * sigma_exponent * csc_log)
    tau = tau_zenith * torch.exp(tau_exponent * csc_log)
    psi = torch.exp(-dt / tau)
    return psi, var * (1.0 - psi * psi)


def paper_law(*, psi: float, eta_sigma: float, dt: float) -> dict[str, float]:
    """The law's values that reproduce one ``Psi`` and driving-noise std ``eta_sigma`` for every
    satellite (p001's filter): exponents 0, ``sigma_z = eta_sigma / sqrt(1 - Psi^2)``,
    ``tau_z = -dt / ln Psi``."""
    if not 0.0 < psi < 1.0:
        raise ValueError(f"psi must lie in (0, 1) for a correlation time, got {psi}")
    return {
        "sigma_zenith": eta_sigma / math.sqrt(1.0 - psi * psi),
        "sigma_exponent": 0.0,
        "tau_zenith": -dt / math.log(psi),
        "tau_exponent": 0.0,
    }


class ElevationPseudorange(PseudorangeMeasurement):
    """Pseudoranges whose coloured noise follows :func:`elevation_noise` (module docstring).

    Inputs ``u["elevation"] [..., K]`` (rad) and ``u["dt"] [..., 1]`` (or the constructor's
    ``dt``) besides the pseudorange inputs.  ``measurement_noise`` is ``diag(R_eta(el))``;
    :meth:`ar_coefficient` gives ``Psi(el)`` to a :class:`~difffilter.filters.ColoredNoiseUKF`
    built with ``psi=None``.  The parent's ``R`` is a fixed buffer, unused.

    Learnable: ``sigma_zenith``, ``tau_zenith`` (``Positive``), ``sigma_exponent``,
    ``tau_exponent`` (``Bounded(-4, 4)``).
    """

    def __init__(
        self,
        *,
        num_satellites: int,
        layout: GnssStateLayout,
        sigma_zenith: float,
        sigma_exponent: float = 0.0,
        tau_zenith: float,
        tau_exponent: float = 0.0,
        dt: float | None = None,
        reduced: bool = True,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__(
            num_satellites=num_satellites, layout=layout, sigma_range=float(sigma_zenith), reduced=reduced, R_structure="fixed", dtype=dtype
        )
        for name, value in (("sigma_zenith", sigma_zenith), ("tau_zenith", tau_zenith)):
            if not (math.isfinite(float(value)) and float(value) > 0.0):
                raise ValueError(f"{name} must be a positive number, got {value}")
            register_constrained(self, name, torch.tensor(float(value), dtype=dtype), Positive(1e-6))
        for name, value in (("sigma_exponent", sigma_exponent), ("tau_exponent", tau_exponent)):
            if not abs(float(value)) < EXPONENT_BOUND:
                raise ValueError(f"{name} must lie in (-{EXPONENT_BOUND}, {EXPONENT_BOUND}), got {value}")
            register_constrained(self, name, torch.tensor(float(value), dtype=dtype), Bounded(-EXPONENT_BOUND, EXPONENT_BOUND))
        self.dt = None if dt is None else float(dt)

    def _law(self, u: Controls) -> tuple[Tensor, Tensor]:
        el = control(u, "elevation").to(self.sigma_zenith.dtype)
        if isinstance(u, dict) and "dt" in u:
            dt: float | Tensor = u["dt"].to(el.dtype)  # [..., 1] broadcasts over the satellites
        elif self.dt is not None:
            dt = self.dt
        else:
            raise KeyError("ElevationPseudorange needs u['dt'] [..., 1] or a fixed dt= at construction")
        return elevation_noise(
            el,
            dt,
            sigma_zenith=self.sigma_zenith,
            sigma_exponent=self.sigma_exponent,
            tau_zenith=self.tau_zenith,
            tau_exponent=self.tau_exponent,
        )

    def ar_coefficient(self, u: Controls) -> Tensor:
        """``Psi(el) [..., K]`` of the step whose inputs are ``u``."""
        return self._law(u)[0]

    def measurement_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        return torch.diag_embed(self._law(u)[1])
