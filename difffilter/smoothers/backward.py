"""The sequential RTS backward recursion with a hand-written reverse mode.

:func:`sequential_rts` runs the recursion of :func:`~difffilter.smoothers.base.rts_backward`
(plain state differences; angular states take the autograd loop there) as one autograd node:
the forward loop does two small products per step without recording a graph, the lag-one
cross-covariances ``G_t P_{t|T}`` of all steps come from one batched product afterwards, and the
backward loop carries only the adjoints of the smoothed moments, ``a_{t} = G_t^T a_{t-1} + ...``,
``A_t = G_t^T sym(A_{t-1}) G_t + ...``; every other gradient (of the gains, filtered and
predicted moments) is then formed for all steps at once.  Autograd's replay of the loop would
instead run ~10 small operations per step, some of them on the slow per-matrix path of ``bmm``.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from ..linalg import symmetrize

__all__ = ["sequential_rts"]


def _mv(a: Tensor, v: Tensor) -> Tensor:
    return (a @ v[..., None])[..., 0]


class _SequentialRTS(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx: Any, mean: Tensor, cov: Tensor, prior_mean: Tensor, prior_cov: Tensor, gains: Tensor, m0: Tensor, p0: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        steps = mean.shape[1]
        m_t, p_t, g_t = mean.unbind(1), cov.unbind(1), gains.unbind(1)
        pm_t, pp_t = prior_mean.unbind(1), prior_cov.unbind(1)
        s_mean, s_cov = m_t[-1], p_t[-1]
        means, covs = [s_mean], [s_cov]
        for t in range(steps - 1, -1, -1):
            prev_m, prev_p = (m_t[t - 1], p_t[t - 1]) if t > 0 else (m0, p0)
            s_mean = prev_m + _mv(g_t[t], s_mean - pm_t[t])
            s_cov = symmetrize(prev_p + g_t[t] @ (s_cov - pp_t[t]) @ g_t[t].mT)
            means.append(s_mean)
            covs.append(s_cov)
        m_init, p_init = means.pop(), covs.pop()
        s_means, s_covs = torch.stack(means[::-1], 1), torch.stack(covs[::-1], 1)
        cross = gains @ s_covs
        ctx.save_for_backward(prior_mean, prior_cov, gains, s_means, s_covs)
        ctx.set_materialize_grads(False)  # unused outputs' gradients stay None: their adjoints are skipped
        return s_means, s_covs, cross, m_init, p_init

    @staticmethod
    @once_differentiable
    def backward(
        ctx: Any, d_means: Tensor | None, d_covs: Tensor | None, d_cross: Tensor | None, d_m0: Tensor | None, d_p0: Tensor | None
    ) -> tuple[Tensor | None, ...]:
        prior_mean, prior_cov, gains, s_means, s_covs = ctx.saved_tensors
        bsz, steps, n = s_means.shape
        g_t = gains.unbind(1)
        # the means' recursion never reads the covariances: a loss of the means alone (the usual
        # training loss) needs no covariance adjoints at all
        am, a_m = _mean_adjoints(g_t, d_means, d_m0, s_means)
        d_gain = am[..., :, None] * (s_means - prior_mean)[..., None, :]
        d_mean = torch.cat([am[:, 1:], a_m[:, None]], 1)
        d_pm = -_mv(gains.mT, am)
        d_cov = d_pp = d_init_p = None
        if d_covs is not None or d_cross is not None or d_p0 is not None:
            # the smoothed cov at t receives G_t^T dX_t from cross_t = G_t P_{t|T}, and its output's gradient
            extra = gains.mT @ d_cross if d_cross is not None else None
            extra = d_covs if extra is None else extra if d_covs is None else extra + d_covs
            a_p = s_covs.new_zeros(bsz, n, n) if d_p0 is None else d_p0
            extra_t = extra.unbind(1) if extra is not None else None
            adj = []  # adjoint of the symmetrised output of step t, P_{t-1|T}
            for t in range(steps):
                a_p = symmetrize(a_p)
                adj.append(a_p)
                a_p = g_t[t].mT @ a_p @ g_t[t]
                if extra_t is not None:
                    a_p = a_p + extra_t[t]
            ap = torch.stack(adj, 1)
            diff_p = s_covs - prior_cov
            d_gain = d_gain + ap @ gains @ (diff_p + diff_p.mT)
            if d_cross is not None:
                d_gain = d_gain + d_cross @ s_covs.mT
            d_pp = -(gains.mT @ ap @ gains)
            d_cov = torch.cat([ap[:, 1:], a_p[:, None]], 1)
            d_init_p = ap[:, 0]
        return d_mean, d_cov, d_pm, d_pp, d_gain, am[:, 0], d_init_p


def _mean_adjoints(g_t: tuple[Tensor, ...], d_means: Tensor | None, d_m0: Tensor | None, like: Tensor) -> tuple[Tensor, Tensor]:
    """Adjoints ``[B, T, n]`` of the smoothed means ``x_{t-1|T}`` that step ``t`` outputs (``x_{-1|T}``
    first) and that of ``x_{T-1|T}``, from the gradients of the means and of ``x_{-1|T}``."""
    a_m = like.new_zeros(like.shape[0], like.shape[-1]) if d_m0 is None else d_m0
    extra = d_means.unbind(1) if d_means is not None else None
    adj = []
    for t in range(len(g_t)):
        adj.append(a_m)
        a_m = _mv(g_t[t].mT, a_m)
        if extra is not None:
            a_m = a_m + extra[t]
    return torch.stack(adj, 1), a_m


def sequential_rts(
    mean: Tensor, cov: Tensor, prior_mean: Tensor, prior_cov: Tensor, gains: Tensor, initial_mean: Tensor, initial_cov: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The RTS backward recursion over time, one autograd node (module docstring).

    Arguments and results as :func:`~difffilter.smoothers.base.rts_backward` (without angular
    states).  Not for ``torch.func`` transforms or double backward (``rts_backward`` then takes
    its autograd loop).
    """
    return _SequentialRTS.apply(mean, cov, prior_mean, prior_cov, gains, initial_mean, initial_cov)
