"""Compile generated C++ into a shared library, cached on disk by the hash of its source.

The cache lives in ``$DIFFFILTER_CACHE_DIR`` (default ``~/.cache/difffilter/kernels``); a
library is keyed by the source text, the compiler command and the machine's CPU flags, so a
second process that builds the same kernel loads it without compiling.  Writes are atomic
(a temporary file renamed into place), so concurrent processes may share the directory.

Every library has a record beside it (``<name>.so.sha256``: its size and SHA-256) written
before the library is moved into place.  A library is loaded only after its size and hash
match the record: mapping a truncated shared object can kill the process with SIGBUS and a
garbage one raises ``OSError``, so a damaged entry (or one without a record, from an older
version) is deleted and compiled again instead, with one :class:`CacheIntegrityWarning`
when the entry was damaged.

Builds of different kernels never wait for each other; builds of one kernel happen once: threads
of a process wait on a lock per cache key, processes (the jobs of a sweep sharing one cache) on
an advisory file lock per cache key (``fcntl.flock``, where the platform has it), and whoever
comes second loads what the first built.
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
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

try:
    import fcntl
except ImportError:  # not POSIX: processes may then build one kernel twice (writes stay atomic)
    fcntl = None  # type: ignore[assignment]

__all__ = [
    "CacheIntegrityWarning",
    "CompileError",
    "atomic_write",
    "cache_dir",
    "compile_library",
    "compiler_available",
    "verify_record",
    "write_record",
]

_GCC_FLAGS = ["-fira-region=one"]
_FLAGS = ["-march=native", "-fno-math-errno", "-fno-trapping-math", "-shared", "-fPIC", "-std=c++17", "-w"]
_lock = threading.Lock()  # guards the two dicts below, never held during a build
_loaded: dict[str, ctypes.CDLL] = {}
_key_locks: dict[str, threading.Lock] = {}


class CompileError(RuntimeError):
    """The C++ compiler failed or is missing."""


class CacheIntegrityWarning(RuntimeWarning):
    """A cached kernel or program was damaged (size or hash differs from its record) and is rebuilt."""


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file renamed into place (readers never see a part)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=path.parent, delete=False, suffix=".tmp") as fh:
        fh.write(data)
        tmp = fh.name
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)


def _record_path(path: Path) -> Path:
    return path.with_name(path.name + ".sha256")


def _digest(data: bytes) -> str:
    return f"{len(data)} {hashlib.sha256(data).hexdigest()}\n"


def write_record(path: Path, data: bytes) -> None:
    """Store the size and SHA-256 of ``data``, the future content of ``path``, beside it."""
    atomic_write(_record_path(path), _digest(data).encode())


def verify_record(path: Path) -> str:
    """``"ok"`` when ``path``'s size and hash equal its record, ``"missing"`` when the file or its
    record is absent, ``"damaged"`` when they differ."""
    try:
        record = _record_path(path).read_text()
    except (OSError, UnicodeDecodeError):
        return "missing"
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except FileNotFoundError:
        return "missing"
    except OSError:
        return "damaged"
    return "ok" if _digest(data) == record else "damaged"


def _discard(path: Path, why: str) -> None:
    if why == "damaged":
        warnings.warn(
            f"cached kernel {path} does not match its recorded size and SHA-256 (truncated or overwritten); rebuilding it",
            CacheIntegrityWarning,
            stacklevel=3,
        )
    for p in (path, _record_path(path)):
        try:
            p.unlink()
        except FileNotFoundError:
            pass


def cache_dir() -> Path:
    """Where compiled kernels are kept (``$DIFFFILTER_CACHE_DIR`` or ``~/.cache/difffilter/kernels``)."""
    root = os.environ.get("DIFFFILTER_CACHE_DIR")
    return Path(root) if root else Path.home() / ".cache" / "difffilter" / "kernels"


def _compiler() -> str | None:
    return _find_compiler(os.environ.get("CXX"), os.environ.get("PATH"))


@functools.lru_cache(maxsize=8)
def _find_compiler(cxx: str | None, path: str | None) -> str | None:
    # cached per (CXX, PATH): the search stats every PATH entry, and the engine policy asks on every call
    for name in (cxx, "g++", "c++", "clang++"):
        if name and shutil.which(name, path=path):
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


def _key_lock(key: str) -> threading.Lock:
    with _lock:
        return _key_locks.setdefault(key, threading.Lock())


@contextmanager
def _file_lock(path: Path) -> Iterator[None]:
    """Exclusive advisory lock on ``path`` across processes (a no-op without ``fcntl``)."""
    if fcntl is None:
        yield
        return
    with open(path, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


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
    with _key_lock(key):
        with _lock:
            lib = _loaded.get(key)
        if lib is not None:  # built by another thread meanwhile
            return lib
        root = cache_dir()
        root.mkdir(parents=True, exist_ok=True)
        target = root / f"{tag}_{key}.so"
        # never map an unverified file: a truncated shared object can SIGBUS the process
        if (verify_record(target) if target.exists() else "absent") != "ok":
            with _file_lock(root / f"{tag}_{key}.lock"):
                state = verify_record(target) if target.exists() else "absent"  # another process may have built it
                if state != "ok":
                    if state != "absent":
                        _discard(target, state)
                    _build(cxx, flags, source, root, target)
        try:
            lib = ctypes.CDLL(str(target))
        except OSError as err:  # verified yet unloadable (e.g. replaced between check and load): once more
            with _file_lock(root / f"{tag}_{key}.lock"):
                _discard(target, "damaged")
                _build(cxx, flags, source, root, target)
            try:
                lib = ctypes.CDLL(str(target))
            except OSError:
                raise CompileError(f"the freshly built kernel {target} cannot be loaded: {err}") from err
        with _lock:
            _loaded[key] = lib
        return lib


def _build(cxx: str, flags: list[str], source: str, root: Path, target: Path) -> None:
    with tempfile.TemporaryDirectory(dir=root) as tmp:
        src = Path(tmp) / "kernel.cpp"
        src.write_text(source)
        out = Path(tmp) / "kernel.so"
        proc = subprocess.run([cxx, *flags, str(src), "-o", str(out)], capture_output=True, text=True)
        if proc.returncode != 0:
            raise CompileError(f"{cxx} failed ({proc.returncode}): {proc.stderr[-3000:]}")
        write_record(target, out.read_bytes())  # the record first: a reader that sees the library sees it
        os.replace(out, target)
