"""Training on world-frame labels near gimbal lock says so, naming the trajectory; camera-frame training does not."""

from __future__ import annotations

import logging

import pandas as pd
import pytest
from tinydata import turning_angles, write_tiny_dataset

from bronchocli.config import load_config
from bronchocli.data import reader
from bronchocli.training.prepare import prepare


@pytest.mark.parametrize("frame", ["world", "camera"])
def test_world_frame_training_warns_about_gimbal_lock(tmp_path, monkeypatch, caplog, frame):
    monkeypatch.setattr(reader, "_warned", set())
    root = write_tiny_dataset(tmp_path / "ds", patients=1, lobes=("ur",), trajectories=6, frames=12, image_size=16)
    table = pd.read_csv(root / "p00.csv")
    first = table["trajectory"].astype(str) == str(table["trajectory"].iat[0])
    table.loc[first, ["Rx", "Ry", "Rz"]] = turning_angles(-88.9, int(first.sum()))
    table.to_csv(root / "p00.csv", index=False)
    config = tmp_path / "exp.yaml"
    config.write_text(f"name: t\ndataset: {{root: {root}}}\nsplits: {{train: 4, val: 1, test: 1}}\n"
                      f"runs: {{uri: sqlite:///{tmp_path / 'm.db'}}}\ndata: {{window: 2}}\n"
                      "train: {batch_size: 4}\n")
    cfg = load_config(config)
    cell = cfg.cell(arch="baseline", rot_loss="mse", population="personalized", seed=0, pose_frame=frame)
    with caplog.at_level(logging.WARNING):
        prepare(cfg, cell, progress=False)
    found = [r.getMessage() for r in caplog.records if "gimbal lock" in r.getMessage()]
    if frame == "camera":
        assert not found
    else:
        assert len(found) == 1 and f"p00/ur/{table['trajectory'].iat[0]} frames " in found[0]
