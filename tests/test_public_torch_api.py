"""The compiled engine uses torch's public API, so that a torch upgrade that removes what it needs
fails here, loudly, instead of changing results silently."""

from __future__ import annotations

import re
from pathlib import Path

import torch

from difffilter.engines.kernel import unreferenced
from difffilter.engines.lower import _op_name
from difffilter.engines.trace import StepLayout, _step_function
from difffilter.filters import UKF
from difffilter.models import FunctionalModel

ENGINE = Path(__file__).resolve().parents[1] / "difffilter" / "engines"
D = torch.float64
#: the private names the engine still reads, each behind a fallback that keeps results correct
ALLOWED_PRIVATE = {
    "torch._C._storage_Use_Count",  # buffer reuse; without it buffers are never reused (test below)
    "torch._dynamo.config",  # recompile limit of the inductor engine (documented knob)
    "torch._C._functorch",  # is a torch.func transform active? without it the engine's error falls back to eager
}


def test_engine_uses_no_other_private_torch_name():
    found = set()
    for path in ENGINE.glob("*.py"):
        text = path.read_text()
        names = re.findall(r"torch(?:\.\w+)*\._\w+(?:\.\w+)*", text)
        found |= {n for n in names if not re.search(r"\.__\w+__$", n)}  # dunders are public
        assert "_reparametrize_module" not in text, path
    assert found <= ALLOWED_PRIVATE, found - ALLOWED_PRIVATE


def test_the_public_api_the_engine_needs_exists():
    assert callable(torch.func.functional_call)
    assert callable(torch.func.functionalize)
    assert isinstance(torch.ops.aten.add.Tensor, torch.library.OpOverload)
    assert _op_name(torch.ops.aten.add.Tensor) == "add"
    assert _op_name(torch.ops.aten.mul) == "mul"  # an overload packet


def test_buffer_reuse_can_tell_an_unreferenced_buffer():
    buf = torch.empty(4, 3)
    assert unreferenced(buf)
    view = buf[1:]
    assert not unreferenced(buf)
    del view
    assert unreferenced(buf)


def test_traced_step_takes_the_trained_parameters_as_inputs():
    """The step the engine traces reads the parameter values it is given (functional_call), not
    the module's own: with a doubled raw Q it equals the filter's step with that Q."""
    model = FunctionalModel(f=lambda x: 0.9 * x, h=lambda x: x[..., :1] ** 2, Q=0.1 * torch.eye(2, dtype=D), R=0.2 * torch.eye(1, dtype=D))
    ukf = UKF(model)
    layout = StepLayout(belief=(("cov", (2, 2), D), ("mean", (2,), D)), measurement_dim=1, has_mask=False, controls=None, dtype=D)
    belief = {"cov": torch.eye(2, dtype=D)[None], "mean": torch.tensor([[1.0, -0.5]], dtype=D)}
    trained = [(n, p) for n, p in ukf.named_parameters() if p.requires_grad]
    z = torch.tensor([[0.7]], dtype=D)
    new = [p.detach() * 2.0 for _, p in trained]
    out = _step_function(ukf, layout, sorted(belief), trained, {})(belief["cov"], belief["mean"], z, *new)
    with torch.no_grad():
        for (_, p), v in zip(trained, new, strict=True):
            p.copy_(v)
        prior = ukf.predict(dict(belief), None)
        post, info = ukf.update(prior, z, None, None)
    assert torch.allclose(out[0], post["cov"], rtol=1e-14, atol=0) and torch.allclose(out[1], post["mean"], rtol=1e-14, atol=0)
    assert torch.allclose(out[4], info.log_likelihood, rtol=1e-14, atol=0)
