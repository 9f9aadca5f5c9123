"""Runs left RUNNING by a process that died: which process runs a run, whether it lives, ending the dead ones.

The liveness test (a pid and its start tick) is also what ``cores`` uses to ignore dead processes' entries.
"""

from __future__ import annotations

import logging
import os
import socket
from pathlib import Path
from typing import Any, Mapping

from mlflow.entities import Run

from ..errors import BronchoError
from .records import TAG_FAILURE

TAG_HOST, TAG_PID, TAG_PSTART = "process.host", "process.pid", "process.start"


def _process_start(pid: int) -> str | None:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def process_tags() -> dict[str, str]:
    """Which process runs a run (host, pid, start tick): lets the next process tell a live run from a dead one."""
    pid = os.getpid()
    return {TAG_HOST: socket.gethostname(), TAG_PID: str(pid), TAG_PSTART: process_start()}


def process_start() -> str:
    """This process's start tick (``/proc``; "?" where it cannot be read): with the pid, names one process."""
    return _process_start(os.getpid()) or "?"


def pid_alive(pid: int, start: str | None) -> bool:
    """Whether process ``pid`` of this host lives and is the one that started at tick ``start`` (None or "?":
    not compared), not another process that reused the pid."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # another user's live process
    now = _process_start(pid)
    return not (now is not None and start not in (None, "?") and now != start)  # pid reused by another process


def process_alive(tags: Mapping[str, str]) -> bool | None:
    """Whether the process a run's tags name is alive: True/False on this host, None when it cannot be told."""
    if tags.get(TAG_HOST) != socket.gethostname() or not str(tags.get(TAG_PID, "")).isdigit():
        return None
    return pid_alive(int(tags[TAG_PID]), tags.get(TAG_PSTART))


def repair_zombie(client: Any, run: Run, who: str) -> bool:
    """End a RUNNING run whose process died (FAILED, with the reason); True when it did.

    A run still alive is refused (one line); one on another host is left alone (the sweep's heartbeat
    takeover settles those).
    """
    if run.info.status != "RUNNING":
        return False
    alive = process_alive(run.data.tags)
    if alive:
        raise BronchoError(f"run {run.info.run_id} is still running (process {run.data.tags.get(TAG_PID)} on this "
                           "host); stop it first (Ctrl-C or kill -TERM), then resume")
    if alive is None:
        return False
    reason = (f"process {run.data.tags.get(TAG_HOST)}:{run.data.tags.get(TAG_PID)} ended without closing the run "
              f"(killed, or the store was unwritable); marked FAILED by {who}")
    client.set_tag(run.info.run_id, TAG_FAILURE, reason)
    client.set_terminated(run.info.run_id, "FAILED")
    logging.getLogger(__name__).warning("run %s: %s", run.info.run_id, reason)
    fail_pending_models(client, run)
    return True


def fail_pending_models(client: Any, run: Run) -> list[str]:
    """Mark FAILED the logged models of ``run`` left PENDING (its process was killed while logging the model:
    nothing else would ever finalise them); returns their ids."""
    try:
        models = client.search_logged_models(
            [run.info.experiment_id], filter_string=f"source_run_id = '{run.info.run_id}'")  # status: compared below
    except Exception as exc:  # noqa: BLE001 - a store without logged models (an old server): nothing to finalise
        logging.getLogger(__name__).debug("logged models of run %s not searched: %s", run.info.run_id, exc)
        return []
    ids = [m.model_id for m in models if str(getattr(m.status, "name", m.status)).upper().endswith("PENDING")]
    for model_id in ids:
        client.finalize_logged_model(model_id, "FAILED")
        logging.getLogger(__name__).warning("logged model %s of run %s was left PENDING: marked FAILED",
                                            model_id, run.info.run_id)
    return ids


def process_age_s() -> float | None:
    """Seconds since this process started (Linux ``/proc``; None elsewhere): the start-up a user waits through."""
    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        start_ticks = int(fields[19])  # field 22 of stat(5), counted after the command name
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return uptime - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None
