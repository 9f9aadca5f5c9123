"""Every FINISHED run logs an MLflow Model that MLflow itself loads and runs on the CPU."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch
from inference.pose_tolerance import assert_close, close
from PIL import Image

from bronchocli.inference.loading import resolve
from bronchocli.inference.mlflow_model import FrameSizeWarning, ModelInputError, check_frames
from bronchocli.runs.client import client_for
from bronchocli.training.evaluate import POSE_COLS


def frames_of(run, key: str) -> np.ndarray:
    patient, lobe, traj = key.split("/")
    names = sorted((run.dataset / patient / lobe).glob(f"t{int(traj):03d}_f*.png"))
    return np.stack([np.asarray(Image.open(p).convert("RGB")) for p in names])


def logged_relative(run, key: str) -> np.ndarray:
    patient, lobe, traj = key.split("/")
    p = run.predictions
    rows = p[(p.patient == patient) & (p.lobe == lobe) & (p.trajectory == traj)].sort_values("frame")
    return rows[[f"pred_rel_{c}" for c in POSE_COLS]].to_numpy()[1:]


@pytest.fixture(scope="module")
def pyfunc(tiny_run):
    mlflow.set_tracking_uri(tiny_run.cfg.paths.mlflow_uri)
    try:
        yield mlflow.pyfunc.load_model(f"runs:/{tiny_run.run_id}/model")
    finally:
        mlflow.set_tracking_uri(None)


def test_pyfunc_predicts_the_runs_logged_predictions_of_every_test_trajectory(tiny_run, pyfunc):
    for key in tiny_run.test_keys():
        frames = frames_of(tiny_run, key)
        out = pyfunc.predict(frames)
        assert out.shape == (len(frames) - 1, 6) and out.dtype == np.float64
        assert_close(out, logged_relative(tiny_run, key))


def test_a_temporal_model_predicts_in_the_chunks_evaluation_used(tiny_temporal_run):
    """conv3d pads in time at each chunk's borders: the model must chunk as evaluation did (data.window pairs)."""
    run = tiny_temporal_run
    model = mlflow.pyfunc.load_model(mlflow.artifacts.download_artifacts(
        resolve(client_for(run.cfg), run.run_id).location))
    assert model.get_raw_model().chunk == 3
    for key in run.test_keys():
        frames = frames_of(run, key)
        assert_close(model.predict(frames), logged_relative(run, key))
    whole = model.get_raw_model().net(torch.from_numpy(frames.transpose(0, 3, 1, 2)).unsqueeze(0))[0][0]
    assert not close(whole.detach().double().numpy(), logged_relative(run, key))  # chunks matter


def test_the_model_has_a_signature_an_input_example_fp16_weights_and_its_spec(tiny_run, pyfunc):
    sig = pyfunc.metadata.signature
    spec_in, spec_out = sig.inputs.inputs[0], sig.outputs.inputs[0]
    assert spec_in.type == np.dtype(np.uint8) and spec_in.shape == (-1, -1, -1, 3)
    assert spec_out.type == np.dtype(np.float64) and spec_out.shape == (-1, 6)
    client = client_for(tiny_run.cfg)
    local = Path(mlflow.artifacts.download_artifacts(resolve(client, tiny_run.run_id).location))
    example = json.loads((local / "input_example.json").read_text())
    assert np.asarray(example).shape == (2, 32, 32, 3)  # the first two frames of a test trajectory
    weights = torch.load(local / "data" / "bronchopose" / "weights.pt", weights_only=True)
    floats = {v.dtype for v in weights["state_dict"].values() if v.is_floating_point()}
    assert floats == {torch.float16}
    spec = json.loads((local / "data" / "bronchopose" / "spec.json").read_text())
    assert (spec["arch"], spec["image_size"], spec["pose_frame"], spec["run_id"]) == ("baseline", 32, "world",
                                                                                      tiny_run.run_id)
    size = sum(p.stat().st_size for p in local.rglob("*") if p.is_file())
    n_params = sum(v.numel() for v in weights["state_dict"].values())
    assert size < 2 * n_params + 2_000_000  # fp16: two bytes a value, plus the small files
    # The model is an MLflow 3 logged model of the run: registrable from runs:/<id>/model.
    models = client.search_logged_models(experiment_ids=[client.get_run(tiny_run.run_id).info.experiment_id])
    assert [m.source_run_id for m in models if m.name == "model"].count(tiny_run.run_id) == 1
    # Named "model" (runs:/<id>/model finds it by name), it says its cell in its tags and description (issue 36.5)
    ours = next(m for m in models if m.source_run_id == tiny_run.run_id)
    run = client.get_run(tiny_run.run_id)
    label = spec["cell"]
    assert ours.tags["cell"] == label and ours.tags["arch"] == "baseline" and ours.tags["cell_key"] == spec["cell_key"]
    assert ours.tags["mlflow.note.content"] == run.data.tags["mlflow.note.content"] and label in ours.tags[
        "mlflow.note.content"]
    assert {"eval.ctf_angle", "eval.rpe_gap"} <= set(ours.params)  # the run's params, the evaluation's constants too


