"""A trial's Optuna heartbeat thread left running by a stop signal is ended (the worker would hang at exit)."""

from __future__ import annotations

import threading

import optuna
from optuna.storages._heartbeat import HeartbeatThread

from bronchocli.sweep.tuning.worker import end_heartbeats


class _Beats:
    """The heartbeat side of a storage, counting the beats it records."""

    def __init__(self) -> None:
        self.beats = 0
        self.first = threading.Event()

    def get_heartbeat_interval(self) -> int:
        return 3600  # the thread would wait an hour between beats: only its stop event ends it

    def record_heartbeat(self, trial_id: int) -> None:
        self.beats += 1
        self.first.set()


def test_a_heartbeat_whose_with_block_never_ran_is_stopped_and_joined():
    beats = _Beats()
    orphan = HeartbeatThread(7, beats)  # what optuna's __enter__ starts; a signal then skips its __exit__
    orphan.start()
    assert beats.first.wait(10)
    thread = orphan._thread
    assert thread.is_alive() and not thread.daemon  # the interpreter would wait for it at shutdown
    assert end_heartbeats() == 1
    assert not thread.is_alive()
    assert beats.beats == 1  # stopped in its wait, not after another beat
    assert end_heartbeats() == 0  # nothing left


def test_threads_that_are_not_optuna_heartbeats_are_left_alone():
    stop = threading.Event()
    other = threading.Thread(target=lambda a, b, c: c.wait(), args=(None, None, stop))
    other.start()
    try:
        assert end_heartbeats(timeout_s=0.1) == 0
        assert other.is_alive()
    finally:
        stop.set()
        other.join()


def test_the_optuna_heartbeat_loop_is_where_end_heartbeats_looks():
    # the name end_heartbeats matches: a renamed loop in a newer Optuna must fail here, not hang workers
    assert HeartbeatThread._record_heartbeat.__qualname__ == "HeartbeatThread._record_heartbeat"
    assert optuna.__version__
