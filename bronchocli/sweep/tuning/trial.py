"""Hyperparameter tuning with Optuna: what one trial of a cell's study is.

Each trial samples ``tune.space`` (dotted config paths -> distributions), trains
the cell with those values as one MLflow run (tagged ``run_kind=trial``, the
study and trial number) and returns ``tune.objective`` of that run (the best
validation loss by default), which the study minimises. Per-validation values
are reported to Optuna, whose pruner (median or Hyperband) may stop a trial
early: its run is KILLED and tagged ``pruned``. The study lives in the shared
storage (``studies``); its trials are rows of the claims table, claimed and run
by sweep workers of any launcher (``launch``, ``worker``), so
``--trials N`` is the study's rows, not this process's. A trial stopped by a
signal hands its checkpoint to a trial of the same parameters that the next
claim of its row resumes (``resume``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from typing import Any

import optuna

from ... import runkeys
from ...cells import Cell
from ...config import Config, TuneParam, space_problems
from ...errors import BronchoError, ConfigError
from ...runs.client import client_for, experiment_id
from ...runs.contract import RunPruned
from ...runs.parents import study_parent
from ...runs.records import TAG_PARENT, run_name
from ...training.cost import COST_TARGET, cost_value
from .studies import ATTR_OBJECTIVE, storage_for
from .resume import ATTR_RUN, keep_for_resume, resume_from, worth_resuming

log = logging.getLogger(__name__)


class TrialFailed(BronchoError):
    """A trial's run FAILED (e.g. a non-finite loss); the study records it and its row fails."""


ATTR_CELL = "cell"
ATTR_WORKER = "worker"  # the worker (host, pid, GPU) that ran the trial, as its claims row names it


def study_name(cfg: Config, cell: Cell) -> str:
    """The default study of a cell: everything of the cell except the hyperparameters being searched."""
    fold = f"-{cell.fold}" if cell.fold else ""
    size = f"-t{cell.train_trajectories}" if cell.train_trajectories else ""
    return f"{cfg.name}-{cell.arch}-{cell.rot_loss}-{cell.population}{fold}-{cell.pose_frame}-s{cell.seed}{size}"


def check_space(cfg: Config) -> None:
    """Every ``tune.space`` key must be a settable config path and every distribution well formed
    (``config.space_problems``, which loading a config already runs)."""
    problems = space_problems(cfg)
    if problems:
        raise ConfigError("invalid tune.space:\n  " + "\n  ".join(problems))


def suggest(trial, space: Mapping[str, TuneParam]) -> dict[str, Any]:
    values: dict[str, Any] = {}
    for path, p in space.items():
        if p.type == "float":
            values[path] = trial.suggest_float(path, p.low, p.high, log=p.log, step=p.step)
        elif p.type == "int":
            values[path] = trial.suggest_int(path, int(p.low), int(p.high), log=p.log, step=int(p.step or 1))
        else:
            values[path] = trial.suggest_categorical(path, p.choices)
    return values


# What a trial returns, per tune.objective: (the per-validation key reported to the pruner, the run's metric)
OBJECTIVES = {"val_loss": (runkeys.VAL_LOSS, runkeys.best_of(runkeys.VAL_LOSS)),
              "val_ratio": (runkeys.VAL_RATIO, runkeys.best_of(runkeys.VAL_RATIO)),
              # the cost of learning (training/cost.py): pairs seen until val.ratio.pos_l2 <= COST_TARGET; each
              # trial stops there (train.stop_at_ratio), its validations report the ratio to the pruner
              "cost": (runkeys.VAL_RATIO, runkeys.cost("pairs", COST_TARGET))}


def objective_metric(cfg: Config) -> str:
    """The run metric a trial's value is (``val_best.loss`` or ``val_best.ratio.pos_l2``)."""
    return OBJECTIVES[cfg.tune.objective][1]


def _val_every_pairs(cfg: Config) -> int:
    return cfg.train.val_every * cfg.train.pairs_per_step


def budgeted(base: Config, trial_cfg: Config) -> Config:
    """A trial's config under ``tune.budget_pairs``: as many steps as the budget's pairs at the trial's pairs per
    step, validations every as many pairs as the study's base config validates at (``train.val_every`` x its pairs
    per step), so every trial is judged at the same pairs seen; ``trial_cfg`` itself without a budget."""
    budget = base.tune.budget_pairs
    if budget is None:
        return trial_cfg
    per_step = trial_cfg.train.pairs_per_step
    steps = max(1, math.ceil(budget / per_step))
    every = max(1, min(steps, round(_val_every_pairs(base) / per_step)))
    return trial_cfg.with_values({"train.steps": steps, "train.val_every": every})


def make_pruner(cfg: Config):
    """Trials report at optimiser steps (every train.val_every), or at pairs seen under tune.budget_pairs:
    the warm-up and the resources are in those units."""
    t = cfg.tune
    unit = _val_every_pairs(cfg) if t.budget_pairs is not None else cfg.train.val_every
    end = t.budget_pairs if t.budget_pairs is not None else cfg.train.steps
    if t.pruner == "median":
        return optuna.pruners.MedianPruner(n_startup_trials=t.startup_trials,
                                           n_warmup_steps=t.warmup_validations * unit)
    if t.pruner == "hyperband":
        return optuna.pruners.HyperbandPruner(min_resource=max(1, t.warmup_validations) * unit, max_resource=end)
    return optuna.pruners.NopPruner()


