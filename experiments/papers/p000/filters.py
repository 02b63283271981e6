"""p000's literal UKF: the propagated sigma points reused for the update as they are.

p000 pushes the *propagated* points ``chi_i(k|k-1) = f(chi_i(k-1))`` through ``h`` and forms
``P_zz = R + sum W_i dZ dZ^T`` and ``P_xz = sum W_i dX dZ^T`` from them, while its predicted
covariance is ``P- = sum W_i dX dX^T + Q``.  The points do not carry ``Q``, so ``P_zz`` and
``P_xz`` miss ``H Q H^T`` and ``Q H^T``: the gain is too small whenever ``Q`` is not negligible
next to the propagated spread.  :class:`~difffilter.filters.UKF` with
``redraw_after_predict=False`` (the project's variant) extends the points by ``x- +- gamma
sqrt(Q)_i`` so the moments see the whole ``P-``; :class:`LiteralReuseUKF` drops that extension
and is what the paper's equations say.  It is kept for the paper comparison (and its failures are
reported); the library UKF is the hand-tuned filter.
"""

from __future__ import annotations

from difffilter.filters.base import Belief
from difffilter.filters.sigma_points import SigmaPoints
from difffilter.filters.ukf import UKF
from difffilter.models.base import Controls, StateSpaceModel

__all__ = ["LiteralReuseUKF"]


class LiteralReuseUKF(UKF):
    """:class:`~difffilter.filters.UKF` with additive noise and the propagated points reused for
    the update *without* the ``sqrt(Q)`` extension (module docstring).

    Args:
        model: the state-space model (additive noise).
        sigma_points: sigma-point set (p000: ``Julier(kappa=3 - n)``).
    """

    def __init__(self, model: StateSpaceModel, *, sigma_points: SigmaPoints | None = None) -> None:
        super().__init__(model, sigma_points=sigma_points, redraw_after_predict=False, noise="additive")

    def predict(self, belief: Belief, u: Controls) -> Belief:
        out = super().predict(belief, u)
        n = out["mean"].shape[-1]
        keep = out["sigma_wm"].shape[-1] - 2 * n  # the propagated points; the rest is the sqrt(Q) extension
        out["sigma_points"] = out["sigma_points"][..., :keep, :]
        out["sigma_wm"], out["sigma_wc"] = out["sigma_wm"][:keep], out["sigma_wc"][:keep]
        return out
