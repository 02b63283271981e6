"""A fused, batch-last engine for the Kalman-family filters, built for ``torch.compile``.

The reference filters (:class:`~difffilter.filters.UKF`, :class:`~difffilter.filters.EKF`, ...)
work batch-first and call batched LAPACK/BLAS kernels on many tiny matrices (8x8 Cholesky
factors, 8x17 products): at a few hundred trajectories the time goes to per-call and per-matrix
overheads, not to arithmetic.  :class:`FusedFilter` runs the *same* filter equations on tensors
laid out batch-last (``mean [n, B]``, ``cov [n, n, B]``) and writes every small matrix operation
(Cholesky factor, triangular solves, products) as element-wise arithmetic over the batch, with
no data-dependent branches.  One filter step is then a single straight-line graph that
``torch.compile`` turns into one vectorised loop over the batch (forward and backward).

What is fused: ``UKF`` (additive noise, redrawn or reused points, any sigma-point set),
``SimplifiedUKF``, ``EKF`` and ``KalmanFilter`` (Joseph form or not), with masks, controls,
angle residuals, state-dependent noise, and belief carry-over for truncated back-propagation.
The wrapped filter's model is shared, so its parameters are trained in place.  Augmented-noise
UKFs, square-root filters and mixers are not fused (their reference implementations stay the
way to run them).

Numerics differ from the reference in one place: the reference Cholesky retries a failing
factor with bounded jitter, the fused factor clamps a non-positive pivot to
``n * eps * max(diag)`` (no branch).  Each clamp is counted per trajectory in
``FilterResult.extras["cholesky_clamps"]`` (``[B, T]``); on positive-definite inputs both agree to rounding.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from ..models.base import Controls, DynamicsModel, MeasurementModel
from .base import Belief, FilterResult, GaussianFilter, slice_controls, through_diffuse_phase
from .diffuse import DIFFUSE_COV
from .ekf import EKF
from .ukf import UKF, SimplifiedUKF

__all__ = ["FusedFilter", "fuse"]

_LOG_2PI = math.log(2.0 * math.pi)
_MIN_RECOMPILE_LIMIT = 64
_MAX_CONTRACTION = 32


# -- element-wise small linear algebra on batch-last tensors [..., B] ---------------------------
def _usum(terms: list[Tensor]) -> Tensor:
    """Sum of a short list of same-shaped tensors as a chain of element-wise additions.

    Used for the short sums over the measurement components in the update, which stay in the
    element-wise form of the code around them.  The sums over sigma points and matrix products
    stay reductions: written this way they measured slower (UKF forward, B = 256: 229-232k vs
    259-265k trajectory-steps/s), as the compiler then streams each output element's terms
    from memory instead of keeping a trajectory's points in cache."""
    acc = terms[0]
    for t in terms[1:]:
        acc = acc + t
    return acc


def _mm(a: Tensor, b: Tensor) -> Tensor:
    """``[i, k, B] @ [k, j, B] -> [i, j, B]`` (either factor may have batch size 1)."""
    return (a[:, :, None] * b[None]).sum(1)


def _t(a: Tensor) -> Tensor:
    return a.transpose(0, 1)


def _sym(a: Tensor) -> Tensor:
    return 0.5 * (a + _t(a))


def _chol(a: Tensor) -> tuple[Tensor, Tensor]:
    """Lower Cholesky factor of ``a [n, n, B]`` and the number of clamped pivots ``[B]``.

    Branch-free: a pivot that is not above ``n * eps * max_j a_jj`` (rounding, a semi-definite
    or a non-finite matrix) is replaced by that floor, so one bad batch element never changes
    the others and the graph has no data-dependent control flow.
    """
    n = a.shape[0]
    eps = torch.finfo(a.dtype).eps
    tiny = torch.finfo(a.dtype).tiny
    diag = torch.stack([a[j, j] for j in range(n)])
    floor = (n * eps) * diag.abs().amax(0) + tiny
    rows: list[list[Tensor]] = [[] for _ in range(n)]  # rows[i][j] = L_ij for j <= i
    clamps = torch.zeros_like(floor)
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s = s - rows[j][k] * rows[j][k]
        ok = s > floor
        clamps = clamps + (~ok).to(a.dtype)
        d = torch.sqrt(torch.where(ok, s, floor))
        rows[j].append(d)
        inv = 1.0 / d
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s = s - rows[i][k] * rows[j][k]
            rows[i].append(s * inv)
    zero = torch.zeros_like(floor)
    return torch.stack([torch.stack(r + [zero] * (n - len(r))) for r in rows]), clamps


