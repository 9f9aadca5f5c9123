"""Checkpoints: plain data loaded with weights_only=True, refused when planted or foreign, CUDA RNG of one device,
free space checked and failed writes leaving nothing behind."""

from __future__ import annotations

import errno
import pickle
import random
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from training.test_loop import settings, trainer

from bronchocli.io import fmt_bytes
from bronchocli.runs.ownership import MARKER
from bronchocli.training import checkpoint
from bronchocli.training.checkpoint import BadCheckpoint, CheckpointWriteError


class WritesAFile:
    """Unpickling this writes ``marker``: what a planted checkpoint would do (any code could run instead)."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (Path.write_text, (Path(self.marker), "code ran"))


def fitted(tmp_path: Path, steps: int = 2):
    t = trainer(settings(steps=steps, val_every=2), ckpt_dir=tmp_path / "run1", cell_key="cellA")
    t.fit()
    return t, tmp_path / "run1" / "last.pt"


def test_a_checkpoint_is_plain_data_that_loads_with_weights_only(tmp_path):
    t, path = fitted(tmp_path)
    state = torch.load(path, map_location="cpu", weights_only=True)  # refuses any non-plain object
    assert state["format"] == checkpoint.FORMAT and state["run_id"] == "run1" and state["cell_key"] == "cellA"
    assert isinstance(state["rng"]["numpy"]["keys"], torch.Tensor) and isinstance(state["rng"]["python"], tuple)
    assert state["step"] == 2 and checkpoint.load(path, run_id="run1", cell_key="cellA")["step"] == 2


def test_the_restored_random_states_draw_the_same_numbers(tmp_path):
    torch.manual_seed(3)
    np.random.seed(4)
    random.seed(5)
    np.random.normal()  # a cached Gaussian in numpy's state too
    saved = checkpoint.rng_state()
    expected = (torch.rand(3), np.random.normal(size=3), [random.random() for _ in range(3)])
    checkpoint.save(tmp_path / "c.pt", {"rng": saved})
    torch.manual_seed(99)
    np.random.seed(99)
    random.seed(99)
    checkpoint.set_rng_state(torch.load(tmp_path / "c.pt", weights_only=True)["rng"])
    assert torch.equal(torch.rand(3), expected[0])
    assert np.array_equal(np.random.normal(size=3), expected[1])
    assert [random.random() for _ in range(3)] == expected[2]


class FakeCuda:
    """torch.cuda as a process with ``n`` visible GPUs sees it (each device has its own RNG state)."""

    def __init__(self, monkeypatch, n: int) -> None:
        self.n, self.current, self.restored = n, 0, []
        self.states = [torch.full((16,), i, dtype=torch.uint8) for i in range(n)]
        for name in ("is_available", "device_count", "get_rng_state", "get_rng_state_all", "set_rng_state",
                     "set_rng_state_all", "current_device"):
            monkeypatch.setattr(torch.cuda, name, getattr(self, name))

    def is_available(self):
        return self.n > 0

    def device_count(self):
        return self.n

    def current_device(self):
        return self.current

    def get_rng_state(self, device="cuda"):
        return self.states[self.current].clone()

    def get_rng_state_all(self):
        return [s.clone() for s in self.states]

    def set_rng_state(self, state, device="cuda"):
        self.restored.append(state.clone())

    def set_rng_state_all(self, states):
        for i, s in enumerate(states):
            self.states[i] = s  # IndexError when the checkpoint saw more devices than this process: issue 21, 1


@pytest.mark.parametrize("visible_on_resume", [1, 0])
def test_a_checkpoint_from_8_gpus_resumes_where_1_or_none_is_visible(tmp_path, monkeypatch, visible_on_resume):
    t, _ = fitted(tmp_path)
    with monkeypatch.context() as m:
        cuda = FakeCuda(m, 8)
        cuda.current = 5  # the run's GPU on the 8-GPU node
        path = t.save_resume()
    state = checkpoint.load(path, run_id="run1", cell_key="cellA")
    assert torch.equal(state["rng"]["cuda"], torch.full((16,), 5, dtype=torch.uint8))  # one device, not 8
    cuda = FakeCuda(monkeypatch, visible_on_resume)
    resumed = trainer(settings(steps=4, val_every=2), ckpt_dir=tmp_path / "run1", cell_key="cellA")
    resumed.load_state(state)
    assert resumed.step == 2
    if visible_on_resume:
        assert len(cuda.restored) == 1 and torch.equal(cuda.restored[0], state["rng"]["cuda"])
    else:
        assert cuda.restored == []


def plant(path: Path, marker: Path, how: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"format": checkpoint.FORMAT, "model": WritesAFile(marker)}
    if how == "torch":
        torch.save(payload, path)
    else:
        path.write_bytes(pickle.dumps(payload))


@pytest.mark.parametrize("how", ["torch", "pickle"])
def test_a_planted_checkpoint_is_refused_without_running_its_code(tmp_path, how):
    marker = tmp_path / "pwned"
    path = tmp_path / "run1" / "last.pt"
    plant(path, marker, how)
    with pytest.raises(BadCheckpoint) as err:
        checkpoint.load(path)
    assert not marker.exists()
    message = str(err.value)
    assert str(path) in message and "\n" not in message and "refused" in message


@pytest.mark.parametrize("content, message", [
    (None, "truncated"),
    ({"format": 1}, "format 1"),
    ({"format": checkpoint.FORMAT, "model": {}}, "missing"),
    ([1, 2], "not a dict"),
])
def test_anything_but_a_whole_checkpoint_is_one_line_naming_the_file(tmp_path, content, message):
    path = tmp_path / "last.pt"
    if content is None:
        _, good = fitted(tmp_path)
        path.write_bytes(good.read_bytes()[:500])
    else:
        torch.save(content, path)
    with pytest.raises(BadCheckpoint) as err:
        checkpoint.load(path)
    text = str(err.value)
    assert str(path) in text and "\n" not in text
    if message != "truncated":
        assert message in text


def test_a_checkpoint_of_another_run_or_cell_is_refused(tmp_path):
    _, path = fitted(tmp_path)
    with pytest.raises(BadCheckpoint, match="run_id 'run1', not 'run2'"):
        checkpoint.load(path, run_id="run2")
    with pytest.raises(BadCheckpoint, match="cell_key 'cellA', not 'cellB'"):
        checkpoint.load(path, run_id="run1", cell_key="cellB")


# -- disk full ---------------------------------------------------------------------------------------------------


def free_space(monkeypatch, free: int) -> None:
    real = shutil.disk_usage
    monkeypatch.setattr(checkpoint.shutil, "disk_usage",
                        lambda p: real(p)._replace(free=free))


def test_too_little_free_space_refuses_before_writing_and_names_what_is_needed(tmp_path, monkeypatch):
    t, path = fitted(tmp_path)
    before = path.read_bytes()
    need = checkpoint.SPACE_FACTOR * checkpoint.nbytes({"format": 2, **t.state()})
    free_space(monkeypatch, need - 1)
    with pytest.raises(CheckpointWriteError) as err:
        t.save_resume()
    text = str(err.value)
    assert str(path) in text and fmt_bytes(need) in text and "\n" not in text
    assert path.read_bytes() == before and sorted(path.parent.iterdir()) == [path.parent / MARKER, path]  # the marker too
    free_space(monkeypatch, need)
    t.save_resume()  # exactly enough is enough


def test_a_run_on_a_full_disk_fails_before_its_first_step(tmp_path, monkeypatch):
    free_space(monkeypatch, 1000)
    t = trainer(settings(steps=2, val_every=2), ckpt_dir=tmp_path / "run1", cell_key="cellA")
    with pytest.raises(CheckpointWriteError, match="not enough disk space"):
        t.fit()
    assert t.step == 0


@pytest.mark.parametrize("failure", [
    OSError(errno.ENOSPC, "No space left on device"),
    OSError(errno.EIO, "Input/output error"),
    RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 448 vs 384"),
])
def test_a_failed_write_removes_its_temporary_file_and_keeps_the_old_checkpoint(tmp_path, monkeypatch, failure):
    t, path = fitted(tmp_path)
    before = path.read_bytes()

    def half_written(obj, f):
        Path(f).write_bytes(b"PK\x03\x04 half")
        raise failure

    monkeypatch.setattr(checkpoint.torch, "save", half_written)
    with pytest.raises(CheckpointWriteError) as err:
        t.save_resume()
    text = str(err.value)
    assert str(path) in text and "needs about" in text and "\n" not in text
    assert path.read_bytes() == before and sorted(path.parent.iterdir()) == [path.parent / MARKER, path]  # the marker too


def test_a_real_small_file_system_fills_up_cleanly(tmp_path, small_fs):
    """On a 1 MB tmpfs (root only): the pre-check and, when bypassed, the write itself fail in one line."""
    t = trainer(settings(steps=2, val_every=2), ckpt_dir=small_fs / "run1", cell_key="cellA")
    t.fit()  # the tiny net fits
    big = {"model": torch.zeros(400_000)}  # 1.6 MB of weights: cannot fit
    with pytest.raises(CheckpointWriteError, match="not enough disk space"):
        checkpoint.save(small_fs / "run2" / "last.pt", big)
    with pytest.MonkeyPatch.context() as m:
        m.setattr(checkpoint, "check_space", lambda *a, **k: None)
        with pytest.raises(CheckpointWriteError, match="could not write the checkpoint"):
            checkpoint.save(small_fs / "run2" / "last.pt", big)
    assert [p.name for p in (small_fs / "run2").iterdir()] == []
    assert checkpoint.load(small_fs / "run1" / "last.pt")["step"] == 2
