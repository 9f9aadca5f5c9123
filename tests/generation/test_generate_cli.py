"""`bronchopose data generate` and `data preview` end to end on a tiny dataset, and their errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from bronchocli.errors import BronchoError

REPO = Path(__file__).resolve().parents[2]
TINY_FLAGS = ["--set", "dataset.generate.max_frames=3", "--set", "dataset.generate.voxel_mm=1.0",
              "--set", "dataset.generate.lobes=[br, ul]"]


@pytest.fixture
def data_cli():
    """Invoke the `data` command group (exit code, output); a BronchoError counts as exit code 2 with its message."""
    from typer.testing import CliRunner

    from bronchocli.commands.data import app

    def run(*args: str) -> tuple[int, str]:
        # wide, as the other CLI tests: an 80-column console wraps the summary table's long temp paths
        result = CliRunner().invoke(app, list(args), env={"COLUMNS": "200"})
        if isinstance(result.exception, BronchoError):
            return 2, str(result.exception)
        if result.exception is not None and not isinstance(result.exception, SystemExit):
            raise result.exception
        return result.exit_code, result.output

    return run


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    from typer.testing import CliRunner

    from bronchocli.commands.data import app

    out = tmp_path_factory.mktemp("cli") / "tiny"
    args = ["generate", "--config", str(REPO / "experiments.yaml"), "--anatomy", "procedural", "--patients", "1",
            "--image-size", "32", "--trajectories", "1", "--seed", "3", "--workers", "1", "--out", str(out),
            "--no-progress", *TINY_FLAGS]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output + repr(result.exception)
    return out, result.output


def test_generate_writes_the_dataset_and_a_summary(generated):
    out, output = generated
    meta = json.loads((out / "dataset.json").read_text())
    assert meta["patients"] == ["p00"] and meta["lobes"] == ["br", "ul"]
    assert meta["image_size"] == [32, 32] and meta["generator"]["seed"] == 3
    assert meta["counts"]["trajectories"] == 2 and meta["counts"]["frames"] == 6
    assert "6 in 2 trajectories" in output and meta["fingerprint"][:16] in output


def test_generate_again_is_a_no_op(generated, data_cli, repo):
    out, _ = generated
    code, output = data_cli("generate", "--config", str(repo / "experiments.yaml"), "--anatomy", "procedural",
                            "--patients", "1", "--image-size", "32", "--trajectories", "1", "--seed", "3",
                            "--out", str(out), "--no-progress", *TINY_FLAGS)
    assert code == 0 and "already complete" in output
    code, message = data_cli("generate", "--config", str(repo / "experiments.yaml"), "--seed", "4", "--patients", "1",
                             "--image-size", "32", "--trajectories", "1", "--out", str(out), "--no-progress", *TINY_FLAGS)
    assert code == 2 and "different config" in message and "generate.seed" in message


def test_preview_draws_montage_and_positions(generated, data_cli, tmp_path):
    out, _ = generated
    code, output = data_cli("preview", str(out), "--out", str(tmp_path / "m.png"), "--columns", "3", "--pdf")
    assert code == 0, output
    for name in ("m.png", "m-positions.png", "m.pdf", "m-positions.pdf"):
        assert (tmp_path / name).stat().st_size > 1000
    montage = np.asarray(Image.open(tmp_path / "m.png").convert("RGB")).astype(float)
    assert montage.std() > 10  # frames drawn, not a blank canvas


def test_errors_are_one_line(data_cli, tmp_path, repo):
    code, message = data_cli("preview", str(tmp_path))
    assert code == 2 and "dataset.json" in message and "\n" not in message
    code, message = data_cli("generate", "--config", str(repo / "experiments.yaml"), "--anatomy",
                             str(tmp_path / "nowhere.vtu"), "--out", str(tmp_path / "x"), "--no-progress")
    assert code == 2 and "nowhere.vtu" in message
    code, message = data_cli("generate", "--config", str(repo / "experiments.yaml"), "--image-size", "8",
                             "--out", str(tmp_path / "y"), "--no-progress")
    assert code == 2 and "image_size" in message
