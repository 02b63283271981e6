"""Small helpers every layer of difffilter may import (the floor: it imports only torch).

* :func:`as_dtype` - a torch dtype from a name (configs cannot write ``torch.float64``).
* :func:`generator` - the one seed convention of the simulators and samplers.
* :func:`tensor`, :func:`covariance` - tensors and covariances from plain config numbers.
* :func:`control` - one named per-step input from a controls dict, with a clear error.
* :func:`document_init` - ``help(cls.__init__)`` shows the class's own documentation.
"""

from __future__ import annotations

import inspect
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

__all__ = ["as_dtype", "control", "covariance", "document_init", "generator", "tensor"]


def as_dtype(dtype: torch.dtype | str | None, default: torch.dtype = torch.float64) -> torch.dtype:
    """``torch.float64``, ``"float64"``, ``"torch.float32"``, ``"64"`` or ``None`` -> a torch dtype."""
    if dtype is None:
        return default
    if isinstance(dtype, torch.dtype):
        return dtype
    name = str(dtype).removeprefix("torch.")
    aliases = {"64": "float64", "32": "float32", "double": "float64", "float": "float32", "16": "float16"}
    out = getattr(torch, aliases.get(name, name), None)
    if not isinstance(out, torch.dtype) or not out.is_floating_point:
        raise ValueError(f"dtype must name a floating-point torch dtype (e.g. 'float64'), got {dtype!r}")
    return out


def generator(seed: int | torch.Generator | None) -> torch.Generator:
    """A ``torch.Generator`` from an int seed (deterministic), a generator (returned as is, so
    draws continue its stream), or ``None`` (a random seed)."""
    if isinstance(seed, torch.Generator):
        return seed
    gen = torch.Generator()
    if seed is None:
        gen.seed()
    else:
        gen.manual_seed(int(seed))
    return gen


def tensor(data: float | Sequence[float] | Sequence[Sequence[float]], dtype: torch.dtype | str | None = "float64") -> Tensor:
    """``torch.tensor(data, dtype=dtype)`` for configs."""
    return torch.as_tensor(data, dtype=as_dtype(dtype))


def covariance(value: float | Sequence[float] | Sequence[Sequence[float]] | Tensor, dim: int, dtype: torch.dtype) -> Tensor:
    """A covariance ``[dim, dim]`` from a scalar (``s I``), a vector (diagonal) or a matrix."""
    v = torch.as_tensor(value, dtype=dtype)
    if v.ndim == 0:
        return v * torch.eye(dim, dtype=dtype)
    if v.ndim == 1:
        if v.shape[0] != dim:
            raise ValueError(f"a diagonal covariance needs {dim} variances, got {v.shape[0]}")
        return torch.diag(v)
    if v.shape != (dim, dim):
        raise ValueError(f"covariance must be [{dim}, {dim}], got {tuple(v.shape)}")
    return v


def control(u: Any, key: str, owner: str = "this model") -> Tensor:
    """``u[key]`` of a per-step inputs dict; ``KeyError`` naming ``owner`` and the key when absent."""
    if not isinstance(u, Mapping) or key not in u:
        raise KeyError(f"{owner} needs u[{key!r}] (per-step inputs dict)")
    value: Tensor = u[key]
    return value


def document_init(classes: Iterable[Any]) -> None:
    """Give the ``__init__`` of each class in ``classes`` the class docstring (where the class
    defines ``__init__`` without a docstring of its own), so that ``help(UKF.__init__)`` describes
    the arguments instead of showing the text ``nn.Module.__init__`` would pass on."""
    for cls in classes:
        init = cls.__dict__.get("__init__") if isinstance(cls, type) else None
        if init is None or init.__doc__ or not cls.__doc__ or not hasattr(init, "__doc__"):
            continue
        init.__doc__ = f"Build a ``{cls.__name__}`` (arguments below, from the class docstring).\n\n{inspect.cleandoc(cls.__doc__)}"
