"""A cell runner that trains for real and, while ``$SWEEP_FAKE_DIR/fill`` exists, fills the disk of the run's
stores just before the run logs its outcome (the model): the disk is full for MLflow's store, the artifacts and
the claims database alike, as when another job fills a shared disk (issue 37.3). ``--runner
disk_fakes:fill_then_train``; the filler is ``<folder of runs.checkpoints>/filler``."""

from __future__ import annotations

import os
from pathlib import Path

from bronchocli import urls
from bronchocli.training import artifacts
from bronchocli.training.run import run_cell


def fill(folder: Path) -> None:
    """Write zeros to ``folder/filler`` until the file system refuses: nothing is left free there."""
    for size in (1 << 20, 4096, 1):
        try:
            with open(folder / "filler", "ab") as f:
                while True:
                    f.write(b"\0" * size)
                    f.flush()
        except OSError:
            continue


def fill_then_train(cfg, cell, **kw):
    if (Path(os.environ["SWEEP_FAKE_DIR"]) / "fill").exists():
        log_outcome = artifacts.log_outcome

        def full_disk_first(client, run_id, cfg_, *args, **kwargs):
            fill(cfg_.paths.checkpoints.parent)
            return log_outcome(client, run_id, cfg_, *args, **kwargs)

        artifacts.log_outcome = full_disk_first
    return run_cell(cfg, cell, **kw)


def fill_stores_then_train(cfg, cell, **kw):
    """As ``fill_then_train``, the filler in the folder of the MLflow store (``<runs.uri's folder>/filler``)."""
    if (Path(os.environ["SWEEP_FAKE_DIR"]) / "fill").exists():
        log_outcome = artifacts.log_outcome

        def full_disk_first(client, run_id, cfg_, *args, **kwargs):
            fill(urls.sqlite_file(cfg_.paths.mlflow_uri).parent)
            return log_outcome(client, run_id, cfg_, *args, **kwargs)

        artifacts.log_outcome = full_disk_first
    return run_cell(cfg, cell, **kw)
