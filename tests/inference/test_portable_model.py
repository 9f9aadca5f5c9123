"""A logged model loads and predicts where only torch and MLflow are installed: no bronchocli.

The venv holds ``torch`` (pinned to this torch's release: the CPU wheel this
machine's pip finds, never a CUDA download) and ``mlflow`` (pinned to this
one) and nothing else; MLflow loads the tiny run's model by its ``runs:/`` URI
from the run's own store and predicts on the model's input example. The
prediction equals the project's own (``api.load_model``: the same fp16
weights, fp32 compute). One venv per test session: pip's cache makes it
cheaper after the first.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch
from inference.pose_tolerance import assert_close
from mlflow.models import Model

from bronchocli import api
from bronchocli.inference.loading import resolve
from bronchocli.runs.client import client_for
from bronchocli.training import bundle

SCRIPT = """\
import importlib.util, json, sys
import numpy as np, mlflow, torch
from mlflow.models import Model

torch.set_num_threads(1)  # as the test process predicts (tests/inference/conftest.py): the same summation order

assert importlib.util.find_spec("bronchocli") is None, "bronchocli must not be importable here"
uri, run_id, out = sys.argv[1:4]
mlflow.set_tracking_uri(uri)
local = mlflow.artifacts.download_artifacts(f"runs:/{run_id}/model")
model = mlflow.pyfunc.load_model(f"runs:/{run_id}/model")
example = Model.load(local).load_input_example(local)
pred = model.predict(example)
np.save(out, pred)
ours = sorted(m for m in sys.modules if m.split(".")[0] == "bronchocli")
print(json.dumps({"loader": model.loader_module, "bronchocli": ours, "shape": list(pred.shape)}))
"""


def _env() -> dict[str, str]:
    """This process's environment without what would put bronchocli (or this venv) on the venv's path."""
    drop = {"PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSTARTUP", "PYTHONUSERBASE"}
    return {k: v for k, v in os.environ.items() if k not in drop} | {"PYTHONNOUSERSITE": "1"}


@pytest.fixture(scope="session")
def bare_python(tmp_path_factory) -> Path:
    """The python of a fresh venv holding only torch and mlflow (and what they depend on)."""
    root = tmp_path_factory.mktemp("bare-venv")
    venv.EnvBuilder(with_pip=True, clear=True).create(root)
    python = root / "bin" / "python"
    pins = [f"torch=={torch.__version__.split('+')[0]}", f"mlflow=={mlflow.__version__}"]
    # --no-compile: byte-compiling every module of torch, MLflow and their dependencies is most of pip's CPU time;
    # Python compiles the few this test imports.
    done = subprocess.run([str(python), "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
                           "--no-compile", *pins], capture_output=True, text=True, env=_env(), cwd=root)
    assert done.returncode == 0, f"pip install {' '.join(pins)} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return python


# slow (issue 46, measured): building the bare venv (pip install torch + mlflow) is 264 s of setup and 140 s of
# call on the shared 2-core machine, the costliest non-Slurm test of CI. What it checks stays in CI:
# test_mlflow_loads_the_model_where_bronchocli_cannot_be_imported loads and predicts with bronchocli unimportable
# (the same script, the same comparison with api.predict), and
# test_the_model_carries_the_projects_own_model_code_and_lists_what_it_imports checks the model's requirements
# are exactly mlflow, numpy, pillow and torch. Only the install from those requirements alone is left to
# `pytest -m slow`.
@pytest.mark.slow
def test_a_logged_model_loads_and_predicts_with_only_torch_and_mlflow(tiny_run, bare_python, tmp_path):
    out = tmp_path / "pred.npy"
    (tmp_path / "predict.py").write_text(SCRIPT)
    done = subprocess.run([str(bare_python), "predict.py", tiny_run.cfg.paths.mlflow_uri, tiny_run.run_id, str(out)],
                          capture_output=True, text=True, env=_env(), cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-4000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["bronchocli"] == [] and report["loader"].startswith(bundle.PREFIX)
    bare = np.load(out)

    # The project's own loader, on the same artifact and the same input example.
    local = Path(mlflow.artifacts.download_artifacts(resolve(client_for(tiny_run.cfg), tiny_run.run_id).location))
    example = Model.load(str(local)).load_input_example(str(local))
    ours = api.predict(api.load_model(tiny_run.run_id, mlflow_uri=tiny_run.cfg.paths.mlflow_uri), example)
    assert bare.shape == ours.shape == (len(example) - 1, 6) and bare.dtype == np.float64
    assert_close(bare, ours)  # same weights, fp32: kernels' summation order only


def test_mlflow_loads_the_model_where_bronchocli_cannot_be_imported(tiny_run, tmp_path):
    """The fast check of the same (no venv to build): this Python, with every import of bronchocli failing."""
    out = tmp_path / "pred.npy"
    (tmp_path / "predict.py").write_text('import sys\nsys.modules["bronchocli"] = None\n' + SCRIPT.replace(
        'assert importlib.util.find_spec("bronchocli") is None', "assert True"))
    done = subprocess.run([sys.executable, "predict.py", tiny_run.cfg.paths.mlflow_uri, tiny_run.run_id, str(out)],
                          capture_output=True, text=True, env=_env(), cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-4000:]
    assert json.loads(done.stdout.strip().splitlines()[-1])["bronchocli"] == ["bronchocli"]  # the blocked entry
    local = Path(mlflow.artifacts.download_artifacts(resolve(client_for(tiny_run.cfg), tiny_run.run_id).location))
    example = Model.load(str(local)).load_input_example(str(local))
    ours = api.predict(api.load_model(tiny_run.run_id, mlflow_uri=tiny_run.cfg.paths.mlflow_uri), example)
    assert_close(np.load(out), ours)


def test_the_model_carries_the_projects_own_model_code_and_lists_what_it_imports(tiny_run):
    """One copy of each model: the bundle's files are the project's source files, byte for byte."""
    local = Path(mlflow.artifacts.download_artifacts(resolve(client_for(tiny_run.cfg), tiny_run.run_id).location))
    pyfunc = Model.load(str(local)).flavors["python_function"]
    expected = bundle.bundle_for("baseline")
    assert pyfunc["loader_module"] == expected.loader_module
    shipped = local / pyfunc["code"] / expected.package
    assert sorted(p.name for p in shipped.glob("*.py")) == sorted(["__init__.py", *(f.name for f in expected.files)])
    for source in expected.files:
        assert (shipped / source.name).read_bytes() == source.read_bytes(), source.name
    requirements = (local / "requirements.txt").read_text().split()
    assert sorted(r.split("==")[0] for r in requirements) == ["mlflow", "numpy", "pillow", "torch"]
    spec = json.loads((local / "data" / "bronchopose" / "spec.json").read_text())
    assert spec["model_class"] == ".baseline:BaselineNet"


def test_the_logged_model_has_the_runs_params_metrics_and_test_dataset(tiny_run):
    client = client_for(tiny_run.cfg)
    run = client.get_run(tiny_run.run_id)
    model = client.get_logged_model(resolve(client, tiny_run.run_id).model_id)
    assert model.params == run.data.params and model.params["arch"] == "baseline"
    metrics = {m.key: m for m in model.metrics}
    # The end-of-run metrics (test errors, references, budget) are the model's too; the validation curves are not.
    assert {"pair.pos_l2.mean", "acc.pos_l2.mean", "train.steps", "n_params"} <= set(metrics)
    assert not {"train_loss", "val_loss"} & set(metrics)
    assert all(m.value == pytest.approx(run.data.metrics[k]) for k, m in metrics.items())
    test_metric = metrics["pair.pos_l2.mean"]
    assert test_metric.value == pytest.approx(run.data.metrics["pair.pos_l2.mean"])
    inputs = {d.dataset.name: d.dataset.digest for d in run.inputs.dataset_inputs}
    assert (test_metric.dataset_name, test_metric.dataset_digest) in inputs.items()
    assert test_metric.dataset_name.endswith(":test")


def test_a_model_logged_before_it_carried_its_code_still_loads_through_the_project(tiny_run, tmp_path):
    """Old runs name bronchocli.inference.mlflow_model as their loader and have no code/: the project reads
    their data/ folder as before, and so does MLflow where bronchocli is installed."""
    from bronchocli.inference.mlflow_model import LEGACY_LOADER

    local = Path(mlflow.artifacts.download_artifacts(resolve(client_for(tiny_run.cfg), tiny_run.run_id).location,
                                                     dst_path=str(tmp_path)))
    meta = Model.load(str(local))
    pyfunc = meta.flavors["python_function"]
    shutil.rmtree(local / pyfunc.pop("code"))
    pyfunc["loader_module"] = LEGACY_LOADER
    meta.save(str(local / "MLmodel"))
    spec_path = local / "data" / "bronchopose" / "spec.json"
    spec = json.loads(spec_path.read_text())
    del spec["model_class"]
    spec_path.write_text(json.dumps(spec))
    frames = Model.load(str(local)).load_input_example(str(local))
    ours = api.predict(api.load_model(str(local)), frames)
    legacy = mlflow.pyfunc.load_model(str(local))
    assert legacy.loader_module == LEGACY_LOADER
    np.testing.assert_allclose(legacy.predict(frames), ours, rtol=0, atol=0)
    assert sys.modules[LEGACY_LOADER]  # MLflow imported the project's legacy loader


def test_a_folder_whose_loader_is_not_ours_is_refused_in_one_line(tiny_run, tmp_path):
    from bronchocli.errors import BronchoError

    local = Path(mlflow.artifacts.download_artifacts(resolve(client_for(tiny_run.cfg), tiny_run.run_id).location,
                                                     dst_path=str(tmp_path)))
    meta = Model.load(str(local))
    meta.flavors["python_function"]["loader_module"] = "someone.else"
    meta.save(str(local / "MLmodel"))
    with pytest.raises(BronchoError, match=r"not a bronchopose model \(its pyfunc loader is 'someone.else'"):
        api.load_model(str(local))
