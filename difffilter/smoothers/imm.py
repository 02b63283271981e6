"""Fixed-interval smoothing of an IMM: Kim's approximate RTS-type IMM smoother."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..filters.base import Belief, FilterResult, RecursiveFilter
from ..mixers.imm import IMM, combine_gaussians
from ..models.base import Controls
from .base import Smoother, rts_step, smoother_gains
from .result import SmootherResult
from .transition import check_smoothable, transition_cross_covariance

__all__ = ["IMMSmoother"]


class IMMSmoother(Smoother):
    """Kim's fixed-interval IMM smoother (Kim 1994; the RTS form of Murphy's "Switching Kalman
    filters", 1998), batched and differentiable.

    From the IMM's per-mode posteriors ``(x^j_t, P^j_t)`` and mode probabilities ``mu^j_t``, for
    ``t = T-1 .. 0`` with smoothed ``(x^i_{t|T}, P^i_{t|T}, mu^i_{t|T})`` known:

    1. ``P(j at t-1 | i at t, z_{<t}) = Pi[j, i] mu^j_{t-1} / c_i``, ``c_i = sum_j Pi[j, i] mu^j_{t-1}``;
       ``U[j, i] = mu^i_{t|T} P(j | i)``, ``mu^j_{t-1|T} = sum_i U[j, i]``, ``W[i|j] = U[j, i] / mu^j_{t-1|T}``;
    2. for every pair, one RTS step from mode ``j``'s posterior through mode ``i``'s prediction
       (the mode filter's own ``predict`` and cross-covariance):
       ``x^{ji} = x^j + G^{ji} (x^i_{t|T} - x^{ji}_-)``, ``P^{ji} = P^j + G^{ji}(P^i_{t|T} - P^{ji}_-)G^{ji T}``;
    3. ``x^j_{t-1|T}``, ``P^j_{t-1|T}``: the ``W[.|j]``-mixture of the ``x^{ji}`` moment-matched; the
       output is the ``mu_{t-1|T}``-mixture of the modes (as the IMM's output).

    The approximation is Kim's: step 1 assumes the future measurements carry no information about
    the mode at ``t - 1`` beyond the mode at ``t``.  With one mode, or modes that are all the same,
    it is the RTS smoother exactly.  Probabilities are handled in log space.

    Supported: IMMs whose modes :class:`~difffilter.smoothers.rts.RTSSmoother` supports and share
    the state (no ``embed``/``project`` maps).  Modes of different dimensions are refused: the
    backward step needs ``Cov(x^j_{t-1}, x^i_t)`` across the embedding, which a moment map
    ``(mean, cov) -> (mean, cov)`` does not provide, and the filled-in components (e.g. a CV
    mode's acceleration) have no dynamics to smooth.  Fixed-lag IMM smoothing is not provided.

    Outputs (``SmootherResult``): ``mean``, ``cov`` (combined), ``initial_mean``/``initial_cov``,
    extras ``mode_probs [B, T, M]``, ``mode_means [B, T, M, n]``, ``mode_covs`` (smoothed),
    ``initial_mode_probs [B, M]`` (the mode before the first measurement, smoothed) and
    ``mode_pair_probs [B, T, M, M]``, ``[:, t, j, i] = P(mode j at t - 1, mode i at t | all)``
    in step 1's approximation (``U[j, i]``; at ``t = 0`` the mode before the first measurement):
    the expected transition counts of EM (:func:`difffilter.learn.em.fit_em`).
    ``cross_cov`` is ``None`` (the mixture's lag-one covariance is not formed).
    """

    def __init__(self, imm: IMM, *, time_chunk: int | None = None) -> None:
        if not isinstance(imm, IMM):
            raise TypeError(f"IMMSmoother needs an IMM, got {type(imm).__name__}")
        for j, f in enumerate(imm.filters):
            check_smoothable(f)
            if imm.embed_maps[j] is not None or imm.project_maps[j] is not None:
                raise ValueError(
                    f"IMMSmoother: mode {j} has embed/project maps; smoothing needs modes that share the state "
                    "(the RTS step needs the cross-covariance across the embedding, which moment maps do not give)"
                )
        super().__init__(imm, time_chunk=time_chunk)

    def _pair_moments(self, mode_means: Tensor, mode_covs: Tensor, controls: Controls) -> tuple[Tensor, Tensor, Tensor]:
        """Prediction of every mode ``j``'s posterior by every mode ``i``'s filter: mean
        ``[B, T, j, i, n]``, covariance and cross-covariance ``[B, T, j, i, n, n]``."""
        n = mode_means.shape[-1]
        out = []
        for j in range(mode_means.shape[2]):
            row = []
            for filt in self.filter.filters:
                row.append(
                    self.per_step(lambda m, p, u, f=filt: _predict_packed(f, m, p, u), mode_means[:, :, j], mode_covs[:, :, j], controls)
                )
            out.append(torch.stack(row, 2))
        packed = torch.stack(out, 2)  # [B, T, j, i, n, 1 + 2n]
        return packed[..., 0], packed[..., 1 : n + 1], packed[..., n + 1 :]

    def smooth(self, result: FilterResult, initial: Belief, controls: Controls = None) -> SmootherResult:
        """Backward pass over the IMM's ``result`` of a window that started from ``initial``."""
        tiny = math.log(torch.finfo(result.mean.dtype).tiny)
        means = torch.cat([initial["mode_means"][:, None], result.extras["mode_means"]], 1)  # [B, T+1, M, n]
        covs = torch.cat([initial["mode_covs"][:, None], result.extras["mode_covs"]], 1)
        log_mu = torch.cat([initial["log_mode_probs"][:, None], result.extras["mode_probs"].log()], 1).clamp_min(tiny)
        pm, pc, cross = self._pair_moments(means[:, :-1], covs[:, :-1], controls)
        gains = smoother_gains(cross, pc)
        log_pi = self.filter.log_transition()  # [j, i]
        # per-step views (unbound once: see rts_backward)
        m_t, c_t, l_t, g_t, pm_t, pc_t = (x.unbind(1) for x in (means, covs, log_mu, gains, pm, pc))
        s_mean, s_cov, s_log_mu = m_t[-1], c_t[-1], l_t[-1]
        out_means, out_covs, out_log, out_pairs = [s_mean], [s_cov], [s_log_mu], []
        for t in range(result.mean.shape[1] - 1, -1, -1):
            log_joint = l_t[t][:, :, None] + log_pi  # [B, j, i]
            log_back = log_joint - torch.logsumexp(log_joint, 1, keepdim=True)  # P(j at t-1 | i at t)
            log_u = log_back + s_log_mu[:, None, :]
            out_pairs.append(log_u)
            s_log_prev = torch.logsumexp(log_u, 2).clamp_min(tiny)  # [B, j]
            w = torch.exp(log_u - s_log_prev[..., None])  # W[i | j]
            x_ji, p_ji = rts_step(m_t[t][:, :, None], c_t[t][:, :, None], g_t[t], pm_t[t], pc_t[t], s_mean[:, None], s_cov[:, None])
            s_mean, s_cov = combine_gaussians(w, x_ji, p_ji)
            s_log_mu = s_log_prev - torch.logsumexp(s_log_prev, -1, keepdim=True)
            out_means.append(s_mean)
            out_covs.append(s_cov)
            out_log.append(s_log_mu)
        rev = lambda xs: torch.stack(xs[::-1], 1)  # noqa: E731
        mode_means, mode_covs, log_probs = rev(out_means), rev(out_covs), rev(out_log)  # [B, T+1, ...]
        mean, cov = combine_gaussians(log_probs.exp(), mode_means, mode_covs)
        return SmootherResult(
            mean=mean[:, 1:], cov=cov[:, 1:], filtered=result, initial_mean=mean[:, 0], initial_cov=cov[:, 0],
            extras={"mode_probs": log_probs[:, 1:].exp(), "mode_means": mode_means[:, 1:], "mode_covs": mode_covs[:, 1:],
                    "initial_mode_probs": log_probs[:, 0].exp(), "mode_pair_probs": torch.stack(out_pairs[::-1], 1).exp()},
        )  # fmt: skip


def _predict_packed(filt: RecursiveFilter, mean: Tensor, cov: Tensor, u: Controls) -> Tensor:
    """``[N, n, 1 + 2n]``: the filter's prediction (mean, covariance) and its cross-covariance."""
    prior = filt.predict(filt.init_belief(mean, cov), u)
    cross = transition_cross_covariance(filt, mean, cov, u)
    return torch.cat([prior["mean"][..., None], prior["cov"], cross], -1)
