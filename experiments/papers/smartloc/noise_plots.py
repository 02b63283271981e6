"""Figures of the learned pseudorange extras: noise models against elevation and C/N0, and the
outlier gate's weight against the normalised innovation."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from matplotlib.figure import Figure

__all__ = ["binned_sigma", "gate_values", "plot_noise_models"]

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


def gate_values(filt: Any) -> dict[str, list[float]]:
    """``gate_threshold``, ``gate_floor`` (m) and, for a smooth gate, ``gate_softness`` of a
    pseudorange filter's reject gate (empty without a gate)."""
    gate = getattr(filt.model.measurement, "robust_gate", None)
    if gate is None:
        return {}
    out = {"gate_threshold": [float(torch.as_tensor(gate.threshold).detach())], "gate_floor": [float(torch.as_tensor(gate.floor).detach())]}
    if gate.soft:
        out["gate_softness"] = [float(gate.gate_softness.detach())]
    return out


def plot_noise_models(
    filters: Mapping[str, Any], drives: Sequence[Any], *, title: str = "", gates: Mapping[str, Any] | None = None
) -> Figure:
    """Pseudorange sigma against elevation (left) and C/N0 (middle), per constellation: the
    receiver's reported sigma (what the hand-tuned filter uses) and each filter's noise model
    evaluated on the drives' satellites (RMS per bin); right: the reject gate's weight ``1 / f``
    on a range against its normalised innovation ``|e| / sqrt(R + floor^2)`` for ``filters`` and
    ``gates`` (e.g. the hand-tuned and the untrained gated filter; threshold, floor and softness
    in the legend)."""
    from experiments.ranging.report import gate_curve  # the same RobustGate curve as the ranging figure

    u = _side_information(drives)
    el, cn0, grp = u["elevation"].numpy(), u["cn0"].numpy(), u["constellation"].numpy().astype(int)
    curves = {"receiver (hand-tuned)": np.sqrt(u["pr_var"].numpy())}
    for name, filt in filters.items():
        nm = getattr(filt.model.measurement, "noise_model", None)
        if nm is not None:
            with torch.no_grad():
                curves[name] = torch.sqrt(nm(u, u["pr_var"])).numpy()
    fig = Figure(figsize=(16, 4.2))
    axes = fig.subplots(1, 3)
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
    res = torch.linspace(0.0, 8.0, 321, dtype=torch.float64)
    styles = {"hand-tuned": "k:", "untrained-gate": "k--"}
    for i, (name, filt) in enumerate({**dict(gates or {}), **filters}.items()):
        g = gate_values(filt)
        if g:
            soft = f", t {g['gate_softness'][0]:.3g}" if "gate_softness" in g else " (hard)"
            label = f"{name}: {g['gate_threshold'][0]:.2f} sigma, floor {g['gate_floor'][0]:.1f} m{soft}"
            kw = {"label": label} if name in styles else {"label": label, "color": f"C{i}"}
            axes[2].semilogy(res, 1.0 / gate_curve(g, res), styles.get(name, "-"), **kw)
    axes[2].set(xlabel="normalised innovation |e| / sqrt(R + floor²)", ylabel="gate weight 1/f", ylim=(1e-6, 2))
    axes[2].set_title("reject gate (weight of a range in the update)", fontsize=9)
    axes[2].legend(fontsize=6)
    axes[0].set_xlabel("elevation (deg)")
    axes[1].set_xlabel("C/N0 (dB-Hz)")
    for ax in axes[:2]:
        ax.set_ylabel("pseudorange sigma (m, RMS per bin)")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7)
    fig.suptitle(f"learned pseudorange extras: noise model and reject gate {title}".strip())
    fig.tight_layout()
    return fig