def _sigma_offsets(cov: Tensor, gamma: float, has_center: bool) -> tuple[Tensor, Tensor]:
    """Sigma-point offsets ``[S, n, B]`` from the mean (``0`` if centred, ``+-gamma L[:, i]``, the
    order of :class:`~difffilter.filters.SigmaPoints`) of ``cov [n, n, B]``, and clamped pivots."""
    lf, clamps = _chol(cov)
    cols = _t(lf) * gamma  # row i = column i of L
    centre = [torch.zeros_like(cols[:1])] if has_center else []
    return torch.cat(centre + [cols, -cols], 0), clamps


def _solve_lower(lf: Tensor, b: Tensor) -> Tensor:
    """``L^{-1} b`` for lower-triangular ``L [m, m, B]`` and ``b [m, k, B]`` (forward substitution)."""
    m = lf.shape[0]
    xs: list[Tensor] = []
    for i in range(m):
        s = b[i]
        for k in range(i):
            s = s - lf[i, k][None] * xs[k]
        xs.append(s / lf[i, i][None])
    return torch.stack(xs)


def _solve_lower_t(lf: Tensor, b: Tensor) -> Tensor:
    """``L^{-T} b`` for lower-triangular ``L [m, m, B]`` and ``b [m, k, B]`` (back substitution)."""
    m = lf.shape[0]
    xs: list[Tensor | None] = [None] * m
    for i in range(m - 1, -1, -1):
        s = b[i]
        for k in range(i + 1, m):
            s = s - lf[k, i][None] * xs[k]  # type: ignore[operator]
        xs[i] = s / lf[i, i][None]
    return torch.stack(xs)  # type: ignore[arg-type]


def _bl(mat: Tensor, rank: int) -> Tensor:
    """Batch-first ``[..., B?]`` model output of ``rank`` trailing dims -> batch-last (size-1 batch if none)."""
    if mat.ndim == rank:
        return mat[..., None]
    if mat.ndim != rank + 1:
        raise ValueError(f"expected a [{', '.join('d' * rank)}] or [B, ...] tensor from the model, got shape {tuple(mat.shape)}")
    return mat.permute(*range(1, rank + 1), 0)


def _call_points(fn: Callable[..., Tensor], pts: Tensor, u: Controls) -> Tensor:
    """Apply a batch-first model function to points ``[S, d, B]`` (as the view ``[S, B, d]``)."""
    return fn(pts.transpose(1, 2), u).transpose(1, 2)


def _wmean(pts: Tensor, wm: Tensor) -> Tensor:
    """Weighted mean of points ``[S, d, B]`` relative to the first point (see ``ukf.weighted_mean``)."""
    ref = pts[0]
    return ref + ((pts - ref[None]) * wm[:, None, None]).sum(0)


def _wcov(a: Tensor, b: Tensor, wc: Tensor) -> Tensor:
    """``sum_s wc_s a_s b_s^T`` for ``a [S, p, B]``, ``b [S, q, B]`` -> ``[p, q, B]``."""
    return ((wc[:, None, None] * a)[:, :, None] * b[:, None]).sum(0)


_MATMULS = (torch.matmul, torch.Tensor.matmul, torch.Tensor.__matmul__, torch.bmm, torch.mm)


class _SmallMatmulAsSum(torch.overrides.TorchFunctionMode):
    """Inside the fused step, matrix products with a short contraction (a model's ``x @ F.mT``,
    ``H @ x``...) become broadcast multiply-and-sum: the compiler then fuses them with the
    rest of the step instead of calling an external GEMM on tiny matrices, which splits the
    step's kernel in two (measured: 1.30 ms -> 0.76-0.79 ms per UKF step, B = 256)."""

    def __torch_function__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
        if func in _MATMULS and not kwargs and len(args) == 2:
            a, b = args
            if isinstance(a, Tensor) and isinstance(b, Tensor) and a.ndim >= 2 and b.ndim >= 2 and a.shape[-1] <= _MAX_CONTRACTION:
                return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
        return func(*args, **(kwargs or {}))


def _unreferenced(buf: Tensor) -> bool:
    """True if no tensor other than ``buf`` itself (no view, no returned result, no NumPy
    array) shares ``buf``'s memory; False when that cannot be told."""
    try:
        return torch._C._storage_Use_Count(buf.untyped_storage()._cdata) <= 2  # buf + the storage object asked
    except Exception:  # noqa: BLE001 - a private helper; without it, never reuse
        return False


