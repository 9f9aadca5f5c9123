"""The sweep tests' experiments.yaml (tests/sweep/conftest.py's ``make_config``; module fixtures call it too)."""

from __future__ import annotations

import shutil
from pathlib import Path

import yaml


def config_in(folder: Path, mlflow_template: Path, storage: str | None = None, name: str = "t",
              archs=("baseline", "lstm"), losses=("mse",), populations=("personalized",), sweep: dict | None = None,
              grid_order: bool = False, **sections):
    """Write an experiments.yaml in ``folder`` (MLflow store copied from the template) and load it.

    ``slurm``: the Slurm launcher's own section, written where it belongs (``sweep.launchers.slurm``).

    ``grid_order``: no measured speed settings, so workers claim the cells in the grid's order (the shipped
    measurements order them longest first, and a re-measurement may swap two architectures)."""
    from bronchocli.config import load_config

    if grid_order:
        (folder / "no-speed-settings.json").write_text('{"version": 1, "devices": {}}')
        sections["train"] = {**sections.get("train", {}), "speed_settings": "no-speed-settings.json"}
    launchers = {"slurm": sections.pop("slurm")} if "slurm" in sections else {}
    db = folder / "mlflow.db"
    if not db.exists():
        shutil.copy(mlflow_template, db)
    data = {
        "name": name,
        "runs": {"uri": "sqlite:///mlflow.db", "artifacts": "artifacts"},
        "storage": {"url": storage or "sqlite:///sweep.db"},
        "dataset": {"root": "data/tiny"},
        "grid": {"arch": list(archs), "rot_loss": list(losses), "population": list(populations),
                 "folds": ["p00"], "seed": [0]},
        "sweep": {"max_retries": 1, "heartbeat_s": 0.3, "stale_after_s": 2.0, "poll_s": 0.1,
                  **({"launchers": launchers} if launchers else {}), **(sweep or {})},
        **sections,
    }
    path = folder / "experiments.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_config(path)
