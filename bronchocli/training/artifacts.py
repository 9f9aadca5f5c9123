"""What a run leaves in MLflow: params, config, split manifest, metrics, predictions, errors, figure, weights.

* at the start: the dataset fingerprint tag, the comparable params
  (``run_params``: the cell's coordinates and the run settings that
  differ from the defaults), the dataset as an MLflow dataset input per split
  (train/val/test as context, digest = the fingerprint), ``env.torch`` and
  ``env.cuda`` tags, the run description, ``config.yaml`` (the full resolved
  config, passwords redacted) and ``split_manifest.csv``;
* training curves at step = optimiser step, every ``runs.log_every`` steps and
  at every validation: ``train_loss`` (the mean since the previous point),
  ``lr``, ``grad_norm`` (unscaled global L2 norm; at the ``log_every`` points)
  and ``pairs_per_s`` (training throughput since the previous point), one
  ``log_batch`` per validation;
* per validation: ``val_loss``, ``val.*``, ``train.pairs_seen``,
  ``train.epochs``, ``train.skipped_steps`` and ``train.core_s`` (their last
  point is the run's value: the end of a run is a validation, so a key every
  validation logs is not logged again at the end, and never at step 0 after
  later steps: ``final_points``);
* at the end: the evaluation's constants as params (``eval.ctf_position``,
  ``eval.ctf_position_mm``, ``eval.ctf_angle``, ``eval.rpe_gap``:
  ``views.eval_params``), the headline ratios and skills against both references
  (``ratio.*``, ``skill.*``, see ``runs.views.reference_figures``) and the headline errors
  first, then every test metric (model, ``zero_motion.*``, ``train_mean.*``,
  ``pred.std*``) and the budget (``train.steps``, ``train.time_s``,
  ``train.pairs_per_s`` averaged over the run, ...), the ``stop_reason`` tag, the ``vs_references`` tag
  (``views.verdict``: "pair ✓ · acc †"), ``predictions.csv`` (one row per test frame, with the training-mean
  reference's chained poses), ``trajectory_errors.csv`` (one row per test trajectory: what
  ``report`` pairs models on), ``trajectories.png`` and, per
  ``runs.model_artifact`` (fp16, fp32 or none), the MLflow Model ``model``
  (``model_logging``: ``mlflow.pyfunc.load_model("runs:/<id>/model")``); the
  description gains the result.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import torch
from mlflow.entities import Dataset, DatasetInput, InputTag, RunTag

from .. import runkeys
from ..cells import Cell
from ..config import Config
from ..io import save_figure
from ..plots import trajectory_figure
from ..runs.records import TAG_FINGERPRINT, TAG_INIT, TAG_NOTE, backbone_of, log_metrics, log_params
from ..runs.views import TAG_VERDICT, describe, eval_params, ordered_metrics, run_params, verdict
from .engine import Outcome
from .evaluate import predictions_table, reference_predictions
from .model_logging import log_model
from .prepare import RunData

TAG_STOP = "stop_reason"


def _log_file(client, run_id: str, path: Path, artifact_path: str | None = None) -> None:
    client.log_artifact(run_id, str(path), artifact_path)


DIGEST_CHARS = 36  # MLflow's dataset digest column (VARCHAR(36) on PostgreSQL)


def environment_tags() -> dict[str, str]:
    """torch and its CUDA build ("none" for a CPU build); device, precision and GPU name are the engine's."""
    return {"env.torch": torch.__version__, "env.cuda": torch.version.cuda or "none"}


def dataset_name(cfg: Config, part: str) -> str:
    return f"{cfg.paths.dataset.name}:{part}"


def dataset_inputs(cfg: Config, data: RunData) -> list[DatasetInput]:
    """The dataset once per split (name ``<dataset>:<split>``, context train/val/test), digest = fingerprint."""
    root = cfg.paths.dataset
    out = []
    for part, trajectories in data.split.parts().items():
        profile = {"trajectories": len(trajectories), "frames": int(sum(len(t.frame_index) for t in trajectories)),
                   "patients": sorted({t.patient for t in trajectories}), "population": data.split.population,
                   "fold": data.split.fold}
        ds = Dataset(name=dataset_name(cfg, part), digest=data.fingerprint[:DIGEST_CHARS], source_type="local",
                     source=json.dumps({"uri": root.as_uri()}), profile=json.dumps(profile))
        out.append(DatasetInput(ds, [InputTag("mlflow.data.context", part)]))
    return out


