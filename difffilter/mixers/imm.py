"""Interacting multiple-model (IMM) mixer over any bank of difffilter filters (p003)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

from ..filters.base import Belief, RecursiveFilter, StepInfo
from ..filters.diffuse import DIFFUSE_COV, DIFFUSE_SCALE
from ..linalg import symmetrize
from ..models.base import Controls
from ..params import RowStochastic, register_constrained

__all__ = ["IMM", "SubspaceEmbedding", "combine_gaussians"]

MomentMap = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]


def combine_gaussians(weights: Tensor, means: Tensor, covs: Tensor) -> tuple[Tensor, Tensor]:
    """Moment-matched Gaussian of a mixture: ``x = sum_j w_j x_j``,
    ``P = sum_j w_j [P_j + (x_j - x)(x_j - x)^T]`` (symmetrised).

    ``weights [..., M]`` (summing to one), ``means [..., M, n]``, ``covs [..., M, n, n]``.
    """
    w = weights[..., None, :]
    mean = (w @ means)[..., 0, :]
    dev = means - mean[..., None, :]
    spread = (dev * weights[..., :, None]).mT @ dev
    cov = (w @ covs.flatten(-2))[..., 0, :].unflatten(-1, covs.shape[-2:]) + spread
    return mean, symmetrize(cov)


class SubspaceEmbedding:
    """Maps between a mode's state and a larger common state of which it is a coordinate subset.

    ``embed(mean [B, n_j], cov)`` places the mode's components at ``indices`` of the common state
    ``[B, N]`` and fills the others with ``fill_mean`` and independent variance
    ``fill_variance``; ``project(mean [B, N], cov)`` selects ``indices`` back.  Pass the bound
    methods to :class:`IMM` as ``embed``/``project`` entries.

    Args:
        indices: position in the common state of each of the mode's ``n_j`` components.
        common_dim: ``N``.
        fill_mean, fill_variance: scalar or ``[N]`` values for the components the mode lacks
            (entries at ``indices`` are ignored).
    """

    def __init__(
        self, indices: Sequence[int], common_dim: int, *, fill_mean: float | Tensor = 0.0, fill_variance: float | Tensor = 1.0
    ) -> None:
        idx = [int(i) for i in indices]
        if len(set(idx)) != len(idx) or not all(0 <= i < common_dim for i in idx):
            raise ValueError(f"indices must be distinct positions in [0, {common_dim}), got {idx}")
        self.indices = idx
        self.common_dim = int(common_dim)
        self.fill_mean = torch.as_tensor(fill_mean)
        self.fill_variance = torch.as_tensor(fill_variance)

    def _selection(self, like: Tensor) -> tuple[Tensor, Tensor]:
        sel = torch.zeros(self.common_dim, len(self.indices), dtype=like.dtype, device=like.device)
        sel[self.indices, torch.arange(len(self.indices))] = 1.0
        missing = 1.0 - sel.sum(-1)
        return sel, missing

    def embed(self, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
        sel, missing = self._selection(mean)
        fm = self.fill_mean.to(mean).expand(self.common_dim)
        fv = self.fill_variance.to(mean).expand(self.common_dim)
        return mean @ sel.mT + missing * fm, sel @ cov @ sel.mT + torch.diag_embed(missing * fv)

    def project(self, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
        idx = self.indices
        return mean[..., idx], cov[..., idx, :][..., :, idx]


class IMM(RecursiveFilter):
    """Batched interacting multiple-model estimator, computed in log space.

    For modes ``j = 1..M`` (each any difffilter filter: KalmanFilter, EKF, UKF, SimplifiedUKF,
    SquareRootUKF, RCUKF..., kinds may be mixed) with posterior mode probabilities ``w_i`` and
    transition ``Pi[i, j] = P(mode j at k | mode i at k-1)``, one step is

    1. mixing: ``c_j = sum_i Pi[i, j] w_i``, ``mu_{i|j} = Pi[i, j] w_i / c_j``,
       ``x_0j = sum_i mu_{i|j} x_i``, ``P_0j = sum_i mu_{i|j} [P_i + (x_i - x_0j)(x_i - x_0j)^T]``;
    2. each mode predicts from ``(x_0j, P_0j)`` and updates with ``z_k``, giving its innovation
       likelihood ``Lambda_j`` (``StepInfo.log_likelihood``);
    3. ``w_j = Lambda_j c_j / sum_l Lambda_l c_l``, then clamped below at ``prob_floor`` and
       renormalised (so ``w_j >= floor / (1 + M floor)``);
    4. output ``x = sum_j w_j x_j``, ``P = sum_j w_j [P_j + (x_j - x)(x_j - x)^T]``.

    Probabilities are carried as logarithms (``log c_j = logsumexp_i(log Pi[i, j] + log w_i)``,
    the floored normalisation of step 3 by :meth:`RowStochastic.log_value`), so likelihoods as
    small as ``1e-320`` or a 1000-sigma outlier give finite probabilities and gradients.  With
    ``prob_floor=0`` (or while every probability is above the floor) this is the textbook IMM
    (Bar-Shalom); the floor keeps every mode recoverable.  The transition and initial
    probabilities are floored too (:class:`~difffilter.params.RowStochastic`), so
    ``c_j >= floor``.  ``FilterResult.log_likelihood`` holds
    ``log sum_j c_j Lambda_j``, the training signal; ``nis`` is ``sum_j c_j NIS_j``.

    Each mode's belief (with its own extras: square-root factors, residual statistics...) is
    stored in the IMM belief under ``"mode{j}.<key>"``.  Before each mode's prediction its belief
    is rebuilt from the mixed moments with the mode's ``init_belief`` (so derived entries such
    as Cholesky factors follow the mixed covariance), except for the entries the mode filter
    lists in its class attribute ``memory_keys`` (the filter's own memory, e.g. RCUKF's residual
    covariance), which each mode keeps.

    Modes of different state dimensions share a common state of dimension
    ``N = max_j n_j``: ``embed[j](mean_j, cov_j) -> (mean, cov)`` maps mode ``j`` into it and
    ``project[j]`` back (``None`` entries, or omitting both, mean identity).  Example, a
    constant-velocity mode ``[px, vx, py, vy]`` with a constant-acceleration mode
    ``[px, vx, ax, py, vy, ay]``::

        cv_in_ca = SubspaceEmbedding([0, 1, 3, 4], 6, fill_variance=1.0)  # acceleration ~ N(0, 1)
        imm = IMM([KalmanFilter(cv), KalmanFilter(ca)], transition=torch.tensor([[0.95, 0.05], [0.05, 0.95]]),
                  initial_probs=torch.tensor([0.5, 0.5]),
                  embed=[cv_in_ca.embed, None], project=[cv_in_ca.project, None])
        out = imm(z, initial_mean_6, initial_cov_6)   # out.mean [B, T, 6]

    Args:
        filters: the mode filters (all with the same measurement dimension).
        transition: ``[M, M]`` row-stochastic ``Pi``; learnable (:class:`RowStochastic` with
            ``prob_floor``), read/set as ``imm.transition``.
        initial_probs: ``[M]`` mode probabilities before the first step; learnable, read/set as
            ``imm.initial_probs``.
        embed, project: per-mode maps to/from the common state (see above).
        prob_floor: lower bound of transition, initial and posterior mode probabilities.

    Outputs (``FilterResult`` extras): ``mode_probs [B, T, M]`` (posterior), ``mode_means
    [B, T, M, N]``, ``mode_covs [B, T, M, N, N]`` (posterior, in the common state),
    ``mode_log_likelihoods [B, T, M]`` (``log Lambda_j``).
    """

    record_keys = ("mode_means", "mode_covs", "mode_log_likelihoods")

    def __init__(
        self,
        filters: Sequence[RecursiveFilter],
        transition: Tensor,
        initial_probs: Tensor,
        *,
        embed: Sequence[MomentMap | None] | None = None,
        project: Sequence[MomentMap | None] | None = None,
        prob_floor: float = 1e-6,
    ) -> None:
        super().__init__()  # no single model: the modes hold theirs
        filters = list(filters)
        if not filters or not all(isinstance(f, RecursiveFilter) for f in filters):
            raise TypeError("filters must be a non-empty sequence of difffilter recursive filters (RecursiveFilter)")
        num = len(filters)
        mdims = {f.measurement_dim for f in filters}
        if len(mdims) != 1:
            raise ValueError(f"all mode filters must share the measurement dimension, got {sorted(mdims)}")
        if not 0.0 <= prob_floor < 1.0 / num:
            raise ValueError(f"prob_floor must lie in [0, 1/M) = [0, {1.0 / num}), got {prob_floor}")
        self.filters = nn.ModuleList(filters)
        self._common_dim = max(f.state_dim for f in filters)
        self.embed_maps = self._check_maps("embed", embed, num)
        self.project_maps = self._check_maps("project", project, num)
        for j, f in enumerate(filters):
            if f.state_dim != self._common_dim and (self.embed_maps[j] is None or self.project_maps[j] is None):
                raise ValueError(
                    f"mode {j} has state dimension {f.state_dim} != common dimension {self._common_dim}: give embed[j] and project[j] maps"
                )
        dtype = next((d for d in (f._param_dtype() for f in filters) if d is not None), None)
        transition = self._check_probs("transition", transition, (num, num), dtype)
        initial_probs = self._check_probs("initial_probs", initial_probs, (num,), dtype)
        self.prob_floor = float(prob_floor)
        try:
            register_constrained(self, "transition", transition, RowStochastic(prob_floor))
            register_constrained(self, "initial_probs", initial_probs, RowStochastic(prob_floor))
        except ValueError as exc:
            raise ValueError(f"transition/initial_probs: {exc}") from exc

    # -- construction helpers ------------------------------------------------------------------
    @staticmethod
    def _check_maps(name: str, maps: Sequence[MomentMap | None] | None, num: int) -> list[MomentMap | None]:
        if maps is None:
            return [None] * num
        maps = list(maps)
        if len(maps) != num or not all(m is None or callable(m) for m in maps):
            raise ValueError(f"{name} must be a sequence of {num} callables (or None for identity)")
        return maps

    @staticmethod
    def _check_probs(name: str, value: Tensor, shape: tuple[int, ...], dtype: torch.dtype | None) -> Tensor:
        if not isinstance(value, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor of shape {list(shape)}")
        if tuple(value.shape) != shape:
            raise ValueError(f"{name} must have shape {list(shape)}, got {tuple(value.shape)}")
        if dtype is not None:
            value = value.to(dtype)
        elif not value.is_floating_point():
            value = value.to(torch.get_default_dtype())
        if not bool(torch.isfinite(value).all()) or bool((value < 0).any()):
            raise ValueError(f"{name} must hold finite non-negative probabilities")
        if not torch.allclose(value.sum(-1), torch.ones((), dtype=value.dtype), atol=1e-6):
            raise ValueError(f"{name} rows must sum to 1, got sums {value.sum(-1).tolist()}")
        return value

    # -- dimensions ----------------------------------------------------------------------------
    @property
    def state_dim(self) -> int:
        return self._common_dim

    @property
    def measurement_dim(self) -> int:
        return self.filters[0].measurement_dim

    @property
    def num_modes(self) -> int:
        return len(self.filters)

    # -- log-probabilities -----------------------------------------------------------------------
    def _log_param(self, name: str) -> Tensor:
        par = self.parametrizations[name]  # type: ignore[index]
        return par[0].log_value(par.original)

    def log_transition(self) -> Tensor:
        """``log Pi [M, M]`` computed stably from the raw logits."""
        return self._log_param("transition")

    # -- per-mode beliefs ------------------------------------------------------------------------
    @staticmethod
    def _mode_belief(belief: Belief, j: int) -> Belief:
        prefix = f"mode{j}."
        return {k[len(prefix) :]: v for k, v in belief.items() if k.startswith(prefix)}

    def _to_common(self, j: int, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
        emb = self.embed_maps[j]
        return (mean, cov) if emb is None else emb(mean, cov)

    def _from_common(self, j: int, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
        proj = self.project_maps[j]
        return (mean, cov) if proj is None else proj(mean, cov)

    def _diffuse_to_common(self, j: int, mean: Tensor, p_inf: Tensor) -> Tensor:
        """A mode's diffuse covariance part in the common state: embedded without the fill
        variance (the difference of two embeddings is exact: the fill sits where the mode's
        part is zero)."""
        if self.embed_maps[j] is None:
            return p_inf
        return self._to_common(j, mean, p_inf)[1] - self._to_common(j, mean, torch.zeros_like(p_inf))[1]

    def _assemble(self, modes: list[Belief], log_probs: Tensor) -> Belief:
        """IMM belief from mode beliefs and log mode probabilities ``[B, M]``."""
        out: Belief = {}
        means, covs, diffuse = [], [], []
        for j, mb in enumerate(modes):
            out.update({f"mode{j}.{k}": v for k, v in mb.items()})
            x, p = self._to_common(j, mb["mean"], mb["cov"])
            means.append(x)
            covs.append(p)
            if DIFFUSE_COV in mb:
                diffuse.append(self._diffuse_to_common(j, mb["mean"], mb[DIFFUSE_COV]))
        mode_means, mode_covs = torch.stack(means, -2), torch.stack(covs, -3)
        weights = log_probs.exp()
        out["mean"], out["cov"] = combine_gaussians(weights, mode_means, mode_covs)
        out["mode_means"], out["mode_covs"], out["log_mode_probs"] = mode_means, mode_covs, log_probs
        if diffuse:
            mode_diffuse = torch.stack(diffuse, -3)
            out["mode_diffuse_covs"] = mode_diffuse
            out[DIFFUSE_COV] = symmetrize(
                (weights[..., None, :] @ mode_diffuse.flatten(-2))[..., 0, :].unflatten(-1, mode_diffuse.shape[-2:])
            )
            out[DIFFUSE_SCALE] = modes[0][DIFFUSE_SCALE]
        return out

    def init_belief(self, mean: Tensor, cov: Tensor) -> Belief:
        modes = [f.init_belief(*self._from_common(j, mean, cov)) for j, f in enumerate(self.filters)]
        log_probs = self._log_param("initial_probs").expand(mean.shape[0], self.num_modes)
        out = self._assemble(modes, log_probs)
        out["mode_log_likelihoods"] = torch.zeros_like(log_probs)
        return out

    def attach_diffuse(self, belief: Belief, diffuse_cov: Tensor, scale: Tensor) -> Belief:
        modes = [
            f.attach_diffuse(self._mode_belief(belief, j), self._from_common(j, belief["mean"], diffuse_cov)[1], scale)
            for j, f in enumerate(self.filters)
        ]
        out = self._assemble(modes, belief["log_mode_probs"])
        out["mode_log_likelihoods"] = belief["mode_log_likelihoods"]
        return out

    def sensitivity(self, mean: Tensor, u: Controls) -> Tensor | None:  # type: ignore[override]
        """The modes' rows (modes of the common dimension; None if there are none)."""
        rows = [f.sensitivity(mean, u) for f in self.filters if f.state_dim == self._common_dim]
        return torch.cat(rows, -2) if rows else None

    def record(self, belief: Belief) -> dict[str, Tensor]:
        out = {k: belief[k] for k in self.record_keys}
        if "mode_diffuse_covs" in belief:
            out["mode_covs"] = out["mode_covs"] + belief[DIFFUSE_SCALE][..., None, None, None] * belief["mode_diffuse_covs"]
        out["mode_probs"] = belief["log_mode_probs"].exp()
        return out

    # -- one cycle -------------------------------------------------------------------------------
    def predict(self, belief: Belief, u: Controls) -> Belief:
        log_w = belief["log_mode_probs"]  # [B, M] posterior at k-1
        log_joint = log_w[..., :, None] + self.log_transition()  # [B, i, j]
        log_c = torch.logsumexp(log_joint, -2)
        mix = torch.exp(log_joint - log_c[..., None, :])  # mu_{i|j}
        xs, ps = belief["mode_means"], belief["mode_covs"]  # [B, M, N], [B, M, N, N]
        x0 = mix.mT @ xs  # [B, j, N]
        dev = xs[:, None, :, :] - x0[:, :, None, :]  # [B, j, i, N]
        spread = (dev * mix.mT[..., None]).mT @ dev
        p0 = (mix.mT @ ps.flatten(-2)).unflatten(-1, ps.shape[-2:]) + spread
        p0 = symmetrize(p0)
        diffuse = belief.get("mode_diffuse_covs")
        if diffuse is not None:
            # the diffuse parts mix linearly; the means' spread is finite and sits in p0
            d0 = symmetrize((mix.mT @ diffuse.flatten(-2)).unflatten(-1, diffuse.shape[-2:]))
        priors = []
        for j, f in enumerate(self.filters):
            old = self._mode_belief(belief, j)
            fresh = f.init_belief(*self._from_common(j, x0[:, j], p0[:, j]))
            if diffuse is not None:
                fresh = f.attach_diffuse(fresh, self._from_common(j, x0[:, j], d0[:, j])[1], belief[DIFFUSE_SCALE])
            memory = getattr(f, "memory_keys", ())
            mixed = {**old, **{k: v for k, v in fresh.items() if k not in memory}}
            priors.append(f.predict(mixed, u))
        return self._assemble(priors, log_c)

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        log_c = belief["log_mode_probs"]  # predicted mode probabilities
        posts, infos = [], []
        for j, f in enumerate(self.filters):
            post, info = f.update(self._mode_belief(belief, j), z, mask, u)
            posts.append(post)
            infos.append(info)
        log_lik = torch.stack([i.log_likelihood for i in infos], -1)  # [B, M]
        log_joint = log_lik + log_c
        # A fully missing step has Lambda_j = 1 for every mode: its likelihood is exactly 1.
        total = torch.where(infos[0].num_observed > 0, torch.logsumexp(log_joint, -1), torch.zeros_like(log_c[..., 0]))
        log_w = torch.log_softmax(log_joint, -1)
        if self.prob_floor > 0:
            # Clamping (not an affine floor) leaves the textbook recursion exact whenever no mode
            # is below the floor, e.g. a fully missing step then gives w = c exactly.
            log_w = torch.clamp(log_w, min=math.log(self.prob_floor))
            log_w = log_w - torch.logsumexp(log_w, -1, keepdim=True)
        out = self._assemble(posts, log_w)
        out["mode_log_likelihoods"] = log_lik
        nis = (log_c.exp() * torch.stack([i.nis for i in infos], -1)).sum(-1)
        flags = [f for f in (i.flags() for i in infos) if f is not None]
        # The mode probabilities rest on differences of the modes' log-likelihoods, each of which
        # carries a rounding error of about eps * |log-likelihood|: past 1e-2 nats (a 1e10
        # outlier gives 5e19 nats, ~1e4 of rounding in float64) the probabilities are noise,
        # and the mixing feeds that noise back into every mode (measured: 1e8 m off within
        # four steps), so the step is flagged.
        eps = torch.finfo(log_lik.dtype).eps
        flags.append(~(eps * log_lik.abs().amax(-1) <= 1e-2) & (infos[0].num_observed > 0))
        jitters = [i.jitter for i in infos if i.jitter is not None]  # each >= 0: the sum is 0 iff none was repaired
        untrusted = torch.stack(flags, -1).any(-1)
        return out, StepInfo(
            total, nis, infos[0].num_observed, untrusted=untrusted, jitter=sum(jitters[1:], jitters[0]) if jitters else None
        )
