"""Compile generated C++ into a shared library, cached on disk by the hash of its source.

The cache lives in ``$DIFFFILTER_CACHE_DIR`` (default ``~/.cache/difffilter/kernels``); a
library is keyed by the source text, the compiler command and the machine's CPU flags, so a
second process that builds the same kernel loads it without compiling.  Writes are atomic
(a temporary file renamed into place), so concurrent processes may share the directory.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

__all__ = ["cache_dir", "compile_library", "compiler_available", "CompileError"]

_GCC_FLAGS = ["-fira-region=one"]
_FLAGS = ["-march=native", "-fno-math-errno", "-fno-trapping-math", "-shared", "-fPIC", "-std=c++17", "-w"]
_lock = threading.Lock()
_loaded: dict[str, ctypes.CDLL] = {}


class CompileError(RuntimeError):
    """The C++ compiler failed or is missing."""


def cache_dir() -> Path:
    """Where compiled kernels are kept (``$DIFFFILTER_CACHE_DIR`` or ``~/.cache/difffilter/kernels``)."""
    root = os.environ.get("DIFFFILTER_CACHE_DIR")
    return Path(root) if root else Path.home() / ".cache" / "difffilter" / "kernels"


def _compiler() -> str | None:
    for name in (os.environ.get("CXX"), "g++", "c++", "clang++"):
        if name and shutil.which(name):
            return name
    return None


def compiler_available() -> str | None:
    """``None`` if a C++ compiler is on ``PATH``, else why the compiled engine cannot be built."""
    return None if _compiler() is not None else "no C++ compiler (g++, c++ or clang++) on PATH; set CXX"


def _cpu_flags() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            return next((ln for ln in fh if ln.startswith("flags")), "")
    except OSError:
        return ""


@functools.cache
def _is_gcc(cxx: str) -> bool:
    try:
        out = subprocess.run([cxx, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return False
    return "clang" not in out.lower() and ("gcc" in out.lower() or "g++" in out.lower() or "free software foundation" in out.lower())


def compile_library(source: str, *, tag: str = "kernel", opt: str = "-O2") -> ctypes.CDLL:
    """Compile ``source`` with optimisation level ``opt`` (or find it in the cache) and load it."""
    cxx = _compiler()
    if cxx is None:
        raise CompileError(compiler_available())
    # GCC's register allocator spends most of a kernel's build on its region hierarchy; one region
    # for the whole (straight-line) function halves the build (8 s instead of 15 s of CPU for the
    # p000 UKF's reverse kernel, GCC 12), and the kernels measured as fast
    flags = [opt, *(_GCC_FLAGS if _is_gcc(cxx) else []), *_FLAGS]
    key = hashlib.sha256("\0".join([source, cxx, *flags, _cpu_flags()]).encode()).hexdigest()[:32]
    with _lock:
        lib = _loaded.get(key)
        if lib is not None:
            return lib
        root = cache_dir()
        root.mkdir(parents=True, exist_ok=True)
        target = root / f"{tag}_{key}.so"
        if not target.exists():
            with tempfile.TemporaryDirectory(dir=root) as tmp:
                src = Path(tmp) / "kernel.cpp"
                src.write_text(source)
                out = Path(tmp) / "kernel.so"
                proc = subprocess.run([cxx, *flags, str(src), "-o", str(out)], capture_output=True, text=True)
                if proc.returncode != 0:
                    raise CompileError(f"{cxx} failed ({proc.returncode}): {proc.stderr[-3000:]}")
                os.replace(out, target)
        lib = ctypes.CDLL(str(target))
        _loaded[key] = lib
        return lib
