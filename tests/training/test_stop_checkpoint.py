"""A stop signal checkpoints the step it lands on (not the last validation's), and checkpoints are also written by
time: what a Slurm time-limit warning, a requeue or a hard kill would otherwise lose (issue 30)."""

from __future__ import annotations

import signal

import pytest
import torch
from loopfakes import settings
from training.test_loop import trainer

from bronchocli.runs.contract import RunInterrupted
from bronchocli.training import checkpoint


class Flag:
    signal: int | None = None


@pytest.mark.parametrize("signum", [signal.SIGUSR1, signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_between_validations_checkpoints_the_current_step(tmp_path, signum):
    flag = Flag()

    def on_step(step, total):
        if step == 5:  # a signal that lands between the validations of steps 4 and 8
            flag.signal = signum

    t = trainer(settings(steps=12, val_every=4), ckpt_dir=tmp_path, stop=flag, on_step=on_step)
    with pytest.raises(RunInterrupted) as info:
        t.fit()
    name = signal.Signals(signum).name
    assert info.value.signal == signum
    assert str(info.value).startswith(f"{name} received at step 5/12")
    assert f"checkpoint of step 5 saved to {tmp_path / 'last.pt'}" in str(info.value)
    state = checkpoint.load(tmp_path / "last.pt")
    assert state["step"] == 5 and state["micro"] == 5  # the signal's step, not the validation's (4)
    assert [h["step"] for h in state["history"]] == [4.0]

    # resumed, it trains only steps 6..12 and ends on the same weights as a run never interrupted
    straight = trainer(settings(steps=12, val_every=4))
    straight.fit()
    resumed = trainer(settings(steps=12, val_every=4), seed=99)
    resumed.load_state(state)
    seen = []
    resumed.on_step = lambda step, total: seen.append(step)
    resumed.fit()
    assert seen == list(range(6, 13))
    a, b = straight.net.state_dict(), resumed.net.state_dict()
    assert all(torch.allclose(a[k].float(), b[k].float(), atol=1e-6) for k in a)


def test_checkpoints_are_written_by_time_independently_of_validation(tmp_path, monkeypatch):
    saved = []
    real_save = checkpoint.save

    def save(path, state):
        saved.append(state["step"])
        return real_save(path, state)

    monkeypatch.setattr(checkpoint, "save", save)
    clock = iter(float(k) for k in range(10_000))  # each reading of the clock is one second later
    monkeypatch.setattr("bronchocli.training.loop.time.monotonic", lambda: next(clock))
    t = trainer(settings(steps=6, val_every=6, checkpoint_every_s=1.5), ckpt_dir=tmp_path)
    t.fit()
    # one validation (step 6, which checkpoints anyway) and a checkpoint whenever 1.5 s of (fake) time passed
    assert saved == [2, 4, 6], saved
    never = trainer(settings(steps=6, val_every=6), ckpt_dir=tmp_path / "n")
    saved.clear()
    never.fit()
    assert saved == [6]  # the default (no time given to the loop): only the validation's


def test_a_run_taken_over_by_another_worker_never_overwrites_its_checkpoint(tmp_path):
    """A sweep worker that stalled past the cut-off lost its cell to another worker, which resumed the same run
    from the same checkpoint folder; woken up, the stalled one must not write its stale state over it."""
    from bronchocli.runs.contract import RunTakenOver

    flag = Flag()
    flag.owns = lambda: not taken
    taken = False
    theirs = tmp_path / "last.pt"

    def on_step(step, total):
        nonlocal taken
        if step == 5:  # the other worker took the run over and wrote its checkpoint; ours is then stopped
            taken = True
            theirs.write_bytes(b"the new owner's checkpoint")
            flag.signal = signal.SIGTERM

    t = trainer(settings(steps=12, val_every=4), ckpt_dir=tmp_path, stop=flag, on_step=on_step)
    with pytest.raises(RunTakenOver, match="step 5: another sweep worker took the run over"):
        t.fit()
    assert theirs.read_bytes() == b"the new owner's checkpoint"