def _overridden(obj: nn.Module, base: type, name: str) -> bool:
    return getattr(type(obj), name) is not getattr(base, name)


class FusedFilter(nn.Module):
    """Batch-last, branch-free, compilable twin of a Kalman-family filter.

    ``FusedFilter(filt)(measurements, initial_mean, initial_cov, mask=None, controls=None,
    belief=None)`` returns the same :class:`~difffilter.filters.FilterResult` as ``filt(...)``
    (same validation, same mask and log-likelihood semantics), computed by a compiled step.

    Args:
        filt: a ``UKF`` with ``noise="additive"`` (redrawn or reused points), a
            ``SimplifiedUKF``, an ``EKF`` or a ``KalmanFilter``.  Its model (and parameters)
            is shared, not copied.
        compile: compile the step with ``torch.compile`` (default).  False runs the same step
            eagerly (slow: thousands of scalar-sized ops per step; for debugging and tests).
            If compilation fails (e.g. no C++ compiler), a warning is issued and the eager
            step is used.
        compile_options: extra keyword arguments for ``torch.compile``.
        cpp_wrapper: generate the code that calls the compiled kernels (buffer allocation,
            argument passing) in C++ instead of Python (inductor's ``cpp_wrapper``; default).
            Measured on 2 cores, float64, B = 256: UKF forward 259-265k -> 289-306k
            trajectory-steps/s, forward+backward 45k -> 57k; compiling takes about 1.6x longer.
        reuse_buffers: without autograd, the per-step outputs go into preallocated buffers;
            keep them after the call and reuse them in the next call of the same shape once no
            result (or view, or NumPy array) of the previous call is alive any more.  Saves the
            page faults of fresh memory (measured: ~20 % of a UKF forward at B = 256) at the cost
            of holding the last call's output memory.  False allocates every call.
        threads: threads of the compiled CPU kernels (inductor's ``cpp.threads``; forward and
            backward).  Default 1: a step is a chain of short loops over the batch, and
            splitting each over threads costs a barrier per loop, measured 5x slower with 2
            threads on a 2-core machine at B = 256 and 4096.  ``None`` uses
            ``torch.get_num_threads()`` at compile time.

    Compilation is specialised on batch size, dtype and the presence of masks and controls;
    the first call for a new combination compiles (seconds to minutes: ~45 s forward, ~3 min
    forward + backward for the 8-state benchmark UKF), later calls reuse it.
    """

    def __init__(
        self,
        filt: GaussianFilter,
        *,
        compile: bool = True,  # noqa: A002
        compile_options: dict[str, Any] | None = None,
        threads: int | None = 1,
        cpp_wrapper: bool = True,
        reuse_buffers: bool = True,
    ) -> None:
        super().__init__()
        kinds = ((SimplifiedUKF, "sukf"), (UKF, "ukf"), (EKF, "ekf"))
        kind = next((k for cls, k in kinds if isinstance(filt, cls)), None)
        base = next((cls for cls, _ in kinds if isinstance(filt, cls)), None)
        same_equations = base is not None and all(
            getattr(type(filt), name) is getattr(base, name) for name in ("predict", "update", "init_belief", "finalize_belief")
        )
        if kind is None or not same_equations:
            raise TypeError(
                f"FusedFilter supports UKF, SimplifiedUKF, EKF and KalmanFilter (not subclasses with their own "
                f"predict/update), got {type(filt).__name__}; run that filter directly"
            )
        if kind == "ukf" and filt.noise != "additive":
            raise ValueError(f"FusedFilter supports UKF(noise='additive') only, got noise={filt.noise!r}")
        # reliability: the fused step has no circular means or state addition (angular models run the reference filter)
        if filt.model.dynamics.angular or (kind != "ekf" and filt.model.measurement.angular):
            states, meas = list(filt.model.dynamics.angular), list(filt.model.measurement.angular)
            raise TypeError(
                "FusedFilter does not compute wrap-aware unscented means: the model declares angular components "
                f"(states {states}, measurements {meas}); run the filter directly"
            )
        self.kind = kind
        self.filter = filt
        self.use_compile = bool(compile)
        self.compile_options = dict(compile_options or {})
        if threads is not None:
            if not isinstance(threads, int) or threads < 1:
                raise ValueError(f"threads must be a positive int or None, got {threads!r}")
        if "mode" not in self.compile_options:  # torch.compile accepts either a mode or options
            opts = dict(self.compile_options.get("options") or {})
            if threads is not None:
                opts.setdefault("cpp.threads", threads)
            opts.setdefault("cpp_wrapper", bool(cpp_wrapper))
            self.compile_options["options"] = opts
        dyn, meas = filt.model.dynamics, filt.model.measurement
        self._static_q = not _overridden(dyn, DynamicsModel, "process_noise")
        self._static_r = not _overridden(meas, MeasurementModel, "measurement_noise")
        self._compiled: Callable[..., Any] | None = None
        self._compile_failed = False
        self.reuse_buffers = bool(reuse_buffers)
        self._kept_outputs: list[Tensor] = []

    @property
    def model(self) -> nn.Module:
        return self.filter.model

    # -- one step, batch-last --------------------------------------------------------------
    def _noise(self, static: Tensor | None, fn: Callable[[Tensor, Controls], Tensor], mean: Tensor, u: Controls) -> Tensor:
        return static if static is not None else _bl(fn(_t(mean), u), 2)

    def _step(self, *args: Any) -> tuple[Tensor, ...]:
        with _SmallMatmulAsSum():
            return self._step_body(*args)

    def _step_body(
        self, m: Tensor, p: Tensor, z: Tensor, mo: Tensor | None, u: Controls, q_static: Tensor | None, r_static: Tensor | None
    ) -> tuple[Tensor, ...]:
        """``m [n, B]``, ``p [n, n, B]``, ``z [B, m]`` (batch-first), ``mo [m, B]`` observed
        (float) or None, batch-last static ``Q``/``R`` or None.  Returns the posterior, the
        prior, the log-likelihood, NIS, observed count and clamped pivots (all batch-last)."""
        filt = self.filter
        dyn, meas = filt.model.dynamics, filt.model.measurement
        n = m.shape[0]
        clamps = torch.zeros_like(m[0])
        q = self._noise(q_static, dyn.process_noise, m, u)

        # ---- predict
        ux = None  # update points and their deviations from the prior mean (unscented updates)
        if self.kind == "ukf":
            sp = filt.sigma_points
            wm, wc = sp.weights(n, m.dtype, m.device)
            g = sp.gamma(n)
            dx, c = _sigma_offsets(p, g, sp.has_center)
            clamps = clamps + c
            prop = _call_points(dyn, m[None] + dx, u)
            xm = _wmean(prop, wm)
            dev = prop - xm[None]
            pp = _sym(_wcov(dev, dev, wc) + q)
            if not filt.redraw_after_predict:
                lq, c = _chol(q)
                clamps = clamps + c
                qcols = (_t(lq) * g).expand(-1, -1, dev.shape[-1])
                ux = torch.cat([dev, qcols, -qcols], 0)
                wq = torch.full((2 * n,), 0.5 / g**2, dtype=m.dtype, device=m.device)
                uwm = torch.cat([wm, torch.zeros_like(wq)])
                uwc = torch.cat([wc, wq])
        else:
            if self.kind == "sukf":
                f = _bl(dyn.matrix(u), 2)
            else:
                f = _bl(filt.transition_jacobian(_t(m), u), 2)
            xm = _call_points(dyn, m[None], u)[0]
            pp = _sym(_mm(_mm(f, p), _t(f)) + q)

        # ---- update
        r = self._noise(r_static, meas.measurement_noise, xm, u)
        if self.kind in ("ukf", "sukf"):
            if ux is None:
                sp = filt.sigma_points
                uwm, uwc = sp.weights(n, m.dtype, m.device)
                ux, c = _sigma_offsets(pp, sp.gamma(n), sp.has_center)
                clamps = clamps + c
            zs = _call_points(meas, xm[None] + ux, u)
            zhat = _wmean(zs, uwm)
            dz = meas.residual(zs.transpose(1, 2), _t(zhat)[None]).transpose(1, 2)
            pzz = _wcov(dz, dz, uwc) + r  # only its lower triangle is read (by _chol)
            pxz = _wcov(ux, dz, uwc)
            hj = None
        else:
            hj = _bl(filt.measurement_jacobian(_t(xm), u), 2)  # [m, n, B] or [m, n, 1]
            zhat = _call_points(meas, xm[None], u)[0]
            pxz = _mm(pp, _t(hj))
            pzz = _mm(hj, pxz) + r
        e = _t(meas.residual(z, _t(zhat)))  # [m, B]
        md = e.shape[0]
        if mo is not None:
            e = e * mo
            pxz = pxz * mo[None]
            pzz = pzz * (mo[:, None] * mo[None]) + torch.diag_embed(_t(1.0 - mo)).permute(1, 2, 0)
            nobs = mo.sum(0)
        else:
            nobs = torch.full_like(m[0], float(md))
        ls, c = _chol(pzz)
        clamps = clamps + c
        sol = _solve_lower(ls, torch.cat([_t(pxz), e[:, None]], 1))  # [m, n + 1, B]
        w, v = sol[:, :-1], sol[:, -1]
        new_m = xm + _usum([w[i] * v[i] for i in range(md)])
        joseph = self.kind == "ekf" and filt.joseph
        if joseph:
            gain = _t(_solve_lower_t(ls, w))  # K = W^T L^{-1}: [n, m, B]
            hm, rm = hj, r
            if mo is not None:
                hm = hj * mo[:, None]
                rm = r * (mo[:, None] * mo[None])
            eye = torch.eye(n, dtype=m.dtype, device=m.device)[..., None]
            a = eye - _mm(gain, hm)
            new_p = _sym(_mm(_mm(a, pp), _t(a)) + _mm(_mm(gain, rm), _t(gain)))
        else:
            new_p = pp - _usum([w[i][:, None] * w[i][None] for i in range(md)])  # P- - W^T W: symmetric as P- is
        maha = _usum([v[i] * v[i] for i in range(md)])
        logdet = 2.0 * _usum([torch.log(ls[i, i]) for i in range(md)])
        ll = -0.5 * (maha + logdet + nobs * _LOG_2PI)
        return new_m, new_p, xm, pp, ll, maha, nobs, clamps

    def _step_fn(self) -> Callable[..., Any]:
        if not self.use_compile or self._compile_failed:
            return self._step
        if self._compiled is None:
            # Graphs are specialised on grad mode, requires_grad of the carried belief, masks and
            # batch size, and every FusedFilter shares the step's code object: allow enough
            # variants that a few filters never fall back to eager execution.
            cfg = torch._dynamo.config
            name = "recompile_limit" if hasattr(cfg, "recompile_limit") else "cache_size_limit"
            if getattr(cfg, name) < _MIN_RECOMPILE_LIMIT:
                setattr(cfg, name, _MIN_RECOMPILE_LIMIT)
            self._compiled = torch.compile(self._step, dynamic=False, **self.compile_options)
        return self._compiled

    def _output_buffers(self, shapes: list[tuple[int, ...]], like: Tensor) -> list[Tensor]:
        """Batch-last output buffers of a forward pass without autograd: the previous call's
        buffers when nothing else references their memory any more (``reuse_buffers``), else
        new ones.  Touching fresh memory costs a page fault per 4 KiB: measured 170-200 us of
        a ~900 us UKF step at B = 256 (two [T, 8, 8, B] covariance buffers)."""
        old = self._kept_outputs
        self._kept_outputs = []
        if (
            self.reuse_buffers
            and [tuple(b.shape) for b in old] == shapes
            and all(b.dtype == like.dtype and b.device == like.device and _unreferenced(b) for b in old)
        ):
            bufs = old
        else:
            del old
            bufs = [like.new_empty(shape) for shape in shapes]
        if self.reuse_buffers:
            self._kept_outputs = bufs
        return bufs

    # -- the time loop ---------------------------------------------------------------------
    def forward(
        self,
        measurements: Tensor,
        initial_mean: Tensor | None = None,
        initial_cov: Tensor | None = None,
        mask: Tensor | None = None,
        controls: Controls = None,
        *,
        belief: Belief | None = None,
    ) -> FilterResult:
        """Same arguments and result as :meth:`GaussianFilter.forward` of the wrapped filter;
        ``extras["cholesky_clamps"] [B, T]`` counts clamped Cholesky pivots per step."""
        filt = self.filter
        z, mask3, mean0, cov0 = filt.check_inputs(measurements, initial_mean, initial_cov, mask, controls)
        if belief is None:
            if mean0 is None or cov0 is None:
                raise ValueError("initial_mean and initial_cov are required unless belief= is given")
            with parametrize.cached():
                belief = filt.start_belief(mean0, cov0, slice_controls(controls, 0))
        # reliability: a diffuse prior's first steps run in the reference filter's exact two-part form
        if DIFFUSE_COV in belief:
            return through_diffuse_phase(filt, self.forward, z, mask3, controls, belief)
        bsz, steps, _ = z.shape
        n = filt.state_dim
        if belief["mean"].shape != (bsz, n) or belief["cov"].shape != (bsz, n, n):
            raise ValueError(f"belief must hold mean [B, n] = [{bsz}, {n}] and cov [B, n, n], got {tuple(belief['mean'].shape)}")
        m = _t(belief["mean"]).contiguous()
        p = belief["cov"].permute(1, 2, 0).contiguous()
        mo_all = None if mask3 is None else mask3.to(z.dtype).permute(1, 2, 0)  # [T, m, B]
        outs: list[tuple[Tensor, ...]] = []
        # Without autograd, the per-step means and covariances go straight into preallocated
        # batch-last buffers and each step's tensors are freed at once: the memory of a step is
        # reused by the next one (with a list and a final stack, a forward pass first grows the
        # heap by T steps' worth of fresh pages, then copies them).  With autograd, in-place
        # writes into one buffer would chain T copy nodes, so the list is kept.
        direct = not torch.is_grad_enabled()
        if direct:
            bufs = self._output_buffers([(steps, *shape) for shape in ((n, bsz), (n, n, bsz), (n, bsz), (n, n, bsz))], z)
        with parametrize.cached():
            dyn, meas = filt.model.dynamics, filt.model.measurement
            q_static = _bl(dyn.Q, 2) if self._static_q else None
            r_static = _bl(meas.R, 2) if self._static_r else None
            if self.kind in ("ukf", "sukf"):  # fill the weight cache now: a first fill inside the graph forces a recompile
                filt.sigma_points.weights(n, z.dtype, z.device)
            step = self._step_fn()
            compiled = self.use_compile and not self._compile_failed
            for t in range(steps):
                args = (m, p, z[:, t], None if mo_all is None else mo_all[t], slice_controls(controls, t), q_static, r_static)
                if compiled and t == 0:
                    try:
                        res = step(*args)
                    except Exception as exc:  # noqa: BLE001 - any compiler failure falls back to the eager step
                        warnings.warn(
                            f"FusedFilter: torch.compile failed ({type(exc).__name__}: {exc}); running the step eagerly", stacklevel=2
                        )
                        self._compile_failed = True
                        step = self._step
                        res = step(*args)
                else:
                    res = step(*args)
                # compiled outputs may come back in another memory layout: keep the inputs'
                # strides fixed so that the compiled step is not specialised again
                m, p = res[0].contiguous(), res[1].contiguous()
                if direct:
                    for buf, val in zip(bufs, res[:4], strict=True):
                        buf[t] = val
                    outs.append(res[4:])
                else:
                    outs.append(res)
        if direct:
            cols = [()] * 4 + list(zip(*outs, strict=False))
            mean, cov, prior_mean, prior_cov = (b.movedim(-1, 0) for b in bufs)
        else:
            cols = list(zip(*outs, strict=False))
            mean = torch.stack(cols[0]).permute(2, 0, 1)
            cov = torch.stack(cols[1]).permute(3, 0, 1, 2)
            prior_mean = torch.stack(cols[2]).permute(2, 0, 1)
            prior_cov = torch.stack(cols[3]).permute(3, 0, 1, 2)
        ll, nis, nobs, clamps = (torch.stack(c, 1) for c in cols[4:])
        final = {"mean": mean[:, -1], "cov": cov[:, -1]}
        return FilterResult(
            mean=mean,
            cov=cov,
            prior_mean=prior_mean,
            prior_cov=prior_cov,
            log_likelihood=ll,
            nis=nis,
            num_observed=nobs,
            final_belief=final,
            extras={"cholesky_clamps": clamps},
        )


def fuse(
    filt: GaussianFilter,
    *,
    compile: bool = True,  # noqa: A002
    threads: int | None = 1,
    cpp_wrapper: bool = True,
    reuse_buffers: bool = True,
    **compile_options: Any,
) -> FusedFilter:
    """``FusedFilter(filt, compile=..., threads=..., cpp_wrapper=..., reuse_buffers=...,
    compile_options=compile_options)``."""
    return FusedFilter(
        filt, compile=compile, compile_options=compile_options, threads=threads, cpp_wrapper=cpp_wrapper, reuse_buffers=reuse_buffers
    )
