"""What keeps a sweep worker's claim alive and how the worker stops: the heartbeat thread and the stop signals.

A worker (``worker.py``) installs ``StopSignals`` (SIGINT, SIGTERM, and SIGUSR1 in a Slurm task) and runs a
``Heartbeat`` beside each cell it holds: the heartbeat refreshes the claim in the claims table, and tells the
worker once when another worker has taken the claim over (this one looked dead); ``Heartbeat.holds`` is what
the run asks before it writes a checkpoint or ends, so a worker that stalled past the cut-off and woke up
never writes over the run of the worker that took its cell over.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from .. import interrupts
from ..runs.contract import RunInterrupted
from .storage import RUNNING, CellRow, StorageError, SweepStore

log = logging.getLogger(__name__)


def is_interrupt(exc: BaseException) -> bool:
    return isinstance(exc, (KeyboardInterrupt, RunInterrupted))


class StopSignals:
    """Turns SIGINT/SIGTERM/SIGHUP into a stop request; interrupts the runner when one is in progress."""

    def __init__(self, event: Any = None, parent_pid: int | None = None):
        self.requested: int | None = None
        self.installed = False  # only a process that handles SIGTERM itself may send it to itself
        self.in_runner = False
        self.self_term = False  # a SIGTERM we sent ourselves because the claim was lost
        self.event, self.parent_pid = event, parent_pid

    def install(self, extra: Sequence[int] = ()) -> None:
        """Handle SIGINT, SIGTERM, SIGHUP (``interrupts.STOP_SIGNALS``) and ``extra`` (under Slurm: SIGUSR1, the
        time-limit warning) as a stop."""
        for s in (*interrupts.STOP_SIGNALS, *extra):
            signal.signal(s, self._handle)
        self.installed = True

    def _handle(self, signum: int, frame: Any) -> None:
        if self.self_term and signum == signal.SIGTERM:
            self.self_term = False
        else:
            self.requested = signum
        if self.in_runner:
            raise KeyboardInterrupt

    def parent_gone(self) -> bool:
        return self.parent_pid is not None and os.getppid() != self.parent_pid

    @property
    def stop(self) -> bool:
        return self.requested is not None or (self.event is not None and self.event.is_set()) or self.parent_gone()

    def wait(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while not self.stop and (left := end - time.monotonic()) > 0:
            time.sleep(min(0.1, left))


class Heartbeat(threading.Thread):
    """Refreshes the claim every ``interval`` seconds; calls ``on_lost`` once if the claim is gone."""

    def __init__(self, store: SweepStore, token: str, interval: float, on_lost: Callable[[], None],
                 signals: StopSignals, lease_s: float = math.inf):
        super().__init__(name="sweep-heartbeat", daemon=True)
        self.store, self.token, self.interval, self.on_lost, self.signals = store, token, interval, on_lost, signals
        self.lease_s = lease_s  # sweep.stale_after_s: how long after its last heartbeat a claim can be taken over
        self.lost = False
        self.renewed_at = time.monotonic()
        self._halt = threading.Event()

    def holds(self) -> bool:
        """Whether this worker still holds the claim, asked before the run writes a checkpoint or ends: renews it
        (so no takeover can start for ``lease_s``) and answers False once another worker took it over. With the
        claims database away it holds while its last renewal is well within ``lease_s`` (nobody can have
        taken it over yet), and not after: past that, a worker cut off from the database may have lost it."""
        if self.lost:
            return False
        try:
            return self._renew()
        except StorageError as exc:
            log.warning("claim not renewed: %s", exc)
            return time.monotonic() - self.renewed_at < 0.8 * self.lease_s

    def _renew(self) -> bool:
        """One heartbeat: True when the claim is still ours (renewed now), False (for good) when it is not."""
        if self.store.heartbeat(self.token):
            self.renewed_at = time.monotonic()
            return True
        self.lost = True
        return False

    def run(self) -> None:
        while not self._halt.wait(self.interval):
            if self.signals.installed and self.signals.parent_gone() and self.signals.requested is None:
                log.warning("parent process is gone: stopping")
                self.signals.requested = signal.SIGTERM
                os.kill(os.getpid(), signal.SIGTERM)
            try:
                alive = self._renew()
            except StorageError as exc:  # transient outage: the claim goes stale only after stale_after_s
                log.warning("heartbeat failed: %s", exc)
                continue
            if not alive:
                if not self._halt.is_set():
                    self.on_lost()
                return

    def halt(self) -> None:
        self._halt.set()
        if self.is_alive():
            self.join()


class FutureHeartbeats:
    """Claims whose heartbeat lies ahead of the database's clock, judged on this reader's own clock.

    The stale cut-off compares a heartbeat with the database's clock; where that clock is each machine's own
    (SQLite on shared storage) a worker whose clock runs ahead writes heartbeats from the future, which would
    never look stale. Such a claim is alive while its heartbeat changes: one seen unchanged (same claim, same
    value) for ``stale_after_s`` of this process's monotonic clock is overdue, and ``SweepStore.claim`` takes it
    over like any stale claim (``overdue``)."""

    def __init__(self, stale_after_s: float, clock: Callable[[], float] = time.monotonic):
        self.stale_after_s, self.clock = stale_after_s, clock
        self._seen: dict[str, tuple[tuple[str | None, float], float]] = {}  # key -> ((token, heartbeat), first seen)

    def new(self, rows: Iterable[CellRow], now: float) -> list[CellRow]:
        """Watch ``rows`` (read at database time ``now``); returns the claims from the future first seen now."""
        fresh, ahead = [], set()
        for r in rows:
            if r.damage is None and r.state == RUNNING and r.heartbeat is not None and r.heartbeat > now:
                ahead.add(r.cell_key)
                value = (r.token, r.heartbeat)
                seen = self._seen.get(r.cell_key)
                if seen is None or seen[0] != value:  # new, or renewed by a live worker: the wait starts again
                    if seen is None:
                        fresh.append(r)
                    self._seen[r.cell_key] = (value, self.clock())
        for key in set(self._seen) - ahead:
            del self._seen[key]
        return fresh

    def overdue(self) -> dict[str, float]:
        """Cell key -> the heartbeat seen unchanged for ``stale_after_s``: its claim may be taken over."""
        t = self.clock()
        return {k: value[1] for k, (value, since) in self._seen.items() if t - since >= self.stale_after_s}
