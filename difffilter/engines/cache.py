"""On-disk cache of lowered steps, so that a new process skips tracing and lowering.

A traced and lowered step (:class:`~.trace.TracedStep`: the scalar graph, its input and output
layout) is stored in ``cache_dir()/programs`` under :func:`program_key`, a hash of everything
the trace depends on besides the values of the trained parameters:

* :func:`~.trace.fingerprint` of the filter: every submodule's type and plain attributes (e.g.
  sigma-point settings, flags), which parameters train, the shapes and dtypes of parameters and
  buffers, and the values of buffers and frozen parameters;
* the :class:`~.trace.StepLayout`: belief entries and shapes, measurement size, mask, controls, dtype;
* the source text of every file of the ``difffilter`` package and of every file that defines a
  class of one of the filter's submodules (or a base class) outside ``torch`` - a user's model;
* the versions of torch and Python and this cache's format.

Code that runs in the step but lives in none of those files (a helper module of a user's model,
a function replaced at run time) is not in the key.  A stored step is therefore also *checked*
before it is used: two steps of the filter's own code are run eagerly from the actual initial
belief and compared with the compiled kernel; any difference discards the stored step and the
filter is traced again.  ``DIFFFILTER_PROGRAM_CACHE=0`` turns the cache off.

Each stored step has a size-and-SHA-256 record beside it (as the compiled kernels do, see
:mod:`.build`); the bytes are unpickled only when they match it, so a truncated or overwritten
entry is never unpickled: it is traced again, with one
:class:`~.build.CacheIntegrityWarning`.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import math
import os
import pickle
import sys
import threading
import warnings
from pathlib import Path

import torch
from torch import Tensor, nn

from ..filters.base import RecursiveFilter
from .build import CacheIntegrityWarning, atomic_write, cache_dir, verify_record, write_record
from .kernel import SequenceProgram
from .trace import StepLayout, TracedStep, eager_steps, fingerprint, trace_step

__all__ = ["FORMAT", "load_or_trace", "program_key", "program_path"]

#: bumped whenever the stored layout changes
FORMAT = "difffilter-program-1"
_PACKAGE = str(Path(__file__).resolve().parents[2])  # .../difffilter
_digests: dict[str, str] = {}
_lock = threading.Lock()


def _file_digest(path: str) -> str:
    with _lock:
        d = _digests.get(path)
    if d is None:
        d = hashlib.sha256(Path(path).read_bytes()).hexdigest()
        with _lock:
            _digests[path] = d
    return d


@functools.cache
def _package_files() -> tuple[str, ...]:
    files = []
    for root, dirs, names in os.walk(_PACKAGE):
        dirs[:] = [d for d in dirs if d != "__pycache__"]
        files += [os.path.join(root, n) for n in names if n.endswith(".py")]
    return tuple(sorted(files))


def _class_files(filt: nn.Module) -> list[str] | None:
    """Source files of the classes (and base classes) of ``filt``'s submodules outside torch;
    None when one has no source file (defined interactively): then nothing is cached."""
    files: set[str] = set()
    for mod in filt.modules():
        for cls in type(mod).__mro__:
            top = cls.__module__.split(".")[0]
            if top in ("torch", "builtins", "typing", "abc"):
                continue
            try:
                path = inspect.getsourcefile(cls)
            except (TypeError, OSError):
                path = None
            if path is None or not os.path.isfile(path):
                return None
            files.add(str(Path(path).resolve()))
    return sorted(files)


def program_key(filt: RecursiveFilter, layout: StepLayout) -> str | None:
    """Hash of everything the lowered step of ``filt`` for ``layout`` depends on (see the module
    docstring), or None when it cannot be told (a class without a source file)."""
    classes = _class_files(filt)
    if classes is None:
        return None
    h = hashlib.sha256()
    parts = [FORMAT, torch.__version__, sys.version, fingerprint(filt), repr(layout)]
    for path in sorted(set(_package_files()) | set(classes)):
        rel = os.path.relpath(path, _PACKAGE) if path.startswith(_PACKAGE + os.sep) else path
        parts.append(f"{rel}:{_file_digest(path)}")
    for p in parts:
        h.update(p.encode())
        h.update(b"\0")
    return h.hexdigest()[:40]


def program_path(key: str) -> Path:
    """Where the step of :func:`program_key` ``key`` is stored."""
    return cache_dir() / "programs" / f"step_{key}.pkl"


def _enabled() -> bool:
    return os.environ.get("DIFFFILTER_PROGRAM_CACHE", "1") not in ("0", "false", "no", "off")


def _save(path: Path, traced: TracedStep) -> None:
    state = dict(vars(traced))
    state["params"] = [(name, tuple(p.shape)) for name, p in traced.params]
    data = pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL)
    write_record(path, data)  # the record first: a reader that sees the step sees its record
    atomic_write(path, data)


def _load(path: Path, filt: RecursiveFilter) -> TracedStep | None:
    check = verify_record(path)
    if check != "ok":
        if check == "damaged":
            warnings.warn(
                f"cached program {path} does not match its recorded size and SHA-256 (truncated or overwritten); tracing again",
                CacheIntegrityWarning,
                stacklevel=3,
            )
        return None
    try:
        state = pickle.loads(path.read_bytes())
    except FileNotFoundError:
        return None
    except Exception:  # noqa: BLE001 - a foreign file with a matching record is still only a cache miss
        return None
    named = dict(filt.named_parameters())
    params = []
    for name, shape in state.get("params", []):
        p = named.get(name)
        if p is None or tuple(p.shape) != shape or not p.requires_grad:
            return None
        params.append((name, p))
    state["params"] = params
    try:
        return TracedStep(**state)
    except TypeError:
        return None


def _agrees(prog: SequenceProgram, filt: RecursiveFilter, layout: StepLayout, belief: dict[str, Tensor]) -> bool:
    """Whether the compiled kernel computes what ``filt``'s own step computes now: two steps from
    ``belief`` (batch one) on :func:`~.trace.eager_steps`' inputs, every output field."""
    traced, dtype = prog.traced, layout.dtype
    try:
        ref = eager_steps(filt, layout, belief, steps=2)
    except Exception:  # noqa: BLE001 - the step fails eagerly now: let tracing report it
        return False
    state0 = torch.cat([belief[k].detach().reshape(1, -1).to(dtype) for k in sorted(belief)], 1).T
    step = [torch.zeros(layout.measurement_dim, dtype=dtype)]
    if layout.has_mask:
        step.append(torch.ones(layout.measurement_dim, dtype=dtype))
    step += [torch.zeros(math.prod(s), dtype=dtype) for k, s, _ in layout.controls or () if k not in layout.shared]
    step_in = torch.cat(step).reshape(1, -1, 1).expand(2, -1, prog.lanes).contiguous()
    named = dict(filt.named_parameters())
    params = [named[name].detach().reshape(-1) for name, _ in traced.params]
    flat = torch.cat(params).to(dtype) if params else torch.zeros(1, dtype=dtype)
    shared = torch.zeros(2, layout.shared_size, dtype=dtype) if layout.shared_size else torch.zeros(1, dtype=dtype)
    outs = prog.forward(state0.expand(-1, prog.lanes).contiguous(), step_in, shared, flat.contiguous(), threads=1)
    tol = 1e-6 if dtype == torch.float64 else 1e-3
    for t in range(2):
        if not set(traced.fields) <= set(ref[t]):
            return False
        for name, (gi, off, shape) in traced.fields.items():
            want = ref[t][name].detach().reshape(-1).to(dtype)
            got = outs[gi][t, off : off + math.prod(shape), 0]
            if want.shape != got.shape:
                return False
            scale = float(want[torch.isfinite(want)].abs().max()) if bool(torch.isfinite(want).any()) else 0.0
            if not torch.allclose(got, want, rtol=tol, atol=tol * scale + 1e-30, equal_nan=True):
                return False
    return True


def load_or_trace(filt: RecursiveFilter, layout: StepLayout, belief: dict[str, Tensor], *, reuse_buffers: bool = True) -> SequenceProgram:
    """The compiled program of ``filt``'s step for ``layout``: from the on-disk cache when a
    stored step has the same :func:`program_key` and agrees with the filter's own step on
    ``belief`` (batch one), else traced, lowered and stored."""
    key = program_key(filt, layout) if _enabled() else None
    if key is not None:
        traced = _load(program_path(key), filt)
        if traced is not None:
            prog = SequenceProgram(traced, reuse_buffers=reuse_buffers)
            if _agrees(prog, filt, layout, belief):
                prog.from_cache = True
                return prog
    traced = trace_step(filt, layout, belief)
    if key is not None:
        try:
            _save(program_path(key), traced)  # before the kernel's reverse sweep adds nodes to the graph
        except OSError:
            pass  # a read-only cache directory only costs the next process a trace
    return SequenceProgram(traced, reuse_buffers=reuse_buffers)