def make_sampler(cfg: Config, worker: int = 0):
    seed = cfg.tune.seed + worker  # workers of one study must not propose identical first trials
    if cfg.tune.sampler == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    return optuna.samplers.TPESampler(seed=seed, n_startup_trials=cfg.tune.startup_trials)


def open_study(cfg: Config, cell: Cell, *, study: str | None = None, worker: int = 0):
    name = study or study_name(cfg, cell)
    s = optuna.create_study(study_name=name, storage=storage_for(cfg), direction="minimize",
                            sampler=make_sampler(cfg, worker), pruner=make_pruner(cfg), load_if_exists=True)
    metric = objective_metric(cfg)
    before = s.user_attrs.get(ATTR_OBJECTIVE)
    if before is not None and before != metric:  # trials of one study must minimise one thing
        raise ConfigError(f"tune.objective {cfg.tune.objective!r}: study {name!r} minimises {before} already; "
                          "keep its objective or name a new study (--study NAME)")
    s.set_user_attr("target", cell.tags())
    s.set_user_attr(ATTR_OBJECTIVE, metric)
    return s


def study_parent_or_none(cfg: Config, target: Cell, name: str) -> str | None:
    """The study's parent MLflow run (trials nest under it); None when the MLflow store refused it."""
    try:
        client = client_for(cfg)
        return study_parent(client, cfg, experiment_id(client, cfg), name, target)
    except Exception as exc:  # noqa: BLE001 - nesting is cosmetic: trials must run without it
        log.warning("no parent run for study %s: %s", name, exc)
        return None


def objective(cfg: Config, target: Cell, name: str, *, parent: str | None, worker: str,
              extra_tags: Mapping[str, str] = (), progress: bool = False,
              run_id_callback: Callable[[str], None] = lambda _: None, **run_kw: Any) -> Callable:
    """The function Optuna calls for one trial: train one configured run, return ``tune.objective`` of the weights
    it tested (``objective_metric``); validations report the same quantity to the pruner, at optimiser steps or,
    under ``tune.budget_pairs``, at pairs seen. ``extra_tags`` (the claim's), ``run_id_callback`` (the row records
    the run) and ``run_kw`` go to ``run_cell``; ``run.stop_requested`` holds the signal that arrived while the
    trial evaluated (the trial counts, its worker stops)."""
    from ...training.run import run_cell  # lazy: torch loads only where trials run, not for --show

    reported, metric = OBJECTIVES[cfg.tune.objective]

    def run(trial) -> float:
        values = suggest(trial, cfg.tune.space)
        trial_cfg = budgeted(cfg, cfg.with_values(values))
        if cfg.tune.objective == "cost":  # a trial ends once it learned: the pairs it took are its value
            trial_cfg = trial_cfg.with_values({"train.stop_at_ratio": COST_TARGET})
        cell = trial_cfg.cell(**target.coords())
        per_step = trial_cfg.train.pairs_per_step if cfg.tune.budget_pairs is not None else 1
        trial.set_user_attr(ATTR_CELL, cell.key)
        trial.set_user_attr(ATTR_WORKER, worker)

        def on_validation(step: int, metrics: dict[str, float]) -> None:
            value = metrics[reported]
            trial.report(value, step * per_step)
            if trial.should_prune():
                raise RunPruned(f"pruned by the {cfg.tune.pruner} pruner at step {step} ({reported} {value:.4g})")

        def on_run_id(run_id: str) -> None:
            trial.set_user_attr(ATTR_RUN, run_id)
            run_id_callback(run_id)

        tags = {**dict(extra_tags), "run_kind": "trial", "study": name, "trial": str(trial.number),
                "mlflow.runName": f"trial-{trial.number} · {run_name(cell)}",
                "hparams_source": f"optuna:{name}#{trial.number}"}
        if parent is not None:
            tags[TAG_PARENT] = parent
        resume = resume_from(cfg, trial, cell.key, tags)  # a trial enqueued to continue a stopped one's run
        try:
            result = run_cell(trial_cfg, cell, resume=resume, extra_tags=tags, progress=progress,
                              on_validation=on_validation, run_id_callback=on_run_id, **run_kw)
        except RunPruned as exc:
            raise optuna.TrialPruned(str(exc)) from None
        except BaseException as exc:  # stopped with a checkpoint: a new trial continues it (this one ends FAIL)
            if worth_resuming(exc):
                keep_for_resume(cfg, trial, trial.user_attrs.get(ATTR_RUN) or resume, cell.key)
            raise
        if result.status != "FINISHED":
            raise TrialFailed(f"trial {trial.number} failed: {result.failure_reason}")
        if result.stop_requested:  # a stop request during the trial's evaluation: the trial counts, none follows
            run.stop_requested = result.stop_requested
        value = cost_value(result.metrics) if cfg.tune.objective == "cost" else result.metrics.get(metric, math.nan)
        if not math.isfinite(value):
            raise TrialFailed(f"trial {trial.number}: no finite {metric}")
        return value

    run.stop_requested = None  # the signal of a stop request that arrived while the trial evaluated
    return run
