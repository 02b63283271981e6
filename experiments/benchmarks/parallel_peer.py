"""dynamax's parallel filter and smoother for ``experiments/benchmark_parallel.py``, run in a
process of its own (numpy and JAX only, no torch):

    python experiments/benchmarks/parallel_peer.py DIR

``DIR/spec.json`` names the model (``F, H, Q, R``), the dtype and the cells (a ``.npy`` file of
measurements ``[B, T, m]``, the repeats and the rows to time); each finished cell appends one JSON
line to ``DIR/out.jsonl`` (best time, and for the filter row the per-trajectory log-likelihoods
and the filtered means in ``<cell>.ll.npy`` / ``<cell>.mean.npy``).  A process of its own because
JAX 0.10.2 deadlocked in ``block_until_ready`` when it ran in the benchmark's process, beside
torch and the compiled engine's builds; the parent bounds it with a timeout and keeps the cells
that finished.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["DynamaxPeer"]


class DynamaxPeer:
    """dynamax's associative-scan filter and smoother (``parallel_inference.lgssm_filter`` /
    ``lgssm_smoother``), vmapped over the batch and jitted (the compilation excluded by a
    warm-up); ``fwd+bwd`` is ``jax.grad`` of the summed log-likelihood w.r.t. ``Q`` and ``R``,
    as the torch rows differentiate with respect to their parameters."""

    def __init__(self, f: np.ndarray, h: np.ndarray, q: np.ndarray, r: np.ndarray, *, float64: bool) -> None:
        import jax
        import jax.numpy as jnp
        from dynamax.linear_gaussian_ssm import parallel_inference
        from dynamax.linear_gaussian_ssm.inference import ParamsLGSSM, ParamsLGSSMDynamics, ParamsLGSSMEmissions, ParamsLGSSMInitial

        jax.config.update("jax_enable_x64", float64)
        self.jax = jax
        fj, hj = jnp.asarray(f), jnp.asarray(h)
        n, m = f.shape[0], h.shape[0]

        def params(q: Any, r: Any) -> ParamsLGSSM:
            # dynamax's initial state is x_0 (updated by the first measurement); difffilter's
            # x_{-1} is predicted first: N(F m0, F P0 F^T + Q) with m0 = 0, P0 = I
            return ParamsLGSSM(
                initial=ParamsLGSSMInitial(mean=jnp.zeros(n), cov=fj @ fj.T + q),
                dynamics=ParamsLGSSMDynamics(weights=fj, bias=jnp.zeros(n), input_weights=jnp.zeros((n, 0)), cov=q),
                emissions=ParamsLGSSMEmissions(weights=hj, bias=jnp.zeros(m), input_weights=jnp.zeros((m, 0)), cov=r),
            )

        def loglik(q: Any, r: Any, ys: Any) -> Any:
            return jax.vmap(lambda y: parallel_inference.lgssm_filter(params(q, r), y).marginal_loglik)(ys)

        def filtered(q: Any, r: Any, ys: Any) -> Any:
            post = jax.vmap(lambda y: parallel_inference.lgssm_filter(params(q, r), y))(ys)
            return post.marginal_loglik, post.filtered_means

        self.q, self.r = jnp.asarray(q), jnp.asarray(r)
        self.calls = {
            "filter": jax.jit(filtered),
            "filter fwd+bwd": jax.jit(jax.grad(lambda q, r, ys: loglik(q, r, ys).sum(), argnums=(0, 1))),
            "smoother": jax.jit(jax.vmap(lambda y: parallel_inference.lgssm_smoother(params(self.q, self.r), y).smoothed_means)),
        }

    def time(self, what: str, z: np.ndarray, repeats: int) -> tuple[float, Any]:
        """Best time of ``what`` on ``z [B, T, m]`` and its output (moved to the host)."""
        ys = self.jax.device_put(z)
        call = self.calls[what]
        fn = (lambda: call(ys)) if what == "smoother" else (lambda: call(self.q, self.r, ys))
        out = self.jax.block_until_ready(fn())  # compiles
        best = float("inf")
        for _ in range(repeats):
            start = time.perf_counter()
            self.jax.block_until_ready(fn())
            best = min(best, time.perf_counter() - start)
        return best, self.jax.device_get(out)


def describe(device: str) -> str:
    """JAX and dynamax versions, backend and thread pool, for the table's header."""
    import os

    import dynamax
    import jax

    if device == "cpu":
        jax.config.update("jax_platforms", "cpu")
    flags = os.environ.get("XLA_FLAGS", "")
    pool = f"XLA_FLAGS={flags!r}" if flags else "XLA's default thread pool"
    return f"jax {jax.__version__} on {jax.default_backend()} ({jax.devices()[0].device_kind}), dynamax {dynamax.__version__}, {pool}"


def main(folder: Path) -> None:
    spec = json.loads((folder / "spec.json").read_text())
    about = describe(spec["device"])
    (folder / "about.txt").write_text(about)
    mats = {k: np.asarray(v) for k, v in spec["model"].items()}
    peer = DynamaxPeer(mats["F"], mats["H"], mats["Q"], mats["R"], float64=spec["dtype"] == "float64")
    for cell in spec["cells"]:
        z = np.load(folder / cell["file"])
        for what in cell["whats"]:
            best, out = peer.time(what, z, cell["repeats"])
            line: dict[str, Any] = {"cell": cell["file"], "what": what, "seconds": best}
            if what == "filter":
                np.save(folder / f"{cell['file']}.ll.npy", np.asarray(out[0]))
                np.save(folder / f"{cell['file']}.mean.npy", np.asarray(out[1]))
            with (folder / "out.jsonl").open("a") as fh:
                fh.write(json.dumps(line) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
