"""Proof that the pipeline learns from images: on rendered frames a model beats the image-blind training-mean
predictor by a clear margin, and its predictions vary with the input.

This is the default main job's setting at one seed (OffsetNet, 64² frames of 3 procedural patients, camera-frame
labels, 320 steps of 20 pairs): about 5 minutes on 2 cores, so it is ``slow``. The CI suite checks the same
mechanics in seconds on synthetic frames (tests/training/test_loop.py)."""

from __future__ import annotations

import textwrap

import pytest

from bronchocli.config import load_config
from bronchocli.generation import ensure_dataset
from bronchocli.training.run import run_cell

CONFIG = """\
    name: learn
    dataset:
      root: data
      generate: {patients: 3, lobes: [ur, br, ul, bl], trajectories: 6, image_size: 64, step_mm: [2.0, 4.0],
                 max_frames: 24, workers: 2}
    splits: {train: 4, val: 1, test: 1}
    train: {steps: 320, batch_size: 20, lr: 1.0e-3, val_every: 80, max_val_pairs: 160}
    runs: {model_artifact: none}
"""


@pytest.mark.slow
def test_offsetnet_beats_the_training_mean_and_looks_at_its_input(tmp_path):
    path = tmp_path / "experiments.yaml"
    path.write_text(textwrap.dedent(CONFIG))
    cfg = load_config(path)
    ensure_dataset(cfg, progress=False)
    result = run_cell(cfg, cfg.cell(arch="offsetnet", rot_loss="mse", population="personalized",
                                    pose_frame="camera"), progress=False)
    assert result.status == "FINISHED", result.failure_reason
    m = result.metrics
    assert m["train_mean.pair.pos_l2.mean"] < 0.5 * m["zero_motion.pair.pos_l2.mean"]  # forward on average
    assert m["pair.pos_l2.mean"] < 0.9 * m["train_mean.pair.pos_l2.mean"], m
    assert m["pred.std_ratio.pos"] > 0.2, m  # the predictions follow the images, not a constant
