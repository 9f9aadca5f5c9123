"""`data generate` on a disk that fills while it renders (a real tmpfs), and an interruption before the first frame:
one line that says what is true, exit 2, nothing lost, and the same command resumes (issues 49 and 50)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from mounts import tmpfs

from bronchocli.errors import Interrupted, WriteFailed
from bronchocli.generation import writer
from bronchocli.generation.pipeline import frames_on_disk, generate_dataset

TINY = {
    "dataset.generate.patients": 1,
    "dataset.generate.trajectories": 2,
    "dataset.generate.max_frames": 6,
    "dataset.generate.image_size": 32,
    "dataset.generate.voxel_mm": 1.0,
    "dataset.generate.step_mm": [1.0, 3.0],
    "dataset.generate.seed": 7,
    "dataset.generate.lobes": ["br"],
}


def tiny_config(root: Path):
    from bronchocli.config import Config

    return Config(name="tiny").with_values({**TINY, "dataset.root": str(root)})


def generate_cli(root: Path, cwd: Path) -> subprocess.CompletedProcess:
    """`bronchopose data generate` of the same dataset in a real process (no experiments.yaml: the defaults)."""
    sets = [a for k, v in TINY.items() for a in ("--set", f"{k}={json.dumps(v)}")]
    return subprocess.run([sys.executable, "-m", "bronchocli.cli", "data", "generate", "--out", str(root),
                           "--workers", "1", "--no-progress", *sets], cwd=cwd, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])})


def test_a_disk_that_fills_while_rendering_keeps_the_frames_and_resumes(tmp_path):
    reference = generate_dataset(tiny_config(tmp_path / "ref"), workers=1, progress=False)
    with tmpfs(tmp_path / "disk", "8m") as disk:
        root, filler = disk / "ds", disk / "filler"

        def fill(done: int, total: int) -> None:  # another program fills the disk after the third frame
            if done == 3 and not filler.exists():
                filler.write_bytes(b"\1" * (shutil.disk_usage(disk).free - writer.FRAME_MARGIN // 2))

        with pytest.raises(WriteFailed) as err:
            generate_dataset(tiny_config(root), workers=1, progress=False, callback=fill)
        line = str(err.value)
        assert "\n" not in line and line.startswith(f"data generate: {root}: disk full (")
        assert f" free on the file system mounted at {disk}, about " in line  # the full file system, named
        assert "more needed for the 9 frames left" in line
        assert "the 3 frames rendered so far are kept" in line and "run the same command again to resume" in line
        assert frames_on_disk(root)[0] == 3 and not [p for p in root.rglob("*.tmp")]  # nothing half-written

        again = generate_cli(root, tmp_path)  # the same command while the disk is still full: the same one line
        assert again.returncode == 2, again.stderr
        assert again.stderr.startswith(f"error: data generate: {root}: disk full (")
        assert "the 3 frames rendered so far are kept" in again.stderr
        assert len(again.stderr.strip().splitlines()) == 1 and "Traceback" not in again.stderr
        assert frames_on_disk(root)[0] == 3

        filler.unlink()  # space freed: the same command finishes the dataset, byte for byte the reference
        done = generate_cli(root, tmp_path)
        assert done.returncode == 0, done.stderr
        meta = json.loads((root / "dataset.json").read_text())
        assert meta["fingerprint"] == json.loads((reference / "dataset.json").read_text())["fingerprint"]
        assert not (root / ".work").exists()


def test_a_disk_too_small_for_the_surfaces_is_one_line_and_leaves_no_stub(tmp_path):
    with tmpfs(tmp_path / "disk", "600k") as disk:  # the procedural airway's surface alone needs more
        done = generate_cli(disk / "ds", tmp_path)
        assert done.returncode == 2, done.stderr
        assert done.stderr.startswith(f"error: data generate: {disk / 'ds'}: disk full (")
        assert "no frame was rendered yet" in done.stderr and "Traceback" not in done.stderr
        assert len(done.stderr.strip().splitlines()) == 1  # never VTK's segfault or heap corruption (exit 139/134)
        assert not (disk / "ds").exists()


def test_an_interrupt_before_the_first_frame_names_no_folder_that_does_not_exist(tmp_path, monkeypatch):
    from rich.console import Console

    from bronchocli.generation import entry, pipeline

    def ctrl_c(*args, **kwargs):  # Ctrl-C while the trajectories are planned: before any frame exists
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "plan_lobe", ctrl_c)
    root = tmp_path / "ds-INT-9"
    with pytest.raises(Interrupted) as err:
        entry.generate(tiny_config(root), root, workers=1, progress=False, console=Console())
    assert str(err.value) == (f"data generate stopped before the first frame; nothing was written ({root} was not "
                              "created): run the same command again to start")
    assert not root.exists()
