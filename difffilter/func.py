"""Filters as functions of their parameters: many parameter sets at once with ``torch.func.vmap``.

A filter (or smoother) is an ``nn.Module`` whose ``forward`` is a pure function of its inputs
and its parameters, so ``torch.func.functional_call`` runs it with parameters given as tensors
and ``torch.func.vmap`` runs it for ``K`` parameter sets in one batched call (hyperparameter
sweeps, ensembles, per-seed training), or takes per-sample gradients (``vmap`` over ``grad``)::

    filters = [KalmanFilter(model_k) for model_k in models]      # K filters of one structure
    params = stack_parameters(filters)                          # {name: [K, ...]}
    out = vmap_filter(filters[0], params, z, m0, P0, mask=mask) # FilterResult, leading dim K
    grads = per_sample_grads(filters[0], params, lambda r: -r.total_log_likelihood.sum(), z, m0, P0)

Supported (tested against a Python loop): :class:`~difffilter.filters.KalmanFilter`,
:class:`~difffilter.filters.ParallelKalmanFilter`, :class:`~difffilter.filters.EKF`,
:class:`~difffilter.filters.IteratedEKF`, :class:`~difffilter.filters.UKF`,
:class:`~difffilter.filters.SquareRootUKF`, :class:`~difffilter.smoothers.RTSSmoother`,
:class:`~difffilter.smoothers.ParallelRTSSmoother`, :class:`~difffilter.smoothers.IteratedSmoother`
and :class:`~difffilter.mixers.IMM` (each mode with its own model).  Inside ``vmap`` nothing can branch on a
per-sample value, so: input values are not validated (shapes and dtypes are, as under
``torch.compile``); a Cholesky factorisation that fails gets the largest allowed jitter at once
(:func:`~difffilter.linalg.safe_cholesky`); and a diffuse-prior split
(:mod:`difffilter.filters.diffuse`) that depends on the vmapped values is not made: give an
initial covariance that is not dangerously wide against the measurements (or set
``diffuse_prior = False`` on the filter to get the same values outside ``vmap``).
:class:`~difffilter.engines.FusedFilter` (compiled kernels) and modules that share a parameter
between submodules are refused; an estimator whose code branches on values elsewhere raises
``TypeError`` naming it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor, nn
from torch.func import functional_call, grad, vmap
from torch.nn.utils.parametrize import type_before_parametrizations

from .engines import FusedFilter

__all__ = ["per_sample_grads", "stack_parameters", "vmap_filter"]


def stack_parameters(modules: Sequence[nn.Module]) -> dict[str, Tensor]:
    """The parameters of ``K`` modules of one structure stacked: ``{name: [K, ...]}`` (raw
    parameters, as ``named_parameters`` names them; detached copies, which a caller may
    ``requires_grad_()``).  Buffers are not stacked: :func:`vmap_filter` takes them from the
    module it runs."""
    modules = list(modules)
    if not modules:
        raise ValueError("modules must hold at least one module")
    names = [n for n, _ in modules[0].named_parameters()]
    for i, mod in enumerate(modules[1:], 1):
        if (
            type_before_parametrizations(mod) is not type_before_parametrizations(modules[0])
            or [n for n, _ in mod.named_parameters()] != names
        ):
            raise ValueError(f"modules[{i}] differs in type or parameters from modules[0]; stack modules of one structure")
    tables = [dict(mod.named_parameters()) for mod in modules]
    return {name: torch.stack([t[name].detach() for t in tables]) for name in names}


def _check_module(module: nn.Module, params: dict[str, Tensor]) -> int:
    if not isinstance(module, nn.Module):
        raise TypeError(f"module must be a difffilter filter or smoother (nn.Module), got {type(module).__name__}")
    if any(isinstance(m, FusedFilter) for m in module.modules()):
        raise TypeError("vmap_filter cannot run a FusedFilter (compiled kernels); vmap the filter it wraps instead")
    if len(dict(module.named_parameters(remove_duplicate=False))) != len(dict(module.named_parameters())):
        raise TypeError(
            f"{type(module).__name__} shares a parameter between submodules (e.g. one model in two IMM modes), which "
            "torch.func.functional_call does not restore reliably; give each submodule its own copy"
        )
    if not isinstance(params, dict) or not params:
        raise ValueError("params must be a non-empty dict {name: [K, ...]} (e.g. from stack_parameters)")
    known = dict(module.named_parameters())
    sizes = set()
    for name, value in params.items():
        if name not in known:
            raise ValueError(f"params[{name!r}] is not a parameter of {type(module).__name__}; known: {sorted(known)}")
        if not isinstance(value, Tensor) or value.shape[1:] != known[name].shape:
            raise ValueError(f"params[{name!r}] must have shape [K, {', '.join(map(str, known[name].shape))}]")
        sizes.add(value.shape[0])
    if len(sizes) != 1:
        raise ValueError(f"every params entry needs the same leading size K, got {sorted(sizes)}")
    return sizes.pop()


def _run(fn: Callable[..., Any], module: nn.Module, *args: Any) -> Any:
    try:
        return fn(*args)
    except RuntimeError as err:
        if "vmap" not in str(err):
            raise
        raise TypeError(
            f"{type(module).__name__} cannot run under torch.func.vmap: its code branches on a per-sample value "
            f"({str(err).splitlines()[0][:120]}); see difffilter.func for the supported filters"
        ) from err


def vmap_filter(module: nn.Module, params: dict[str, Tensor], *args: Any, chunk_size: int | None = None, **kwargs: Any) -> Any:
    """``module(*args, **kwargs)`` for each of ``K`` parameter sets, in one vmapped call.

    Args:
        module: a filter or smoother (its parameters not in ``params``, and its buffers, are
            shared by all sets).
        params: ``{name: [K, ...]}`` raw parameters (:func:`stack_parameters`).
        *args, **kwargs: the module's arguments (measurements ``[B, T, m]``...), shared by all sets.
        chunk_size: run the sets in chunks of this size (bounds memory).

    Returns the module's result (:class:`~difffilter.filters.FilterResult` or
    :class:`~difffilter.smoothers.SmootherResult`) with a leading dimension ``K`` on every tensor
    (e.g. ``mean [K, B, T, n]``), equal to running the ``K`` sets one by one.
    """
    _check_module(module, params)

    def one(p: dict[str, Tensor]) -> Any:
        return functional_call(module, p, args, kwargs)

    return _run(vmap(one, chunk_size=chunk_size), module, params)


def per_sample_grads(
    module: nn.Module,
    params: dict[str, Tensor],
    loss: Callable[[Any], Tensor],
    *args: Any,
    chunk_size: int | None = None,
    **kwargs: Any,
) -> dict[str, Tensor]:
    """Gradients ``{name: [K, ...]}`` of the scalar ``loss(module(*args, **kwargs))`` with respect to
    each parameter set of ``params`` (``vmap`` over ``grad``), equal to ``K`` separate backward
    passes."""
    _check_module(module, params)

    def one(p: dict[str, Tensor]) -> Tensor:
        out = loss(functional_call(module, p, args, kwargs))
        if not isinstance(out, Tensor) or out.ndim != 0:
            raise ValueError("loss must return a scalar tensor")
        return out

    return _run(vmap(grad(one), chunk_size=chunk_size), module, params)