def described(client, run_id: str, cfg: Config, cell: Cell, metrics: dict[str, float] | None = None) -> str:
    """The run's description (``views.describe``), its model named with the config's backbone and the run's
    ``init`` tag, as its run name is."""
    init = client.get_run(run_id).data.tags.get(TAG_INIT)
    return describe(cell, metrics, cfg.paths.dataset.name, backbone_of(cfg), init)


def log_start(client, run_id: str, cfg: Config, data: RunData, cell: Cell,
              extra_params: dict[str, str] | None = None) -> None:
    client.set_tag(run_id, TAG_FINGERPRINT, data.fingerprint)
    log_params(client, run_id, {**run_params(cfg, cell), **(extra_params or {})})
    client.log_batch(run_id, tags=[RunTag(k, v) for k, v in {
        **environment_tags(), TAG_NOTE: described(client, run_id, cfg, cell)}.items()])
    client.log_inputs(run_id, datasets=dataset_inputs(cfg, data))
    with tempfile.TemporaryDirectory(prefix="bronchopose-") as tmp:
        out = Path(tmp)
        (out / "config.yaml").write_text(cfg.to_yaml())
        _log_file(client, run_id, out / "config.yaml")
        data.split.write_manifest(out / "split_manifest.csv")
        _log_file(client, run_id, out / "split_manifest.csv")


def final_points(metrics: dict[str, float], history: list[dict[str, float]]) -> tuple[dict[str, float],
                                                                                       dict[str, float]]:
    """The end-of-run metrics split by where they are logged: (at step 0: those with no per-validation history,
    at the last validation's step: the history's keys whose final value differs from that validation's). A key
    every validation logs (``train.core_s``, ``train.pairs_seen``, ...) has its run value as its last point, so its
    curve never jumps back to step 0; it is not logged again when the last validation logged the same value."""
    last = history[-1] if history else {}
    at_zero = {k: v for k, v in metrics.items() if not any(k in h for h in history)}
    at_last = {k: v for k, v in metrics.items() if k not in at_zero and last.get(k) != v}
    return at_zero, at_last


def log_outcome(client, run_id: str, cfg: Config, cell: Cell, data: RunData, outcome: Outcome) -> None:
    # The evaluation's constants as params, then the model (it gets the run's params), so that the test metrics are
    # logged once, as the run's and as the model's (on the test split).
    log_params(client, run_id, eval_params(cfg))
    model_id = log_model(client, run_id, cfg, cell, data, outcome) if cfg.runs.model_artifact != "none" else None
    test = (dataset_name(cfg, "test"), data.fingerprint[:DIGEST_CHARS])
    final, at_last = final_points(outcome.metrics, outcome.fit.history)
    for batch in ordered_metrics(final):  # headline first: the UI lists metrics as logged
        log_metrics(client, run_id, batch, model_id=model_id, dataset=test)
    if at_last:  # a curve's end value, where the last validation did not log it: at that step, never at step 0
        log_metrics(client, run_id, at_last, step=int(outcome.fit.history[-1]["step"]))
    client.set_tag(run_id, TAG_NOTE, described(client, run_id, cfg, cell, outcome.metrics))
    client.set_tag(run_id, TAG_STOP, outcome.fit.stop_reason)
    if judged := verdict(outcome.metrics):
        client.set_tag(run_id, TAG_VERDICT, judged)
    with tempfile.TemporaryDirectory(prefix="bronchopose-") as tmp:
        out = Path(tmp)
        mean = reference_predictions(outcome.predictions, data.label_mean, cell.pose_frame)[runkeys.REFERENCES[1]]
        predictions_table(outcome.predictions, mean).to_csv(out / "predictions.csv", index=False)
        _log_file(client, run_id, out / "predictions.csv")
        outcome.trajectories.to_csv(out / "trajectory_errors.csv", index=False)
        _log_file(client, run_id, out / "trajectory_errors.csv")
        shown = outcome.predictions[:6]
        fig = trajectory_figure([p.gt_abs for p in shown], {cell.arch: [p.pred_abs for p in shown]},
                                titles=[p.key for p in shown])
        for path in save_figure(fig, out / "trajectories"):
            _log_file(client, run_id, path)
