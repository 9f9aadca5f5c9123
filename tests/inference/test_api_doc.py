"""docs/api.md's example runs as written, and bronchocli.api gives what the run logged."""

from __future__ import annotations

import re

import numpy as np
import pytest

from bronchocli import api, geometry
from bronchocli.inference.mlflow_model import FrameSizeWarning
from bronchocli.training.evaluate import POSE_COLS

DOC = "docs/api.md"


def example_block(repo) -> str:
    text = (repo / DOC).read_text()
    match = re.search(r"<!-- executed by tests/inference/test_api_doc.py -->\n```python\n(.*?)```", text, re.S)
    assert match, f"{DOC}: the tested example block is missing"
    return match.group(1)


def test_the_documented_example_runs_against_a_tiny_run(repo, tiny_run, capsys):
    key = tiny_run.test_keys()[0]
    namespace = {"RUN_ID": tiny_run.run_id, "MLFLOW_URI": tiny_run.cfg.paths.mlflow_uri,
                 "TRAJECTORY": str(tiny_run.dataset.joinpath(*key.split("/")))}
    exec(compile(example_block(repo), DOC, "exec"), namespace)
    assert "per-pair position error" in capsys.readouterr().out
    row = tiny_run.errors.iloc[0]
    assert namespace["errors"]["model.pair.pos_l2"] == pytest.approx(row["model.pair.pos_l2"], rel=5e-3)
    assert namespace["errors"]["train_mean.acc.rot_l2"] == pytest.approx(row["train_mean.acc.rot_l2"], rel=1e-9)


def test_api_predicts_the_logged_predictions_and_chains_like_geometry(tiny_run):
    key = tiny_run.test_keys()[1]
    path = tiny_run.dataset.joinpath(*key.split("/"))
    model = api.load_model(tiny_run.run_id, mlflow_uri=tiny_run.cfg.paths.mlflow_uri)
    relative = api.predict(model, api.read_frames(path))
    patient, lobe, traj = key.split("/")
    p = tiny_run.predictions
    rows = p[(p.patient == patient) & (p.lobe == lobe) & (p.trajectory == traj)].sort_values("frame")
    np.testing.assert_allclose(relative, rows[[f"pred_rel_{c}" for c in POSE_COLS]].to_numpy()[1:], rtol=5e-3,
                               atol=1e-2)
    start = np.array([1.0, 2, 3, 170, 10, -170])
    np.testing.assert_allclose(api.chain(model, relative, start), geometry.accumulate(start, relative, "world"))
    with pytest.raises(ValueError, match="need one more"):
        api.score(model, relative, api.read_poses(path)[:-1])


def test_api_resizes_frames_of_another_size_with_a_warning(tiny_run):
    model = api.load_model(tiny_run.run_id, mlflow_uri=tiny_run.cfg.paths.mlflow_uri)
    frames = np.zeros((3, 40, 40, 3), np.uint8)
    with pytest.warns(FrameSizeWarning, match="40x40"):
        assert api.predict(model, frames).shape == (2, 6)
