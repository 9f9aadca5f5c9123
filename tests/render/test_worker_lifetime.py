"""Render pool workers die with the process that started them (issue 32.7: a killed `data generate` left its
workers rendering): ``init_worker`` asks the kernel for SIGKILL when the parent dies (Linux PR_SET_PDEATHSIG)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

POOL = """
import os, sys, threading
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from bronchocli.render.tasks import init_worker
pool = ProcessPoolExecutor(1, mp_context=get_context("spawn"), initializer=init_worker, initargs=(1, os.getpid()))
print(pool.submit(os.getpid).result(), flush=True)
threading.Event().wait()  # the parent is busy for ever (rendering): it is killed, never returns
"""


def _running(pid: int) -> bool:
    """True while ``pid`` exists and is not a zombie (a killed orphan may wait unreaped under a bare init)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_render_worker_dies_when_its_parent_is_killed():
    parent = subprocess.Popen([sys.executable, "-c", POOL], stdout=subprocess.PIPE, text=True,
                              start_new_session=True)
    try:
        worker = int(parent.stdout.readline())
        assert _running(worker)
        os.kill(parent.pid, signal.SIGKILL)  # as `kill -9` of data generate: no handler, no pool shutdown
        parent.wait(timeout=60)
        end = time.monotonic() + 60
        while _running(worker):  # the kernel sends the signal at the parent's exit; allow a loaded machine
            assert time.monotonic() < end, f"render worker {worker} still running after its parent was killed"
            time.sleep(0.05)
    finally:
        if parent.poll() is None:
            parent.kill()
        parent.stdout.close()
