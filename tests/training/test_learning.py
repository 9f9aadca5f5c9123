"""Proof that the pipeline learns from images: on rendered frames a model beats the image-blind training-mean
predictor by a clear margin, and its predictions vary with the input."""

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
      generate: {patients: 1, lobes: [ur, br, ul, bl], trajectories: 6, image_size: 64, step_mm: [2.0, 4.0],
                 max_frames: 24, workers: 1}
    splits: {train: 4, val: 1, test: 1}
    train: {steps: 400, batch_size: 16, lr: 1.0e-3, val_every: 100, threads: 2}
    tracking: {model_artifact: none}
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
