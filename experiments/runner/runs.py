"""The life of a run directory: its status file, resuming, and evaluating a checkpoint under the
config it was trained with.

* :func:`run_status` - a context manager that writes ``status.json`` into the run directory:
  ``running`` at the start (with the process id, host and a heartbeat renewed every 30 s), then
  ``completed``, ``interrupted`` (SIGTERM/SIGINT; with the checkpoint and the command that
  resumes), ``diverged`` (:mod:`difffilter.learn.divergence`; with the reason) or ``failed``
  (with the error), so that a failed or stopped run is marked as such instead of looking like
  an empty or unfinished folder; :func:`read_status` reports a ``running`` whose process was
  killed (SIGKILL leaves no chance to write) as ``killed`` or ``stale``
  (:mod:`experiments.runner.liveness`);
* :func:`resume_checkpoint` - the checkpoint a training run continues from (``ckpt_path=``, or
  ``resume=true``: ``last.ckpt`` of this run directory);
* :func:`checkpoint_config` - the config an evaluation of a checkpoint runs under: the stored
  config of the run that wrote it, with this invocation's paths, trainer, loggers and callbacks,
  and the values given on the command line.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import logging
import signal
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf, open_dict
from pytorch_lightning.utilities.exceptions import SIGTERMException
from pytorch_lightning.utilities.rank_zero import rank_zero_only

from difffilter.learn.callbacks import TrainingInterrupted
from difffilter.learn.checkpoints import read_checkpoint, run_config
from difffilter.learn.divergence import TrainingDivergedError

from .liveness import HEARTBEAT_INTERVAL_S, Heartbeat, assess, stamp

__all__ = ["STATUS_FILE", "LightningTips", "checkpoint_config", "read_status", "resume_checkpoint", "run_status"]

log = logging.getLogger(__name__)

STATUS_FILE = "status.json"
#: Nodes an evaluation takes from its own invocation, not from the checkpoint's run.
RUNTIME_NODES = ("paths", "trainer", "logger", "callbacks", "task_name", "train", "ckpt_path", "resume", "config_from_checkpoint")


def _now() -> str:
    return _dt.datetime.now().isoformat(timespec="seconds")


def _command(checkpoint: str | None) -> str | None:
    """The command line that resumes this run (``None`` outside a Hydra app)."""
    if not HydraConfig.initialized():
        return None
    hc = HydraConfig.get()
    keep = [o for o in hc.overrides.task if o.split("=", 1)[0].lstrip("+~") not in ("ckpt_path", "resume", "hydra.run.dir")]
    script = "experiments/train.py" if hc.job.name == "train" else f"{hc.job.name}.py"
    return " ".join(["python", script, *keep, f"hydra.run.dir={hc.runtime.output_dir}", "resume=true"])


_write_lock = threading.Lock()  # the heartbeat thread and the run write the same file


def _write(path: Path, state: dict[str, Any]) -> None:
    if rank_zero_only.rank != 0:
        return
    with _write_lock:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(state, indent=2) + "\n")
        tmp.replace(path)


def read_status(run_dir: str | Path, *, raw: bool = False) -> dict[str, Any] | None:
    """The ``status.json`` of a run directory (``None`` if it has none); a recorded ``running``
    whose process is gone reads as ``killed`` or ``stale`` (:func:`~experiments.runner.liveness.assess`),
    unless ``raw``."""
    p = Path(run_dir) / STATUS_FILE
    if not p.is_file():
        return None
    state = json.loads(p.read_text())
    return state if raw else assess(state)


@contextlib.contextmanager
def run_status(run_dir: str | Path, *, heartbeat_s: float = HEARTBEAT_INTERVAL_S) -> Iterator[dict[str, Any]]:
    """Mark ``run_dir`` as running (heartbeat every ``heartbeat_s`` seconds), then completed /
    interrupted / diverged / failed (module docstring).

    A SIGTERM that Lightning turned into its own stop (exit status 0) is re-raised as
    :class:`~difffilter.learn.callbacks.TrainingInterrupted` (exit status 143)."""
    path = Path(run_dir) / STATUS_FILE
    state: dict[str, Any] = stamp({"status": "running", "started": _now()}, interval=heartbeat_s)

    def beat() -> None:
        if state.get("status") == "running":
            _write(path, stamp(state, interval=heartbeat_s))

    _write(path, state)
    heart = Heartbeat(beat, interval=heartbeat_s).start()
    try:
        yield state
    except (TrainingInterrupted, SIGTERMException, KeyboardInterrupt) as exc:
        checkpoint = getattr(exc, "checkpoint", None) or _existing(Path(run_dir) / "checkpoints" / "last.ckpt")
        signum = getattr(exc, "signum", int(signal.SIGINT if isinstance(exc, KeyboardInterrupt) else signal.SIGTERM))
        state.update(status="interrupted", ended=_now(), signal=signal.Signals(signum).name, checkpoint=checkpoint)
        state["resume"] = _command(checkpoint) if checkpoint else None
        _write(path, state)
        log.error("run interrupted by %s%s", state["signal"], f"; resume with: {state['resume']}" if state["resume"] else "")
        if isinstance(exc, TrainingInterrupted):
            raise
        raise TrainingInterrupted(signum, checkpoint) from exc
    except TrainingDivergedError as exc:
        state.update(status="diverged", ended=_now(), error=str(exc))
        _write(path, state)
        log.error("%s", exc)
        raise
    except BaseException as exc:
        state.update(status="failed", ended=_now(), error=f"{type(exc).__name__}: {exc}")
        _write(path, state)
        log.exception("run failed")
        raise
    else:
        state.update(status="completed", ended=_now())
        _write(path, state)
    finally:
        heart.stop()


def _existing(path: Path) -> str | None:
    return str(path) if path.is_file() else None


def resume_checkpoint(cfg: DictConfig) -> str | None:
    """The checkpoint a training run resumes from: ``cfg.ckpt_path`` (must exist), else with
    ``cfg.resume`` the ``checkpoints/last.ckpt`` of this run directory (``hydra.run.dir=<the
    interrupted run>``; a first start with ``resume=true`` finds none and starts afresh), else
    ``None``."""
    if cfg.get("ckpt_path"):
        path = Path(str(cfg.ckpt_path))
        if not path.is_file():
            raise FileNotFoundError(f"ckpt_path: no checkpoint file {path}")
        return str(path)
    if cfg.get("resume"):
        last = Path(str(cfg.paths.output_dir)) / "checkpoints" / "last.ckpt"
        if last.is_file():
            log.info("resuming from %s", last)
            return str(last)
        log.info("resume=true: no %s yet, starting afresh", last)
    return None


def _command_line_keys() -> tuple[list[str], list[str]]:
    """``(value keys, group choices)`` set on this command line."""
    if not HydraConfig.initialized():
        return [], []
    hc = HydraConfig.get()
    groups = set(hc.runtime.choices)
    keys = [o.split("=", 1)[0].lstrip("+~") for o in hc.overrides.task if "=" in o]
    return [k for k in keys if k not in groups], [k for k in keys if k in groups]


def checkpoint_config(cfg: DictConfig, checkpoint: str | Path, *, overrides: Sequence[str] | None = None) -> DictConfig:
    """The config under which ``checkpoint`` is evaluated: its run's stored config (what the
    learner was built from), with ``cfg``'s runtime nodes (:data:`RUNTIME_NODES`: output paths,
    trainer, loggers, callbacks) and the values of ``overrides`` (dotted keys; default: the keys
    set on this command line) taken from ``cfg``.  A group choice on the command line
    (``experiment=...``) cannot be applied to a stored config: evaluate with
    ``config_from_checkpoint=false`` to compose a different experiment."""
    stored = run_config(read_checkpoint(checkpoint))
    if stored is None:
        raise ValueError(
            f"{checkpoint} holds no run config (it was not written by run_experiment): evaluate it with "
            "config_from_checkpoint=false and the overrides of its training run"
        )
    merged = OmegaConf.create(stored)
    keys, groups = _command_line_keys()
    keys = keys if overrides is None else list(overrides)
    # debug/ and hydra/ overlays only reach the runtime nodes here; any other group would change
    # what the stored run was
    changed = [g for g in groups if g.split("/", 1)[0] not in (*RUNTIME_NODES, "debug", "hydra")]
    if changed:
        raise ValueError(
            f"{', '.join(changed)}=...: a config group cannot be changed for a stored run config; "
            "add config_from_checkpoint=false to evaluate under the composed config instead"
        )
    with open_dict(merged):
        for node in RUNTIME_NODES:
            if node in cfg:
                merged[node] = cfg[node]
        for key in keys:
            if key.split(".", 1)[0] in RUNTIME_NODES or key.startswith("hydra"):
                continue
            OmegaConf.update(merged, key, OmegaConf.select(cfg, key, throw_on_missing=False), force_add=True)
    return merged


class LightningTips(logging.Filter):
    """A logging filter that drops Lightning's advertising tips (``💡 Tip: ...``) and keeps every
    other record; the run's logging config (``conf/hydra/job_logging/difffilter.yaml``) puts it
    on the console and log-file handlers."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).lstrip().startswith("💡")
