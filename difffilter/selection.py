"""Choosing which parameters train and setting constrained values by name.

Configs name parameters the way the papers do (``learn: [R, Q, tau, transition]``,
``hand_tuned: {R: [4.0, 4.0], tau: 100}``).  A name is matched against the dotted names of a
module's constrained parameters (``model.measurement.R``, ``filters.1.model.dynamics.Q``,
``transition``) and of its plain ``nn.Parameter`` s:

* exactly (``model.measurement.R``),
* by suffix on a dot boundary (``R`` matches ``model.measurement.R`` and, in an IMM, every
  mode's ``...R``), or
* as a glob (``filters.0.*.Q``).

Training is switched on with ``requires_grad_`` on the raw tensors behind each matched
parametrization, so the optimiser only ever sees the selected raw parameters.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from .params import ScaledMatrix

__all__ = [
    "assign_parameters",
    "learnable_values",
    "match_parameters",
    "named_raw_parameters",
    "parameter_owners",
    "select_parameters",
]


def parameter_owners(module: nn.Module) -> dict[str, tuple[nn.Module, str, list[nn.Parameter]]]:
    """``{dotted name: (owning module, attribute, raw parameters)}`` for every constrained and
    plain parameter below ``module``."""
    out: dict[str, tuple[nn.Module, str, list[nn.Parameter]]] = {}
    for mod_name, mod in module.named_modules():
        prefix = f"{mod_name}." if mod_name else ""
        if parametrize.is_parametrized(mod):
            for pname, plist in mod.parametrizations.items():
                out[prefix + pname] = (mod, pname, list(plist.parameters()))
        for pname, p in mod.named_parameters(recurse=False):
            out[prefix + pname] = (mod, pname, [p])
    # Raw tensors of parametrizations also appear as plain parameters of the ParametrizationList
    # children ("...parametrizations.R.original"); they are reached through their constrained name.
    return {k: v for k, v in out.items() if ".parametrizations." not in f".{k}"}


def named_raw_parameters(module: nn.Module) -> dict[str, list[nn.Parameter]]:
    """``{name: raw parameters}`` for every constrained or plain parameter below ``module``."""
    return {k: v[2] for k, v in parameter_owners(module).items()}


def _matches(name: str, pattern: str) -> bool:
    return name == pattern or name.endswith("." + pattern) or fnmatch.fnmatchcase(name, pattern)


def match_parameters(module: nn.Module, patterns: Iterable[str]) -> dict[str, list[str]]:
    """``{pattern: [matched dotted names]}``; raises ``ValueError`` for a pattern matching nothing."""
    names = list(parameter_owners(module))
    out: dict[str, list[str]] = {}
    for pattern in patterns:
        hits = [n for n in names if _matches(n, str(pattern))]
        if not hits:
            raise ValueError(f"parameter name {pattern!r} matches nothing; available: {sorted(names)}")
        out[str(pattern)] = hits
    return out


def select_parameters(module: nn.Module, patterns: Sequence[str] | None) -> list[str]:
    """Make exactly the parameters named by ``patterns`` trainable (``requires_grad_``).

    ``patterns=None`` leaves every parameter trainable.  Returns the matched dotted names.
    """
    owners = parameter_owners(module)
    if patterns is None:
        for p in module.parameters():
            p.requires_grad_(True)
        return sorted(owners)
    chosen = {n for hits in match_parameters(module, patterns).values() for n in hits}
    for p in module.parameters():
        p.requires_grad_(False)
    for name in chosen:
        for p in owners[name][2]:
            p.requires_grad_(True)
    return sorted(chosen)


def learnable_values(module: nn.Module) -> dict[str, Tensor]:
    """Constrained values (detached) of every parameter whose raw tensors require grad."""
    out: dict[str, Tensor] = {}
    with torch.no_grad():
        for name, (mod, attr, raws) in parameter_owners(module).items():
            if raws and any(p.requires_grad for p in raws):
                out[name] = getattr(mod, attr).detach().clone()
    return out


def _coerce(value: Any, current: Tensor, scaled: bool) -> Tensor:
    v = torch.as_tensor(value, dtype=current.dtype, device=current.device)
    if v.shape == current.shape:
        return v
    if current.ndim >= 2 and current.shape[-1] == current.shape[-2]:
        n = current.shape[-1]
        eye = torch.eye(n, dtype=current.dtype, device=current.device)
        if v.ndim == 0:
            # A scalar is the scale of a ScaledMatrix (value = scale * base), else s * I.
            return v if scaled else v * eye.expand_as(current)
        if v.shape == current.shape[:-1]:
            return torch.diag_embed(v)
    if v.ndim == 0 or v.shape == current.shape[-v.ndim :]:
        return v.expand_as(current).clone()
    raise ValueError(f"cannot set a parameter of shape {tuple(current.shape)} from a value of shape {tuple(v.shape)}")


def assign_parameters(module: nn.Module, values: Mapping[str, Any]) -> list[str]:
    """Set constrained values by name: ``{"R": [[4, 0], [0, 4]], "tau": 100.0}``.

    Values may be tensors, numbers or nested lists.  For square-matrix parameters a vector sets
    the diagonal (``R: [4.0, 4.0]``) and a scalar ``s`` sets ``s * I``, except for a
    :class:`~difffilter.params.ScaledMatrix` parameter (``structure="scalar"``), where it sets
    the scale.  A name matching several parameters (every mode's ``Q``) sets all of them.
    Returns the dotted names set.
    """
    owners = parameter_owners(module)
    done: list[str] = []
    for pattern, hits in match_parameters(module, values.keys()).items():
        for name in hits:
            mod, attr, _ = owners[name]
            current = getattr(mod, attr).detach()
            scaled = parametrize.is_parametrized(mod, attr) and any(
                isinstance(c, ScaledMatrix)
                # mod.parametrizations is a ModuleDict once is_parametrized is True; nn.Module's
                # __getattr__ types it as Tensor | Module
                for c in mod.parametrizations[attr]  # type: ignore[index]
            )
            new = _coerce(values[pattern], current, scaled)
            try:
                if parametrize.is_parametrized(mod, attr):
                    setattr(mod, attr, new)
                else:
                    with torch.no_grad():
                        getattr(mod, attr).copy_(new)
            except (ValueError, RuntimeError) as exc:
                raise ValueError(f"cannot set {name} to {values[pattern]!r}: {exc}") from exc
            done.append(name)
    return done
