"""One tiny real training run with its MLflow Model, shared by the inference tests (no VTK)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import pytest
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli.config import Config, load_config
from bronchocli.runs.client import client_for
from bronchocli.training.run import run_cell


@dataclass(frozen=True)
class TinyRun:
    root: Path  # project folder (experiments.yaml, tiny/ dataset, runs/)
    cfg: Config
    run_id: str
    predictions: pd.DataFrame  # the run's logged predictions.csv
    errors: pd.DataFrame  # the run's logged trajectory_errors.csv

    @property
    def dataset(self) -> Path:
        return self.root / "tiny"

    def test_keys(self) -> list[str]:
        t = self.errors
        return [f"{p}/{lb}/{tr}" for p, lb, tr in zip(t.patient, t.lobe, t.trajectory)]


def train_tiny(root: Path, arch: str = "baseline") -> TinyRun:
    if not (root / "tiny").exists():
        write_tiny_dataset(root / "tiny", patients=2, lobes=("ur", "bl"), trajectories=3, frames=8, image_size=32)
        write_config(root, model_artifact="fp16")
    cfg = load_config(root / "experiments.yaml")
    result = run_cell(cfg, cfg.cell(arch=arch, rot_loss="mse", population="personalized", seed=0), progress=False)
    assert result.status == "FINISHED", result.failure_reason
    client = client_for(cfg)
    dtypes = {"patient": str, "lobe": str, "trajectory": str}
    return TinyRun(root, cfg, result.run_id,
                   pd.read_csv(client.download_artifacts(result.run_id, "predictions.csv"), dtype=dtypes),
                   pd.read_csv(client.download_artifacts(result.run_id, "trajectory_errors.csv"), dtype=dtypes))


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> TinyRun:
    """A FINISHED baseline run (4 steps on a 32-px dataset) that logged its fp16 MLflow Model."""
    return train_tiny(tmp_path_factory.mktemp("inference-project"))


@pytest.fixture(scope="session")
def tiny_temporal_run(tmp_path_factory) -> TinyRun:
    """A FINISHED conv3d run: predicted in chunks of data.window pairs, whose borders change its output."""
    return train_tiny(tmp_path_factory.mktemp("inference-temporal"), arch="conv3d")


@pytest.fixture(autouse=True)
def _threads_of_the_evaluation(one_thread):
    """Predict with the thread count the tiny runs evaluated with (``train.threads: 1``).

    Their logged predictions come from one-thread kernels; with two threads the convolutions sum in another
    order. These untrained 4-step networks have features and outputs of ~1e3, so that moves an output by
    ~2e-4 of its component's scale, and an element near zero then misses an elementwise tolerance: the CI
    failure of test_a_temporal_model_predicts_in_the_chunks_evaluation_used (0.036 on a component reaching
    ~130, in a session where an earlier test had left torch at two threads). Not fp16 (evaluation scored the
    same rounded weights), not the chunks (the same), not BatchNorm (eval-mode statistics, the same).
    """
    yield
