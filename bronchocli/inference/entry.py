"""``bronchopose track`` as a library call: apply a model to an opened input, chain and score the poses, write the
trajectory (CSV, figure) and print the errors beside both image-blind references.

The command checks its flags and inputs first (one model source, the first pose, the input, the output folder,
the ground truth), loads the config, resolves ``--best`` to a run (a report table's choice: ``reporting.best``,
a layer above this one) and calls ``track``.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
from mlflow.tracking import MlflowClient
from rich.console import Console
from rich.table import Table

from .. import registry, runkeys
from ..config import Config
from ..runs.client import client_for, require_store
from . import loading, trajectory
from .reader import FrameInput, GroundTruth

SOURCES = runkeys.SOURCES


def errors_table(errors) -> Table:
    """Per metric and evaluation (per pair: mean over pairs; accumulated: endpoint error), model vs references."""
    row = errors.iloc[0]
    table = Table(title="errors: per pair (mean) and accumulated (endpoint after chaining)")
    for name in ("metric", "evaluation", *SOURCES):
        table.add_column(name.replace("_", " "), justify="left" if name in ("metric", "evaluation") else "right")
    for spec in registry.metric_specs(per="pose"):
        metric, unit = spec.name, spec.symbol
        if runkeys.column(metric) not in row:
            continue
        for ev, text in (("pair", "per pair"), ("acc", "accumulated")):
            values = [float(row[runkeys.column(metric, ev, s)]) for s in SOURCES]
            table.add_row(f"{metric} ({unit})" if unit else metric, text,
                          *("nan" if math.isnan(v) else f"{v:.6g}" for v in values))
    return table


def track(cfg: Config, inp: FrameInput, reference: str, out: Path, *, first_pose: np.ndarray | None = None,
          truth: GroundTruth | None = None, register: str | None = None, progress: bool = True,
          console: Console, client: MlflowClient | None = None) -> list[Path]:
    """Track the camera through ``inp`` with the model of ``reference`` (a run id or an MLflow model URI) and
    write the results to ``out``; with ``register``, also register the model under that name. ``client``: the
    config's MLflow client when the caller has one open. Returns the files written."""
    if client is None and not Path(reference).expanduser().is_dir():  # a model folder needs no store
        require_store(cfg)
    client = client or client_for(cfg)
    loaded = loading.load(client, reference)
    if register:
        version = loading.register(client, loaded.ref, register)
        console.print(f"registered as models:/{register}/{version}")
    spec = loaded.model.spec
    console.print(f"[bold]track[/] {inp.name} ({inp.kind}, {inp.n_frames or '?'} frames, {inp.shape[1]}x"
                  f"{inp.shape[0]}) with {loaded.label} (run {loaded.ref.run_id or '?'}, {spec['pose_frame']} "
                  f"pose frame, {spec['image_size']} px)")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = trajectory.track(loaded.model, inp, first_pose, truth, progress=progress)
    for w in caught:
        console.print(f"[yellow]warning:[/] {w.message}")
    title = result.truth.key if result.truth is not None and result.truth.key else Path(inp.name).name
    files = trajectory.write(result, out, title=title, model_label=loaded.label)
    console.print(f"{len(result.poses)} poses chained in the {result.pose_frame} frame from "
                  f"({', '.join(f'{v:g}' for v in result.first_pose)})")
    if result.errors is not None:
        console.print(errors_table(result.errors))
    for f in files:
        console.print(f"wrote {f}")
    return files
