"""The documentation's snippets on smoothing (docs/smoothers/rts.md), non-additive noise and
multi-rate sensors (docs/models.md) and the iterated EKF (docs/filters/iterated.md) run as written
and produce what the text says."""

from __future__ import annotations

import torch

from .readme_snippets import run_snippet, section_snippets


def _snippets() -> list[str]:
    return [
        *section_snippets("docs/smoothers/rts.md", "# RTS"),
        *section_snippets("docs/models.md", "## Non-additive noise"),
        *section_snippets("docs/models.md", "## Several sensors"),
        *section_snippets("docs/filters/iterated.md", "# Iterated EKF"),
    ]


_run = run_snippet


def test_section_has_one_snippet_per_capability():
    assert len(_snippets()) == 4


def test_smoothing_snippet():
    ns = _run(_snippets()[0])
    out, nxt = ns["out"], ns["nxt"]
    assert out.mean.shape == (8, 50, 2) and out.cross_cov.shape == (8, 50, 2, 2) and nxt.mean.shape == (8, 50, 2)
    assert torch.isfinite(out.mean).all() and torch.isfinite(ns["mean"]).all()
    raw = ns["model"].measurement.parametrizations.R.original
    assert raw.grad is not None and torch.isfinite(raw.grad).all()
    # the smoothed variance is at most the filtered one
    assert bool((out.cov.diagonal(dim1=-2, dim2=-1) <= out.filtered.cov.diagonal(dim1=-2, dim2=-1) + 1e-12).all())


def test_nonadditive_snippet():
    ns = _run(_snippets()[1])
    assert ns["ukf"].mean.shape == (4, 30, 3) and torch.isfinite(ns["ukf"].mean).all() and torch.isfinite(ns["ekf"].mean).all()


def test_multisensor_snippet():
    ns = _run(_snippets()[2])
    grid = ns["grid"]
    assert grid.measurements.shape == (3, 200, 4) and int(grid.mask[0, :, 2].sum()) == 20
    torch.testing.assert_close(ns["seq"].mean, ns["joint"].mean, rtol=0, atol=1e-9)


def test_iterated_ekf_snippet():
    ns = _run(_snippets()[3])
    model, z, iekf, ekf = ns["model"], ns["z"], ns["iekf"], ns["ekf"]
    # the iterated estimate fits the ranges much better than the single linearisation
    res = lambda r: float((model.measurement(r.mean[0, 0].detach()) - z[0, 0]).norm())  # noqa: E731
    assert res(iekf) < 0.5 * res(ekf)
