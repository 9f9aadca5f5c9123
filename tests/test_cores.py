"""runs.cores: the fair share of the CPU cores between this project's processes (issue 40)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bronchocli.runs import cores
from bronchocli.runs.cores import Claim, CoreShare, decide, live_claims
from bronchocli.runs.processes import process_start


def claim(n: int, since: float | None = None, threads: int | None = None, explicit: bool = False) -> Claim:
    return Claim(f"c{n}", pid=os.getpid(), start="?", since=float(n if since is None else since), threads=threads,
                 explicit=explicit)


def test_two_live_processes_on_two_cores_take_one_thread_each():
    a, b = claim(1), claim(2)
    assert decide(2, a, [b]) == cores.Decision(1, "share of 2 cores with 2 processes")
    assert decide(2, b, [a]).threads == 1


def test_a_process_alone_takes_every_core():
    assert decide(4, claim(1), []) == cores.Decision(4, "share of 4 cores with 1 process")


def test_the_remainder_goes_to_the_oldest_claims_and_the_shares_add_up_to_the_cores():
    a, b, c = claim(1), claim(2), claim(3)
    assert [decide(8, me, [o for o in (a, b, c) if o != me]).threads for me in (a, b, c)] == [3, 3, 2]


def test_an_explicit_count_always_wins_and_is_held_against_the_others():
    sharing, fixed = claim(1), claim(2, threads=3, explicit=True)
    assert decide(2, fixed, [sharing], explicit=3) == cores.Decision(3, "explicit (train.threads)")
    assert decide(2, fixed, [], explicit=1, explicit_from="--threads").source == "explicit (--threads)"
    got = decide(4, sharing, [fixed])
    assert got.threads == 1 and got.source == "share of 4 cores with 2 processes (3 held by explicit ones)"


def test_never_fewer_than_one_thread():
    me = claim(9)
    assert decide(2, me, [claim(i) for i in range(4)]).threads == 1
    assert decide(2, me, [claim(1, threads=8, explicit=True)]).threads == 1


def test_a_workers_pin_caps_its_share_until_its_siblings_claim():
    me = claim(1)
    pinned = decide(4, me, [], workers=2)
    assert pinned == cores.Decision(2, "worker pin: 4 cores / 2 workers of its command")
    assert decide(4, me, [claim(2), claim(3)], workers=2).threads == 2  # share 2, pin 2: the share says why
    assert decide(4, me, [claim(2), claim(3)], workers=2).source.startswith("share of 4 cores")


@settings(deadline=None)  # pure arithmetic; a loaded machine's pauses are no failure
@given(st.integers(1, 64), st.integers(1, 64))
def test_sharing_processes_never_hold_more_than_the_cores(n_cores, n_procs):
    claims = [claim(i) for i in range(n_procs)]
    total = sum(decide(n_cores, me, [o for o in claims if o is not me]).threads for me in claims)
    assert total == max(n_cores, n_procs)  # every core used; over the cores only by the one-thread floor


def test_claims_of_dead_processes_are_ignored_and_removed(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    (tmp_path / "gone.json").write_text(json.dumps({"pid": pid, "start": "?", "since": 1.0, "threads": 2}))
    reused = {"pid": os.getpid(), "start": "-1", "since": 2.0, "threads": 2}  # this pid, another process's start
    (tmp_path / "reused.json").write_text(json.dumps(reused))
    (tmp_path / "torn.json").write_text("{")  # being written: not a claim now, left alone
    with CoreShare(None, folder=tmp_path, cores=2) as share:
        assert share.check() == cores.Decision(2, "share of 2 cores with 1 process")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["torn.json"]


def test_claims_in_one_folder_share_and_give_back_their_cores(tmp_path):
    with CoreShare(None, folder=tmp_path, cores=2) as first:
        assert first.check().threads == 2
        with CoreShare(None, folder=tmp_path, cores=2) as second:
            assert second.check().threads == 1
            assert first.check().threads == 1  # the re-check at a validation
            (entry,) = [c for c in live_claims(tmp_path) if c.token == second.me.token]
            assert entry.threads == 1 and entry.pid == os.getpid() and entry.start == process_start()
        assert first.check().threads == 2
    assert list(tmp_path.iterdir()) == []


def test_a_training_process_re_decides_within_seconds_not_at_its_next_validation(tmp_path):
    """A run started alone takes every core; another command starting takes one of them back within RECHECK_S
    of training (asked every step through ``fresh``), not only at the next validation (issue 40's defect)."""
    now = [100.0]
    with CoreShare(None, folder=tmp_path, cores=2) as first:
        assert first.fresh(clock=lambda: now[0]) == 2
        with CoreShare(None, folder=tmp_path, cores=2) as second:
            assert second.check().threads == 1
            now[0] += cores.RECHECK_S / 2
            assert first.fresh(clock=lambda: now[0]) == 2  # the decision is still young: no listing
            now[0] += cores.RECHECK_S / 2
            assert first.fresh(clock=lambda: now[0]) == 1  # old enough: decided again, beside the newcomer
            (entry,) = [c for c in live_claims(tmp_path) if c.token == first.me.token]
            assert entry.threads == 1  # and the others see it gave the core back
        now[0] += cores.RECHECK_S
        assert first.fresh(clock=lambda: now[0]) == 2


def test_an_explicit_claim_is_recorded_for_the_others(tmp_path):
    with CoreShare(3, folder=tmp_path, cores=4) as fixed:
        assert fixed.check() == cores.Decision(3, "explicit (train.threads)")
        with CoreShare(None, folder=tmp_path, cores=4) as other:
            assert other.check().threads == 1


def test_an_unwritable_folder_leaves_the_process_deciding_alone(tmp_path, caplog):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with CoreShare(None, folder=blocker / "cores", cores=3) as share:
        assert share.check().threads == 3
    assert "not writable" in caplog.text


def test_the_claims_folder_is_the_users_runtime_folder_or_a_per_user_temporary_one(tmp_path):
    assert cores.claims_folder({"XDG_RUNTIME_DIR": str(tmp_path)}) == tmp_path / "bronchopose" / "cores"
    fallback = cores.claims_folder({})
    assert fallback.name == "cores" and fallback.parent.name.startswith("bronchopose-")
    assert cores.claims_folder({"XDG_RUNTIME_DIR": str(tmp_path / "missing")}) == fallback


@pytest.mark.parametrize("value, want", [("2", 2), ("", None), ("0", None), ("x", None)])
def test_workers_here_reads_the_command_s_worker_count(value, want):
    assert cores.workers_here({cores.WORKERS_ENV: value}) == want