def test_frames_of_another_size_are_resized_with_one_warning(tiny_run, pyfunc):
    key = tiny_run.test_keys()[0]
    frames = frames_of(tiny_run, key)
    big = np.stack([np.asarray(Image.fromarray(f).resize((64, 64), Image.Resampling.BILINEAR)) for f in frames])
    with pytest.warns(UserWarning, match="64x64 pixels, the network takes 32x32") as caught:
        out = pyfunc.predict(big)
    assert {w.category.__name__ for w in caught} == {FrameSizeWarning.__name__}  # the model's own copy of it
    assert out.shape == (len(frames) - 1, 6) and np.isfinite(out).all()


@pytest.mark.parametrize("bad, match", [
    (np.zeros((1, 32, 32, 3), np.uint8), "at least 2"),
    (np.zeros((4, 32, 32), np.uint8), r"does not match expected shape \(-1, -1, -1, 3\)"),  # MLflow's schema check
    (np.zeros((4, 32, 32, 3), np.float32), r"uint8"),
])
def test_bad_frames_are_one_clear_error(pyfunc, bad, match):
    with pytest.raises((ValueError, mlflow.exceptions.MlflowException), match=match):  # the bundle's InputError
        pyfunc.predict(bad)
    if "expected shape" not in match:  # the project's own check: the same words, its one-line error kind
        with pytest.raises(ModelInputError, match=match):
            check_frames(bad)


def test_the_docs_registration_recipe_registers_a_loadable_version(tiny_run, pyfunc):
    """docs/api.md: mlflow.register_model("runs:/<id>/model", name), then models:/name/version and @alias load."""
    version = mlflow.register_model(f"runs:/{tiny_run.run_id}/model", "recipe-pose")
    mlflow.MlflowClient().set_registered_model_alias("recipe-pose", "champion", version.version)
    frames = frames_of(tiny_run, tiny_run.test_keys()[0])
    expected = pyfunc.predict(frames)
    for uri in (f"models:/recipe-pose/{version.version}", "models:/recipe-pose@champion"):
        np.testing.assert_array_equal(mlflow.pyfunc.load_model(uri).predict(frames), expected)


def test_loading_and_predicting_needs_neither_vtk_nor_a_gpu(tiny_run, tmp_path):
    """A fresh process with VTK made unimportable and CUDA hidden loads runs:/<id>/model and predicts."""
    frames = frames_of(tiny_run, tiny_run.test_keys()[0])
    np.save(tmp_path / "frames.npy", frames)
    code = f"""
import sys
for name in ("vtk", "vtkmodules", "skimage"):
    sys.modules[name] = None  # any import of them fails
import mlflow, numpy as np, torch
torch.set_num_threads(1)  # as the run evaluated (train.threads: 1): the same reduction order
assert not torch.cuda.is_available()
mlflow.set_tracking_uri({tiny_run.cfg.paths.mlflow_uri!r})
out = mlflow.pyfunc.load_model("runs:/{tiny_run.run_id}/model").predict(np.load({str(tmp_path / "frames.npy")!r}))
np.save({str(tmp_path / "out.npy")!r}, out)
assert not any(m.startswith(("vtk", "bronchocli.render", "bronchocli.generation", "bronchocli.anatomy"))
               for m in sys.modules if sys.modules[m] is not None)
"""
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert_close(np.load(tmp_path / "out.npy"), logged_relative(tiny_run, tiny_run.test_keys()[0]))
