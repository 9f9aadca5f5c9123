"""Backbone initialisation end to end: recorded on every run, fetched before any run, one line when it cannot be.

``model.pretrained: imagenet`` against the local weights server of tests/weights_server.py; offline (nothing
listens at the download URL, nothing cached) the train and sweep commands stop with one line and exit 2 before
any MLflow run exists.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from weights_server import serve_weights

from bronchocli.config import load_config
from bronchocli.models import initialisation
from bronchocli.runs.client import client_for
from bronchocli.runs.records import TAG_INIT
from bronchocli.training.run import run_cell

MAIN = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
CELL = ["--arch", "offsetnet", "--rot-loss", "mse", "--population", "personalized"]


def test_every_run_records_its_initialisation(tiny_project, tmp_path, monkeypatch):
    server, _, names, _ = next(serve_weights(tmp_path, monkeypatch))
    try:
        for pretrained, expected in ((None, "random"), ("imagenet", f"imagenet:{names['resnet34']}")):
            cfg = load_config(tiny_project / "experiments.yaml",
                              overrides=[f"model.pretrained={pretrained or 'null'}"])
            cell = cfg.cell(arch="offsetnet", rot_loss="mse", population="personalized")
            result = run_cell(cfg, cell, progress=False)
            assert result.status == "FINISHED", result.failure_reason
            run = client_for(cfg).get_run(result.run_id)
            assert run.data.tags[TAG_INIT] == expected
            assert run.data.params["model.pretrained"] == str(pretrained)
        assert server.hits == [f"models/{names['resnet34']}"]
    finally:
        server.close()


def test_initialisation_is_part_of_the_cell_key(tiny_project):
    keys = {p: load_config(tiny_project / "experiments.yaml", overrides=[f"model.pretrained={p}"]).cell(
        arch="lstm", rot_loss="ce", population="personalized").key for p in ("null", "imagenet", "weights.pth")}
    assert len(set(keys.values())) == 3


def _run(args, cwd, torch_home):
    env = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1", "TORCH_HOME": str(torch_home),
           "BRONCHOPOSE_WEIGHTS_URL": "http://127.0.0.1:9/models/"}  # port 9 (discard): nothing listens
    return subprocess.run([sys.executable, "-c", MAIN, *args], capture_output=True, text=True, cwd=cwd, env=env,
                          timeout=300)


@pytest.mark.parametrize("command", [["train", *CELL, "--quiet"], ["sweep", "--workers", "1"]])
def test_offline_without_cached_weights_is_one_line_exit_2_and_no_run(tiny_project, tmp_path, command):
    proc = _run([*command, "--set", "model.pretrained=imagenet", "--set", "runs.experiment=offline-init"],
                tiny_project, tmp_path / "torch-home")
    assert proc.returncode == 2, proc.stdout + proc.stderr
    err = proc.stderr.strip()
    expected = f"place torchvision's efficientnet_b0_rwightman-7f5810bc.pth in {tmp_path / 'torch-home'}"
    if command[0] == "train":
        expected = expected.replace("efficientnet_b0_rwightman-7f5810bc", "resnet34-b627a593")
    assert expected in err and "Traceback" not in err and len(err.splitlines()) == 1, err
    cfg = load_config(tiny_project / "experiments.yaml", overrides=["runs.experiment=offline-init"])
    client = client_for(cfg)
    exp = client.get_experiment_by_name("offline-init")
    assert exp is None or not client.search_runs([exp.experiment_id])


def test_paper_profile_starts_from_imagenet_and_the_cpu_default_from_lite0s_packaged_imagenet_weights(repo):
    paper = load_config(repo / "experiments.yaml", profile="paper")
    assert paper.paths.pretrained == "imagenet" and paper.model.backbone == "efficientnet_b0"
    assert paper.train.pairs_per_step == 512 * paper.data.window  # the authors' 512 windows per step
    assert (paper.train.lr, paper.train.schedule, paper.train.warmup) == (1e-4, "constant", 0.0)
    assert (paper.train.patience, paper.train.min_delta) == (25, 0.005)
    default = load_config(repo / "experiments.yaml")
    # offline-reproducible: Lite0's ImageNet file comes with an installed package, nothing is downloaded
    assert (default.paths.pretrained, default.model.backbone) == ("imagenet", "efficientnet_lite0")
    assert initialisation(default.paths.pretrained, list(default.grid.arch), default.model.backbone) == \
        dict.fromkeys(default.grid.arch, "imagenet:efficientnet-lite0-57934424.pth")
    for profile in ("cpu-study", "table6", "learning-cost"):  # the measured random-initialisation studies, pinned
        cfg = load_config(repo / "experiments.yaml", profile=profile)
        assert (cfg.paths.pretrained, cfg.model.backbone, cfg.model.frozen_stages) == (None, "efficientnet_b0", 0)
