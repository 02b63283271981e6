"""Learnable values as the scalars a learner logs every epoch (:func:`parameter_scalars`)."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["parameter_scalars"]


def parameter_scalars(name: str, value: Tensor, max_elements: int = 64) -> dict[str, float]:
    """Scalars to log for one constrained value: every element of small tensors (upper triangle
    of symmetric matrices, structural zeros left out), only the diagonal of large square ones."""
    v = value.detach().to("cpu", torch.float64)
    if v.ndim == 0:
        return {name: float(v)}
    if v.ndim == 1:
        entries = v if v.numel() <= max_elements else v[:max_elements]
        return {f"{name}[{i}]": float(x) for i, x in enumerate(entries)}
    if v.ndim == 2 and v.shape[0] == v.shape[1]:
        symmetric = bool(torch.allclose(v, v.T))
        if v.numel() > max_elements:
            return {f"{name}[{i},{i}]": float(v[i, i]) for i in range(min(v.shape[0], max_elements))}
        out = {}
        for i in range(v.shape[0]):
            for j in range(i if symmetric else 0, v.shape[1]):
                if i == j or not symmetric or float(v[i, j]) != 0.0:
                    out[f"{name}[{i},{j}]"] = float(v[i, j])
        return out
    flat = v.flatten()
    if flat.numel() <= max_elements:
        return {f"{name}[{i}]": float(x) for i, x in enumerate(flat)}
    return {f"{name}.norm": float(flat.norm())}
