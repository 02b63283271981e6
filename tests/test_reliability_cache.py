"""Kernel cache integrity: a damaged cached kernel or program is rebuilt, never loaded.

A truncated shared object can kill the loading process with SIGBUS (no Python exception) and a
garbage one raises ``OSError: file too short``; both used to happen on the next process that
found the entry.  Each case runs the loader in a fresh subprocess, so a crash fails the test
instead of killing pytest, and checks the value the rebuilt kernel computes.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from difffilter.engines import build, cache

pytestmark = pytest.mark.skipif(build.compiler_available() is not None, reason="no C++ compiler")

_ROOT = Path(__file__).resolve().parents[1]
_SCRIPT = textwrap.dedent(
    """
    import ctypes, warnings
    from difffilter.engines import build
    src = 'extern "C" double forward(double x) { return 3.0 * x + 1.0; }'
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fn = build.compile_library(src, tag="forward", opt="-O0").forward
    fn.restype = ctypes.c_double
    fn.argtypes = [ctypes.c_double]
    n = sum(issubclass(w.category, build.CacheIntegrityWarning) for w in caught)
    print(f"value={fn(2.0)} warnings={n}")
    """
)


def _load_in_subprocess(cache_root: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "DIFFFILTER_CACHE_DIR": str(cache_root), "PYTHONPATH": str(_ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True, env=env, timeout=120)


def _damage_truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])


def _damage_garbage(path: Path) -> None:
    path.write_bytes(b"not an ELF file" * 7)


def _damage_flip(path: Path) -> None:  # same size, one byte differs: only the hash sees it
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(
    "damage",
    [
        _damage_truncate,  # the SIGBUS case: in the default suite
        pytest.param(_damage_garbage, marks=pytest.mark.slow),  # three Python processes each: ~5 s apiece
        pytest.param(_damage_flip, marks=pytest.mark.slow),
    ],
    ids=["truncated", "garbage", "flipped"],
)
def test_a_damaged_cached_kernel_is_rebuilt_with_one_warning(tmp_path: Path, damage) -> None:  # type: ignore[no-untyped-def]
    first = _load_in_subprocess(tmp_path)
    assert first.returncode == 0, first.stderr
    assert "value=7.0 warnings=0" in first.stdout
    (so,) = tmp_path.glob("forward_*.so")
    assert so.with_name(so.name + ".sha256").read_text().split()[0] == str(so.stat().st_size)
    damage(so)
    second = _load_in_subprocess(tmp_path)
    assert second.returncode == 0, f"exit {second.returncode}: {second.stderr[-2000:]}"
    assert "value=7.0 warnings=1" in second.stdout
    third = _load_in_subprocess(tmp_path)  # the rebuilt entry is whole again: no warning
    assert "value=7.0 warnings=0" in third.stdout, third.stderr


@pytest.mark.slow
def test_an_entry_without_a_record_is_rebuilt_silently(tmp_path: Path) -> None:
    """An entry from before records existed cannot be verified: it is rebuilt, not loaded."""
    assert _load_in_subprocess(tmp_path).returncode == 0
    (so,) = tmp_path.glob("forward_*.so")
    so.with_name(so.name + ".sha256").unlink()
    _damage_truncate(so)
    out = _load_in_subprocess(tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "value=7.0 warnings=0" in out.stdout


def _stored_program(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("DIFFFILTER_CACHE_DIR", str(tmp_path))
    path = cache.program_path("0" * 40)
    data = pickle.dumps({"params": []}, protocol=pickle.HIGHEST_PROTOCOL)
    build.write_record(path, data)
    build.atomic_write(path, data)
    assert build.verify_record(path) == "ok"
    return path


@pytest.mark.parametrize("damage", [_damage_truncate, _damage_garbage], ids=["truncated", "garbage"])
def test_a_damaged_stored_program_is_never_unpickled(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, damage) -> None:  # type: ignore[no-untyped-def]
    path = _stored_program(tmp_path, monkeypatch)
    damage(path)

    def no_unpickle(data: bytes) -> object:
        raise AssertionError("a damaged program was unpickled")

    monkeypatch.setattr(cache.pickle, "loads", no_unpickle)
    with pytest.warns(build.CacheIntegrityWarning, match="SHA-256"):
        assert cache._load(path, None) is None  # type: ignore[arg-type]


def test_a_program_without_a_record_is_a_silent_miss(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = _stored_program(tmp_path, monkeypatch)
    path.with_name(path.name + ".sha256").unlink()
    monkeypatch.setattr(cache.pickle, "loads", lambda data: pytest.fail("an unverified program was unpickled"))
    assert cache._load(path, None) is None  # type: ignore[arg-type]
