"""The library calls behind ``bronchopose sweep run | plan | status | gc | cancel``, ``status``, ``tune`` and
``config --grid``: each command parses its flags and reaches exactly one of these through ``bronchocli.api``.

The sweep's verbs (the config loaded by ``task.TaskSpec.load``, the same call a detached worker makes):

- ``run``: the plan's stages with a launcher (local worker processes, Slurm job arrays, any registered one):
  submit the workers, then watch (``launch.launch``, the one driver); ``launcher_options`` refuses the
  options a launcher does not take;
- ``dry_run`` (``sweep plan``): the plan and each cell's state; nothing is started;
- ``gc``: remove the checkpoints nothing can resume on this machine (``dry_run``: list them), list the kept;
- ``cancel``: stop the sweep's workers of a launcher (``dry_run``: list them).

Every verb with ``--dry-run`` changes nothing anywhere: no job submitted or cancelled, no file or row written.

A detached worker is not a verb of the command: it starts
``python -m bronchocli.sweep.task '<spec>'`` (``task.main``). The others:
``status`` (``bronchopose status``), ``grid`` (``config --grid``), ``tune`` and
``show_study`` (``tune`` and ``tune --show``).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from .. import urls
from ..cells import FIELDS, Cell, Selection
from ..config import Config, check_paths, check_roots
from ..config.arguments import ArgumentError
from ..errors import BronchoError
from ..generation import ensure_dataset
from ..io import fmt_bytes
from ..runs.client import check_reachable, client_for, experiment_id, store_missing
from ..runs.parents import KIND_SWEEP, find_parent
from . import damage
from . import launch as launching
from . import placement, planview, summary
from .housekeeping import collect_garbage, foreign, inventory, repair_zombies
from .launchers import GENERIC, Launcher, flag, launcher_class, log_roots, owners, reference
from .launchers import parameters as launcher_parameters
from .plan import StageWalk, open_store
from .stagework import end_abandoned
from .status import SweepState, show_status
from .record import missing_runs
from .storage import FINISHED, SweepStore
from .summary import record_cancel
from .task import TaskSpec, command

log = logging.getLogger(__name__)

TUNE_LAUNCHER = "local"  # ``tune --launcher``'s default (a sweep's: ``sweep.launcher``)


def launcher_kind(cfg: Config, name: str | None) -> type[Launcher]:
    """The launcher ``--launcher`` names (default: ``sweep.launcher``); one line naming the known ones. Its own
    settings (``sweep.launchers.<name>``) and every other launcher section are validated here, before anything
    (``launchers.log_roots``)."""
    kind = launcher_class(name or cfg.sweep.launcher, "--launcher" if name else "sweep.launcher")
    log_roots(cfg, kind)
    return kind


def _local_store(cfg: Config, extra: Sequence[tuple[str, Path]] = ()) -> SweepStore:
    check_paths(cfg, storage=True, logs=True, extra=extra)  # before anything is created (a dry run says so too)
    store = open_store(cfg)
    store.exists()  # an unreachable storage fails here, in runs.timeout_s, before anything is created
    return store


def _workers(workers: int | None, gpus: str, per_gpu: int) -> tuple[int, list[str]]:
    """Local workers and their GPUs: ``--gpus`` (auto, none or a list), default GPUs x ``per_gpu`` (else 1)."""
    devices = placement.parse_gpus(gpus, placement.visible_gpus())
    return workers or placement.default_workers(devices, per_gpu), devices


def launcher_options(kind: type[Launcher], given: Mapping[str, Any], call: str = "api.sweep") -> dict[str, Any]:
    """The launcher options given to ``sweep run`` or ``tune`` (``{"workers": 2}``; None: not given) as
    ``kind(...)`` takes them, each checked against the ``Parameter`` that ``kind.parameters`` declares; one line
    naming, as the command line spells them, those it does not take and the launchers that do (``call``: the API
    call a bad value is named by)."""
    given = {name: value for name, value in given.items() if value is not None}
    if foreign := [name for name in given if name not in kind.parameters]:
        known = launcher_parameters()
        if unknown := [flag(name) for name in foreign if name not in known]:
            raise BronchoError(f"{', '.join(unknown)}: no installed launcher takes "
                               f"{'it' if len(unknown) == 1 else 'them'} (launcher options: "
                               f"{', '.join(map(flag, known))})")
        takers = list(dict.fromkeys(k for name in foreign for k in owners(name)))
        raise BronchoError(f"{', '.join(map(flag, foreign))}: options of the {'/'.join(takers) or 'other'} launcher; "
                           f"launcher {kind.name} does not take {'it' if len(foreign) == 1 else 'them'} "
                           "(docs/sweep.md, \"Launcher options\")")
    for name, value in given.items():
        if not (param := kind.parameters[name]).ok(name, value):
            raise ArgumentError(f"{call}: {name}={value!r}: must be {param.allowed(name)} (as {flag(name)} on the "
                                "command line)")
    return given


def run(cfg: Config, spec: TaskSpec, kind: type[Launcher], *, options: dict[str, Any] | None = None,
        detach: bool = False, retry_failed: bool = False, console: Console) -> int:
    """Run every cell of the plan not FINISHED with launcher ``kind`` (``options``: ``launcher_options``'s): its
    workers run the cells (a detached launcher's each run ``task.command`` with ``spec``), watched unless
    ``detach``; re-running submits only what the queued and running workers do not cover. 0 all FINISHED, 1
    some FAILED, 130 stopped."""
    check_paths(cfg, storage=True, logs=True, extra=log_roots(cfg, kind))  # before anything is created
    launcher = kind(cfg, lambda: command(cfg, replace(spec, launcher=reference(kind))), only=spec.selection(),
                    runner=spec.cell_runner(), **(options or {}))
    launcher.check()  # first: a refused submission writes no 0600 secrets file (``command``, made at the first
    # submission of a launcher whose workers run it, seals the spec)
    store = open_store(cfg)
    store.exists()  # an unreachable storage fails here, in runs.timeout_s, before anything is created
    if cfg.model.pretrained is not None:  # fetch/find backbone weights once, before any worker or run starts
        from ..models import initialisation  # lazy: torch loads in the sweep's parent only when weights are needed

        initialisation(cfg.paths.pretrained, sorted({a for g in [cfg.grid, *(st.stage_grid(cfg.grid)
                                                                          for st in cfg.stages)] for a in g.arch}),
                       cfg.model.backbone)
    return launching.launch(cfg, store, spec.selection(), launcher, detach=detach, console=console,
                            retry_failed=retry_failed)


def dry_run(cfg: Config, only: Selection, *, options: Mapping[str, Any] | None = None, console: Console) -> int:
    """Print the plan (per stage: its cells and their state) and the local workers a run would start, placed by
    the generic launcher ``options`` (workers, gpus, per_gpu; no other is taken); starts nothing."""
    given = {name: value for name, value in (options or {}).items() if value is not None}
    if other := [flag(name) for name in given if name not in GENERIC]:
        raise BronchoError(f"{', '.join(other)}: `sweep plan` takes the generic launcher options only "
                           f"({', '.join(map(flag, GENERIC))})")
    for name, value in given.items():
        if not GENERIC[name].ok(name, value):
            raise ArgumentError(f"api.plan: {name}={value!r}: must be {GENERIC[name].allowed(name)} (as {flag(name)} "
                                "on the command line)")
    store = _local_store(cfg, log_roots(cfg))
    n, _ = _workers(given.get("workers"), given.get("gpus") or "auto", given.get("per_gpu") or 1)
    planview.dry_run(cfg, store, only, n, console)
    return 0


def gc(cfg: Config, console: Console, *, dry_run: bool = False) -> int:
    """Remove the checkpoints no live cell needs on this machine and say what was freed (``dry_run``: what would
    go; nothing is removed), then what is kept and why (a cell, `train --resume` or a study may resume it). Only
    what provably is a run's checkpoint is ever removed (``runs.ownership``)."""
    check_roots(cfg, log_roots(cfg))  # a checkpoints root holding other roots (or a system folder): refused first
    store = open_store(cfg)
    held = inventory(cfg, store if store.exists() else None)
    freed = collect_garbage(cfg, store if store.exists() else None, dry_run=dry_run, held=held)
    verb = "would free" if dry_run else "freed"
    for ck, n in freed:
        what = "rejected/temporary files" if ck.needed else ck.why
        console.print(f"{verb} {fmt_bytes(n)}: {ck.folder} ({what})", highlight=False, soft_wrap=True)
    for ck in held:
        if ck.needed:  # what stays, and why (a run that may be resumed: a cell, `train --resume`, a study)
            console.print(f"kept {fmt_bytes(ck.bytes - ck.waste)}: {ck.folder} ({ck.why})", highlight=False,
                          soft_wrap=True)
    others = foreign(cfg)
    if others:
        shown = ", ".join(p.name for p in others[:8]) + (", ..." if len(others) > 8 else "")
        console.print(f"left alone: {len(others)} entr{'y' if len(others) == 1 else 'ies'} in "
                      f"{cfg.paths.checkpoints} not provably a checkpoint of this project ({shown})", highlight=False)
    console.print(f"gc{' --dry-run' if dry_run else ''}: {verb} {fmt_bytes(sum(n for _, n in freed))} in "
                  f"{len(freed)} checkpoint folder(s)" + ("; nothing was removed" if dry_run else ""))
    return 0


def cancel(cfg: Config, kind: type[Launcher], console: Console, *, dry_run: bool = False,
           study: str | None = None) -> int:
    """Stop every queued or running worker of the sweep (running ones release their cells), or of the tuning
    study ``study`` (``tuning.launch.cancel_study``); ``dry_run``: list them and stop nothing."""
    if not kind.Session.outlives_command:
        raise BronchoError(f"--launcher {kind.name}: its workers are the `{'tune' if study else 'sweep run'}` "
                           "command's own processes; stop that command (Ctrl-C) instead")
    if study is not None:
        from .tuning.launch import cancel_study  # lazy: optuna only for a study

        return cancel_study(cfg, study, kind, console, dry_run=dry_run)
    if not dry_run:  # recorded first: a watcher that sees the workers go never submits them again
        client = client_for(cfg)
        record_cancel(client, experiment_id(client, cfg), cfg.name)
    return launching.cancel(kind(cfg), console, dry_run=dry_run)


# -- bronchopose status, config --grid -----------------------------------------------------------------


def status(cfg: Config, name: str, *, show_all: bool = False, repair: bool = False,
           console: Console) -> SweepState:
    """``bronchopose status``: show the sweep's cells; returns what it showed (``status.SweepState``: the cells, their
    runs and metrics). It writes nothing, unless ``repair``: first end the runs a dead process left RUNNING, the
    parent of a detached sweep whose workers are all gone (``settle_detached``), and repair damaged claims rows."""
    store = open_store(cfg)
    if repair:
        done = repair_zombies(cfg, store if store.exists() else None)
        for run_id, what in done:
            console.print(f"repaired run {run_id}: {what}", highlight=False)
        console.print(f"--repair: {len(done)} run(s) left RUNNING by a dead process were ended")
        if store.exists():
            plan = StageWalk(cfg, store).known_cells() if name == cfg.name else []
            rows = damage.repair(store, name, plan)
            for row, what in rows:
                console.print(f"repaired claims row {row.sweep}/{row.cell_key} ({row.label}): {what} (was: "
                              f"{row.damage})", highlight=False, soft_wrap=True)
            if rows:
                console.print(f"--repair: {len(rows)} damaged claims row(s) repaired")
            finished = [r for r in store.rows(name) if r.state == FINISHED and r.run_id and r.damage is None]
            gone = set(missing_runs(cfg, [r.run_id for r in finished]))
            reset = [r for r in finished if r.run_id in gone and store.repair(r)]
            for r in reset:
                console.print(f"repaired claims row {r.sweep}/{r.cell_key} ({r.label}): pending again (its run "
                              f"{r.run_id} does not exist in MLflow)", highlight=False, soft_wrap=True)
        if name == cfg.name and store.exists():
            settle_detached(cfg, store)  # a detached sweep whose workers are all gone: its parent ends (status says so)
    return show_status(cfg, store, name, show_all, console)


def settle_detached(cfg: Config, store: SweepStore) -> str | None:
    """The sweep's parent run RUNNING though it was submitted with a detachable launcher (``TAG_LAUNCHER``), no
    watcher of it lives (``TAG_WATCHER``) and none of its workers is queued or running (they were all cancelled
    before any ran, say): ended as its last worker would have (``stagework.end_abandoned``); the reason, or None.
    ``status --repair`` asks it (a local sweep's parent it ends by its process tags); plain ``status`` writes
    nothing."""
    try:
        if store_missing(cfg):
            return None
        client = client_for(cfg, reading=True)
        exp = client.get_experiment_by_name(cfg.experiment_name)
        live = exp is not None and exp.lifecycle_stage == "active"  # a deleted one: the table's line says so
        parent = find_parent(client, exp.experiment_id, KIND_SWEEP, cfg.name) if live else None
        tags = client.get_run(parent).data.tags if parent is not None else {}
        name = tags.get(summary.TAG_LAUNCHER)
        if name is None or summary.watcher_alive(tags.get(summary.TAG_WATCHER)):
            return None
        kind = launcher_class(name, f"tag {summary.TAG_LAUNCHER} of parent run {parent}")
    except Exception as exc:  # noqa: BLE001 - the table's own reading of MLflow says what is wrong, in one line
        log.debug("could not read the sweep's parent run: %s", exc)
        return None
    return end_abandoned(cfg, store, None, kind) if kind.Session.outlives_command else None


def grid(cfg: Config, console: Console) -> None:
    """``bronchopose config --grid``: the plan's cells per stage (a selecting stage: what it will choose)."""
    total = 0
    for sp in StageWalk(cfg, None).plans():  # a procedural dataset's patients are known before it exists
        title = f"{cfg.name}" + ("" if sp.stage.name == "grid" else f", stage {sp.stage.name}")
        if sp.cells is None:
            console.print(f"{title}: the top {sp.stage.select.top} combinations of stage "
                          f"{sp.stage.source or 'before'} by {sp.stage.select.by}, chosen when it is done")
            continue
        table = Table("key", *FIELDS, title=title)
        for c in sp.cells:
            table.add_row(c.key, *(v or "-" for v in c.tags().values()))
        console.print(table)
        total += len(sp.cells)
    console.print(f"{total} cells")


# -- bronchopose tune ------------------------------------------------------------------------------------


def show_study(cfg: Config, study: str | None, target: Cell | None, fmt: str, console: Console) -> dict[str, Any]:
    """``tune --show``: the best trial and parameter importances of ``study`` (default: the cell's study); returns
    what it showed (``studies.describe_study``)."""
    from .tuning import studies, trial as tuning  # lazy: optuna only when a study is read

    if study is None and target is None:
        names = studies.list_studies(cfg)
        raise BronchoError("--show needs --study NAME (or the cell's --arch/--rot-loss/--population); "
                           f"studies in the storage: {', '.join(names) or 'none'}")
    study = study or tuning.study_name(cfg, target)
    info = studies.summary(cfg, study)
    if fmt == "json":
        console.print_json(json.dumps(info, default=str))
        return info
    counts = ", ".join(f"{v} {k}" for k, v in info["counts"].items() if v)
    console.print(f"[bold]study[/] {study}: {counts or 'no trials'}")
    best = info["best"]
    if best is None:
        console.print("no completed trial yet")
        return info
    table = Table("parameter", "best value", "importance", title=f"best trial #{best['number']}: "
                  f"{info['objective']} {best['value']:.5g} (MLflow run {best['run_id']})")  # the metric minimised
    for name, value in best["params"].items():
        imp = info["importances"].get(name)
        table.add_row(name, f"{value:.4g}" if isinstance(value, float) else str(value),
                      "—" if imp is None else f"{imp:.3f}")
    console.print(table)
    if info.get("importances_note"):
        console.print(f"importances unavailable: {info['importances_note']}")
    console.print(f"apply it: bronchopose sweep run --use-tuned {study}  (or train --use-tuned {study})")
    return info


def tune(cfg: Config, target: Cell, *, trials: int | None = None, study: str | None = None,
         timeout: float | None = None, kind: type[Launcher] | None = None, options: dict[str, Any] | None = None,
         spec: TaskSpec | None = None, progress: bool = True, console: Console) -> dict[str, Any]:
    """``bronchopose tune``: the cell's study (shared storage, resumable) to ``trials`` rows done, its trials claimed
    by workers of launcher ``kind`` (``options``: ``launcher_options``'s; the local one with one worker and no GPU
    runs it in this process, its own choice), then show its best trial; returns the study's description
    (``studies.describe_study``)."""
    from .tuning import launch as trialrows, studies, trial as tuning  # lazy: optuna only when the command runs

    kind = kind or launcher_class(TUNE_LAUNCHER)
    options = dict(options or {})
    _local_store(cfg)  # paths, then the storage answers (runs.timeout_s): one line before any dataset is rendered
    check_reachable(cfg)  # the MLflow server or database too
    trials = trials or cfg.tune.trials
    name = study or tuning.study_name(cfg, target)
    trialrows.launcher_config(cfg, name)  # a --study that cannot name the rows: one line first
    if "workers" in kind.parameters:  # workers placed here (--workers, --gpus, --per-gpu): one per trial at most
        n, _ = _workers(options.get("workers"), options.get("gpus") or "auto", options.get("per_gpu") or 1)
        options["workers"] = min(n, trials)
    ensure_dataset(cfg)
    if cfg.model.pretrained is not None:  # missing backbone weights: one line before any study or trial run
        from ..models import initialisation  # lazy: torch only when backbone weights must be found or fetched

        initialisation(cfg.paths.pretrained, [target.arch], cfg.model.backbone)
    console.print(f"[bold]tune[/] {name}: {trials} trials, launcher {kind.name}, "
                  f"storage {urls.redact(cfg.paths.storage_url)}")
    def make(lcfg: Config, task: Any, cmd: Any) -> Launcher:
        return kind(lcfg, cmd, study=task, **options)

    s = trialrows.tune(cfg, target, trials, study=name, timeout=timeout or cfg.tune.timeout, spec=spec,
                       make_launcher=make,
                       progress=progress, enqueue=cfg.tune.enqueue, console=console)
    console.print(f"{studies.finished(s)} finished trials in study {name}")
    return show_study(cfg, name, None, "table", console)
