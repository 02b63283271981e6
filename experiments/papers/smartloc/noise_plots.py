"""Figures of learned pseudorange noise models against elevation and C/N0."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from matplotlib.figure import Figure

__all__ = ["binned_sigma", "plot_noise_models"]

_SYSTEM_NAMES = {1: "GPS", 4: "GLONASS"}


def binned_sigma(x: np.ndarray, sigma: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bin centres and the RMS of ``sigma`` (i.e. the square root of the mean variance) per bin of ``x``
    (bins with fewer than 5 values left out)."""
    idx = np.digitize(x, edges) - 1
    centres, values = [], []
    for b in range(len(edges) - 1):
        sel = idx == b
        if sel.sum() >= 5:
            centres.append(0.5 * (edges[b] + edges[b + 1]))
            values.append(float(np.sqrt(np.mean(sigma[sel] ** 2))))
    return np.asarray(centres), np.asarray(values)


def _side_information(drives: Sequence[Any]) -> dict[str, torch.Tensor]:
    parts: dict[str, list[torch.Tensor]] = {}
    for d in drives:
        data = d.data
        used = data.mask & (data.elevation >= 15.0)
        for key, value in (
            ("elevation", data.elevation),
            ("cn0", data.cn0),
            ("constellation", data.constellation.to(torch.float64)),
            ("pr_var", data.pr_var),
        ):
            parts.setdefault(key, []).append(value[used])
    return {k: torch.cat(v) for k, v in parts.items()}


def plot_noise_models(filters: Mapping[str, Any], drives: Sequence[Any], *, title: str = "") -> Figure:
    """Pseudorange sigma against elevation (left) and C/N0 (right), per constellation: the
    receiver's reported sigma (what the hand-tuned filter uses) and each filter's noise model
    evaluated on the drives' satellites (RMS per bin)."""
    u = _side_information(drives)
    el, cn0, grp = u["elevation"].numpy(), u["cn0"].numpy(), u["constellation"].numpy().astype(int)
    curves = {"receiver (hand-tuned)": np.sqrt(u["pr_var"].numpy())}
    for name, filt in filters.items():
        nm = getattr(filt.model.measurement, "noise_model", None)
        if nm is not None:
            with torch.no_grad():
                curves[name] = torch.sqrt(nm(u, u["pr_var"])).numpy()
    fig = Figure(figsize=(11, 4.2))
    axes = fig.subplots(1, 2)
    systems = drives[0].data.systems
    for i, (label, sig) in enumerate(curves.items()):
        for g, sys_id in enumerate(systems):
            sel = grp == g
            if not sel.any():
                continue
            style = "-" if g == 0 else "--"
            name = f"{label}, {_SYSTEM_NAMES.get(sys_id, sys_id)}"
            for ax, x, edges in ((axes[0], el, np.arange(15.0, 91.0, 5.0)), (axes[1], cn0, np.arange(10.0, 56.0, 3.0))):
                c, v = binned_sigma(x[sel], sig[sel], edges)
                ax.plot(c, v, style, color=f"C{i}", label=name, marker="o" if i == 0 else None, ms=3)
    axes[0].set_xlabel("elevation (deg)")
    axes[1].set_xlabel("C/N0 (dB-Hz)")
    for ax in axes:
        ax.set_ylabel("pseudorange sigma (m, RMS per bin)")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7)
    fig.suptitle(f"pseudorange noise models {title}".strip())
    fig.tight_layout()
    return fig
