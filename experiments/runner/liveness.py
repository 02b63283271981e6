"""Tell a run that is still running from one that was killed without a word.

A process killed by SIGKILL (or the OOM killer, or a lost node) cannot update its
``status.json``, which then says ``running`` forever.  The status of a running run therefore
carries the process id, the host name and a heartbeat: :class:`Heartbeat` rewrites the
``heartbeat`` timestamp every ``interval`` seconds from a daemon thread.  :func:`assess` reads a
recorded status and reports what is true now:

* ``killed``: the status says running, the run's host is this machine, and no process has the
  recorded id;
* ``stale``: the status says running but the heartbeat is older than ``stale_factor`` (3)
  heartbeat intervals - the process is gone (its id possibly reused), hung, or on a machine
  this reader cannot see;
* otherwise the recorded status.

An assessed status keeps the recorded one as ``recorded_status`` and says why in ``reason``.
"""

from __future__ import annotations

import datetime as _dt
import os
import socket
import threading
from collections.abc import Callable
from typing import Any

__all__ = ["HEARTBEAT_INTERVAL_S", "Heartbeat", "assess", "process_alive", "stamp"]

#: seconds between heartbeats of a running run
HEARTBEAT_INTERVAL_S = 30.0


def _now() -> _dt.datetime:
    return _dt.datetime.now(_dt.timezone.utc)


def stamp(state: dict[str, Any], *, interval: float = HEARTBEAT_INTERVAL_S) -> dict[str, Any]:
    """Add this process's id, host and a fresh heartbeat to a status ``state`` (in place)."""
    state.update(
        pid=os.getpid(), host=socket.gethostname(), heartbeat=_now().isoformat(timespec="milliseconds"), heartbeat_interval_s=interval
    )
    return state


def process_alive(pid: int) -> bool:
    """Whether a process with id ``pid`` exists on this machine."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def assess(state: dict[str, Any], *, stale_factor: float = 3.0, now: _dt.datetime | None = None) -> dict[str, Any]:
    """``state`` (a ``status.json``) with ``status`` replaced by ``killed`` or ``stale`` where a
    recorded ``running`` is no longer true (module docstring); a copy, never the argument."""
    out = dict(state)
    if state.get("status") != "running":
        return out
    pid, host, beat = state.get("pid"), state.get("host"), state.get("heartbeat")
    if isinstance(pid, int) and host == socket.gethostname() and not process_alive(pid):
        out.update(
            status="killed",
            recorded_status="running",
            reason=f"process {pid} on {host} no longer exists (killed without a chance to record it)",
        )
        return out
    if beat is None:
        return out  # written by a version without heartbeats: nothing to judge by
    try:
        last = _dt.datetime.fromisoformat(str(beat))
    except ValueError:
        return out
    if last.tzinfo is None:
        last = last.astimezone()
    age = ((now or _now()) - last).total_seconds()
    limit = stale_factor * float(state.get("heartbeat_interval_s", HEARTBEAT_INTERVAL_S))
    if age > limit:
        out.update(status="stale", recorded_status="running", reason=f"no heartbeat for {age:.0f} s (more than {limit:.0f} s)")
    return out


class Heartbeat:
    """Call ``write()`` every ``interval`` seconds from a daemon thread until :meth:`stop`."""

    def __init__(self, write: Callable[[], None], *, interval: float = HEARTBEAT_INTERVAL_S) -> None:
        if not interval > 0:
            raise ValueError(f"interval must be > 0 seconds, got {interval!r}")
        self.interval = float(interval)
        self._write = write
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="difffilter-heartbeat", daemon=True)

    def start(self) -> Heartbeat:
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                self._write()
            except OSError:  # a full or vanished disk: the next beat tries again
                pass

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=self.interval + 1)
