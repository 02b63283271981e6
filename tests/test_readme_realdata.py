"""The docs/models.md snippet on side-information noise models and the learnable gate runs as written:
the noise follows the per-step side information, the gate keeps the outlier out, and training
moves the per-group scales and the gate's parameters."""

from __future__ import annotations

import copy

import torch

from difffilter.filters import EKF

from .readme_snippets import run_snippet, section_snippets

HEADING = "## Noise from side information, learned gates"


def test_side_information_snippet() -> None:
    (code,) = section_snippets("docs/models.md", HEADING)
    torch.manual_seed(0)
    ns = run_snippet(code)
    gps, model, res = ns["gps"], ns["model"], ns["res"]
    z, controls, m0, P0, truth = ns["z"], ns["controls"], ns["m0"], ns["P0"], ns["truth"]
    assert torch.isfinite(res.mean).all()
    # R follows the side information: diag(s_type * hdop^2) (gate off, the start's scale 1)
    bare = copy.deepcopy(gps)
    bare.gate = None
    x = torch.zeros(4, dtype=torch.float64)
    u = {k: v[:, 3] for k, v in controls.items()}
    scale = bare.variance.scale.detach()[u["fix_type"]]
    torch.testing.assert_close(torch.diagonal(bare.measurement_noise(x, u), dim1=-2, dim2=-1), scale * u["hdop_sq"])
    # the gate keeps the 80 m outlier (step 20, east) out; the same filter without it is pulled away
    ungated = copy.deepcopy(model)
    ungated.measurement.gate = None
    err = lambda r: (r.mean[:, 20, 0] - truth[:, 20, 0]).abs().max()  # noqa: E731
    with torch.no_grad():
        gated_now = EKF(model)(z, m0, P0, controls=controls)
        loose = EKF(ungated)(z, m0, P0, controls=controls)
    assert float(err(gated_now)) < 10.0 < float(err(loose))
    # training moved every learned value away from its start
    assert not torch.allclose(gps.variance.scale.detach(), torch.ones(2, dtype=torch.float64))
    for name, start in (("gate_threshold", 3.0), ("gate_floor", 2.0), ("gate_softness", 0.2)):
        assert abs(float(getattr(gps.gate, name).detach()) - start) > 1e-3, name
