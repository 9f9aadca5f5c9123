"""The stop signals, met alike by every command: SIGINT (Ctrl-C), SIGTERM (``kill``, ``scancel``, a shutdown) and
SIGHUP (the terminal closed) all stop a command the way Ctrl-C does.

``as_keyboard_interrupts`` (installed by the command line around every command) turns each of them into a
``KeyboardInterrupt`` in the main thread, so the code that keeps Ctrl-C's promises (nothing half-written, the
frames or cells kept, a resumable state) keeps them for the other two as well; it records which signal arrived,
so the command exits with the shell's code for it (``exit_code``: 128 + the signal's number: 130 SIGINT,
143 SIGTERM, 129 SIGHUP) and its one line can name it (``name``). Code that handles the signals itself (a
training run stops after its step, the sweep's and tune's parent stops its workers) handles ``STOP_SIGNALS``
and tells ``note`` which one came.

A launcher may warn its workers with a signal of its own before it stops them (Slurm: SIGUSR1 before the time
limit). A worker declares it for its whole process with ``warned_by`` (the launcher's worker environment says
which signal and what sends it); a training run then stops on it as on the others (``stop_signals``) and its
KILLED reason names what sent it (``meaning``). Nothing here knows any launcher.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

STOP_SIGNALS: tuple[signal.Signals, ...] = tuple(
    s for s in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)) if s is not None)
_received: list[int] = []  # the stop signals this process received, in order
# what sends each stop signal, as a run's KILLED reason says it
MEANINGS = {"SIGTERM": "scancel, requeue or preemption", "SIGINT": "Ctrl-C", "SIGHUP": "the terminal closed"}
_warnings: dict[int, str] = {}  # a launcher's warning signal -> what sends it (``warned_by``)


@contextmanager
def warned_by(signum: int | None, meaning: str) -> Iterator[None]:
    """Inside: ``signum`` is a stop signal of this process too (``stop_signals``), sent by ``meaning`` (e.g.
    "Slurm's time-limit warning"); None: nothing changes. Declared by a sweep worker for its launcher."""
    if signum is None:
        yield
        return
    before = _warnings.get(int(signum))
    _warnings[int(signum)] = meaning
    try:
        yield
    finally:
        if before is None:
            _warnings.pop(int(signum), None)
        else:
            _warnings[int(signum)] = before


# SIGUSR1 reaching a command that no launcher warns with it (a plain `train`, outside Slurm): by default it would
# kill the process silently, leaving its run RUNNING; the command stops on it as on SIGTERM instead
UNWARNED_USR1 = "sent by no launcher of this process: stopped as on SIGTERM"


@contextmanager
def stopped_by(signum: int | None, meaning: str) -> Iterator[None]:
    """Inside: ``signum`` stops this command like the other stop signals: a run stops on it after its step and
    checkpoints (``warned_by``), and outside a run it raises KeyboardInterrupt (recorded, so the command exits
    with 128 + its number). A signal this process ignores stays ignored; None: nothing changes."""
    if signum is None or threading.current_thread() is not threading.main_thread():
        with warned_by(signum, meaning):
            yield
        return
    before = signal.getsignal(signum)
    replaced = before is signal.SIG_DFL
    if replaced:
        signal.signal(signum, _raise)
    try:
        with warned_by(signum, meaning):
            yield
    finally:
        if replaced:
            signal.signal(signum, before)


def stop_signals() -> tuple[int, ...]:
    """``STOP_SIGNALS`` and the warning signal of the launcher this process works for (``warned_by``)."""
    return (*STOP_SIGNALS, *(s for s in _warnings if s not in STOP_SIGNALS))


def meaning(signum: int) -> str | None:
    """What sends the stop signal ``signum`` ("Ctrl-C", a launcher's "time-limit warning"); None: not known."""
    if int(signum) in _warnings:
        return _warnings[int(signum)]
    return MEANINGS.get(signal.Signals(signum).name)


def note(signum: int) -> None:
    """Record that the stop signal ``signum`` arrived (its handler may do anything else)."""
    _received.append(int(signum))


def last() -> int | None:
    """The last stop signal this process received, or None."""
    return _received[-1] if _received else None


def exit_code(default: int = 130) -> int:
    """The shell's exit code of the last stop signal received (128 + its number); ``default`` when none came."""
    return 128 + _received[-1] if _received else default


def name(signum: int | None = None) -> str:
    """``SIGTERM``: the name of ``signum`` (default: the last one received; ``SIGINT`` when none came)."""
    signum = last() if signum is None else signum
    return signal.Signals(signum).name if signum is not None else "SIGINT"


def _raise(signum, frame) -> None:
    note(signum)
    raise KeyboardInterrupt


@contextmanager
def as_keyboard_interrupts() -> Iterator[None]:
    """Inside: every stop signal raises KeyboardInterrupt in the main thread (recorded); outside, the handlers
    that were there. Nothing changes when called from another thread (only the main thread may handle signals),
    nor for a signal this process ignores (a ``nohup`` SIGHUP stays ignored)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _received.clear()  # a command's exit code is that of its own signals (tests run many commands in one process)
    previous = {}
    for s in STOP_SIGNALS:
        if signal.getsignal(s) is signal.SIG_IGN:
            continue
        previous[s] = signal.signal(s, _raise)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


@contextmanager
def ignored_in_children() -> Iterator[None]:
    """Processes started in this block ignore SIGINT and SIGHUP from their first instruction (an ignored signal
    stays ignored across exec): a terminal's Ctrl-C or hang-up reaches its whole process group, and only the
    parent should act on it (it stops its children itself)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    quiet = [s for s in STOP_SIGNALS if s != signal.SIGTERM]
    previous = {s: signal.signal(s, signal.SIG_IGN) for s in quiet}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
