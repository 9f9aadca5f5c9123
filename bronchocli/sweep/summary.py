"""What a sweep's parent MLflow run says about the sweep (the plan that ran, its selections, its outcome), and
what a study's parent says about its Optuna study (``log_study``).

A reviewer opens the parent first, so it states what ran, not the config's grid lists (a stage's own grid
and a selection override those):

* params ``stages`` and, per stage ``s``, ``stage.<s>.cells`` and the values its cells take
  (``stage.<s>.arch``, ``.rot_loss``, ``.population``, ``.fold``, ``.seed``, ``.pose_frame``,
  ``.train_trajectories``), the rule of a selecting stage (``stage.<s>.select``) and, once settled, the
  combinations it kept (``stage.<s>.selected``); ``cells``: the distinct cells of all stages once every
  stage is known. A param is logged once (``runs.parents.log_plan_params``);
* tags ``selection.<s>``: the selection line with the values it ranked by (as ``sweep`` prints it);
* metrics ``cells.planned``, ``cells.finished``, ``cells.failed`` (the claims table's states of every
  planned cell) and, per stage, the best cell by validation: ``best.<s>.<metric>`` (the metric a later stage
  selects this one by, else ``select.by``'s default) and its test figures ``best.<s>.<figure>``
  (``BEST_FIGURES``: the headline and the error it divides), with tags ``best.<s>.cell`` (the cell's label)
  and ``best.<s>.run`` (its run id). Every key is built by ``runkeys``.

The driver (``launch.launch``) records the plan when it has submitted and everything when its watch ends
(not when it detaches). Recording is best effort: the cells' own runs carry the results.

A cancel is recorded there too, in the store every submitter, watcher and worker shares: ``sweep cancel``
tags the parent ``sweep_cancelled`` (``TAG_CANCELLED``) and ends it KILLED before it stops any worker; a
watcher that finds the tag stops re-submitting and exits, a worker that finishes the last stage leaves the
parent KILLED; the next explicit ``sweep run`` removes the tag (``uncancel``).

A detached sweep's workers stopped another way (``scancel`` of a stage's array, a node gone) leave no watcher to
end the parent: the last worker to leave, seeing no other worker of the sweep queued or running and cells not
done, ends it KILLED with the reason as tag ``sweep_stopped`` (``TAG_STOPPED``, ``stagework.settle_parent``); a
worker that starts on it again, or the next ``sweep run`` (``uncancel``), makes it RUNNING again (``reopen``).
"""

from __future__ import annotations

import logging
import socket
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .. import runkeys
from ..cells import FIELDS, Cell
from ..config import Select, Stage
from ..io import save_figure
from ..runs.parents import KIND_SWEEP, find_parent, log_plan_params, set_parent_status
from ..runs.processes import TAG_HOST, TAG_PID, TAG_PSTART, pid_alive, process_tags
from ..runs.records import TAG_NOTE, log_metrics, set_tags
from ..runs.views import text_figure
from . import plan as planning
from .selection import describe_selection, finished_runs
from .storage import FAILED, FINISHED

log = logging.getLogger(__name__)

TAG_CANCELLED = "sweep_cancelled"  # on the sweep's parent run: when `sweep cancel` ran (UTC); removed by `sweep run`
TAG_STOPPED = "sweep_stopped"  # on the sweep's parent run: why it ended with cells not done; removed when resumed
TAG_LAUNCHER = "sweep_launcher"  # on the sweep's parent run: the launcher `sweep run --launcher` submitted it with
TAG_WATCHER = "sweep_watcher"  # ... and the process watching it ("host pid start"), or "detached"


def watcher_tag(detached: bool) -> str:
    """``TAG_WATCHER``'s value for this process: "detached", or which process watches (host, pid, start tick)."""
    if detached:
        return "detached"
    tags = process_tags()
    return f"{tags[TAG_HOST]} {tags[TAG_PID]} {tags[TAG_PSTART]}"


def watcher_alive(value: str | None) -> bool:
    """Whether the watcher ``TAG_WATCHER`` names may still be watching: its process lives, or it runs on another host
    (cannot be told: assumed alive); False for "detached", none, or a process gone here."""
    parts = (value or "").split()
    if len(parts) != 3 or not parts[1].isdigit():
        return False
    return parts[0] != socket.gethostname() or pid_alive(int(parts[1]), parts[2])


def record_cancel(client, exp_id: str, sweep: str) -> str | None:
    """``sweep cancel``: tag the sweep's parent run cancelled and end it KILLED (before any worker is stopped, so
    a watcher never re-submits what is being cancelled); its id, or None when the sweep has no parent yet."""
    parent = find_parent(client, exp_id, KIND_SWEEP, sweep)
    if parent is not None:
        mark_cancelled(client, parent)
    return parent


def mark_cancelled(client, parent: str) -> None:
    """A sweep's or study's parent run tagged cancelled (``TAG_CANCELLED``: its watcher stops) and, while RUNNING,
    ended KILLED. A cancel touches only what runs: a FINISHED parent (every cell done) stays as it is, untagged."""
    status = client.get_run(parent).info.status
    if status == "FINISHED":
        return
    client.set_tag(parent, TAG_CANCELLED, time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    if status in ("RUNNING", "SCHEDULED"):
        set_parent_status(client, parent, 130)


def cancelled(client, parent: str | None) -> bool:
    """Whether ``sweep cancel`` ran since the sweep was last run (a store that does not answer: not known, no)."""
    if parent is None:
        return False
    try:
        return TAG_CANCELLED in client.get_run(parent).data.tags
    except Exception as exc:  # noqa: BLE001 - a busy store must not end a watch; asked again next time
        log.warning("could not read the sweep's parent run %s: %s", parent, exc)
        return False


def uncancel(client, parent: str) -> None:
    """An explicit ``sweep run``: the sweep is no longer cancelled, nor stopped."""
    tags = client.get_run(parent).data.tags
    for tag in (TAG_CANCELLED, TAG_STOPPED):
        if tag in tags:
            client.delete_tag(parent, tag)


def record_stop(client, parent: str, reason: str, code: int) -> None:
    """The sweep's last worker left with cells not done (``code`` 130: KILLED) or failed for good (1: FAILED):
    the parent ends so, ``reason`` as its ``TAG_STOPPED`` tag."""
    client.set_tag(parent, TAG_STOPPED, reason)
    set_parent_status(client, parent, code)


def reopen(client, parent: str) -> bool:
    """A worker starts on a sweep its last worker had stopped (``record_stop``): RUNNING again; True when it was."""
    run = client.get_run(parent)
    if TAG_STOPPED not in run.data.tags or TAG_CANCELLED in run.data.tags:
        return False
    client.update_run(parent, "RUNNING")
    client.delete_tag(parent, TAG_STOPPED)
    return True


BEST_FIGURES = (runkeys.HEADLINE, runkeys.HEADLINE_ERROR)  # the test figures shown next to each stage's best cell
DEFAULT_OBJECTIVE = runkeys.best_of(runkeys.VAL_LOSS)  # a study's objective metric where it names none


def _all_cells(walk: planning.StageWalk) -> list[Cell]:
    seen: dict[str, Cell] = {}
    for stage in walk.stages:
        for c in walk.cells(stage, mine=False) or []:
            seen.setdefault(c.key, c)
    return list(seen.values())


def _combo(combo: dict[str, Any]) -> str:
    return "/".join(str(v) for v in combo.values())


def plan_params(walk: planning.StageWalk) -> dict[str, str]:
    """What the plan runs, per stage (``--only`` aside: the plan, not this process's share of it)."""
    out = {"stages": ",".join(s.name for s in walk.stages)}
    for stage in walk.stages:
        p = f"stage.{stage.name}."
        if stage.select is not None:
            sel = stage.select
            out[p + "select"] = (f"top {sel.top} of {planning.source_of(walk.cfg, stage).name} by {sel.by} "
                                 f"over {','.join(sel.over)}")
        if (selection := walk.selections.get(stage.name)) is not None:
            out[p + "selected"] = ",".join(_combo(c) for c in selection["selected"])
        cells = walk.cells(stage, mine=False)
        if cells is None:
            continue
        out[p + "cells"] = str(len(cells))
        for f in FIELDS:
            values = dict.fromkeys(str(getattr(c, f)) for c in cells if getattr(c, f) is not None)
            if values:
                out[p + f] = ",".join(values)
    if walk.complete:
        out["cells"] = str(len(_all_cells(walk)))
    return out


def selection_tags(walk: planning.StageWalk) -> dict[str, str]:
    return {f"selection.{name}": describe_selection(sel) for name, sel in walk.selections.items()}


def ranked_by(cfg, stage: Stage) -> str:
    """The validation metric that ranks ``stage``'s cells: the one a later stage selects it by, else the default."""
    for later in planning.stages_of(cfg):
        if later.select is not None and later is not stage and planning.source_of(cfg, later).name == stage.name:
            return later.select.by
    return Select().by


def outcome(walk: planning.StageWalk) -> tuple[dict[str, float], dict[str, str]]:
    """Metrics and tags: how many planned cells finished or failed, and each stage's best cell by validation."""
    cfg = walk.cfg
    cells = _all_cells(walk)
    rows = planning.read_plan(walk.store, walk.sweep, cells)
    states = [rows.state(c) for c in cells]
    metrics = {runkeys.cells("planned"): float(len(cells)), runkeys.cells("finished"): float(states.count(FINISHED)),
               runkeys.cells("failed"): float(states.count(FAILED))}
    tags: dict[str, str] = {}
    runs = finished_runs(cfg, cells, walk.sweep) if cells else {}
    for stage in walk.stages:
        by = ranked_by(cfg, stage)
        scored = [(runs[c.key].data.metrics[by], c.label, runs[c.key]) for c in walk.cells(stage, mine=False) or []
                  if c.key in runs and by in runs[c.key].data.metrics]
        if not scored:
            continue
        value, label, run = min(scored, key=lambda t: (t[0], t[1]))
        metrics[runkeys.best(stage.name, by)] = value
        metrics |= {runkeys.best(stage.name, h): run.data.metrics[h] for h in BEST_FIGURES if h in run.data.metrics}
        tags |= {runkeys.best(stage.name, "cell"): label, runkeys.best(stage.name, "run"): run.info.run_id}
    return metrics, tags


def describe_sweep(walk: planning.StageWalk, metrics: Mapping[str, float], tags: Mapping[str, str]) -> str:
    """The parent's description (Markdown, the top of its run page): counts, then per stage what ran, what it
    selected and its best cell, headline first."""
    planned, finished, failed = (int(metrics[runkeys.cells(s)]) for s in runkeys.CELL_STATES)
    lines = [f"Sweep **{walk.sweep}**: {planned} cells planned, {finished} finished, "
             f"{failed} failed. Per stage (params `stage.<name>.*`, metrics `best.<name>.*`):"]
    for stage in walk.stages:
        cells = walk.cells(stage, mine=False)
        what = f"{len(cells)} cells" if cells is not None else "not known yet"
        if (sel := walk.selections.get(stage.name)) is not None:
            what += f", {describe_selection(sel).split(': ', 1)[1]}"
        elif stage.select is not None:
            what += f", selects the top {stage.select.top} of stage {planning.source_of(walk.cfg, stage).name}"
        best = ""
        if (cell := runkeys.best(stage.name, "cell")) in tags:
            by = ranked_by(walk.cfg, stage)
            figures = [f"{h} {text_figure(metrics[k])}" for h in BEST_FIGURES
                       if (k := runkeys.best(stage.name, h)) in metrics]
            best = (f"; best by validation: {tags[cell]} ("
                    + ", ".join(figures + [f"{by} {text_figure(metrics[runkeys.best(stage.name, by)])}"])
                    + ")")
        lines.append(f"- **{stage.name}**: {what}{best}")
    lines.append("The tables and figures of `bronchopose report` are the artifacts under `report/`.")
    return "\n".join(lines)


def record_parent(client, parent: str, walk: planning.StageWalk, *, finished: bool = False) -> None:
    """The plan (params) and selections (tags) on the sweep's parent run; with ``finished`` also the outcome.

    Best effort (a warning): the cells' runs and the claims table hold the results either way.
    """
    try:
        log_plan_params(client, parent, plan_params(walk))
        tags = selection_tags(walk)
        if finished:
            metrics, best = outcome(walk)
            log_metrics(client, parent, metrics)
            tags |= best | {TAG_NOTE: describe_sweep(walk, metrics, best)}
        set_tags(client, parent, tags)
    except Exception as exc:  # noqa: BLE001 - a summary must never turn a finished sweep into a failed one
        log.warning("could not record the sweep's plan on its parent run %s: %s", parent, exc)


# -- a study's parent -----------------------------------------------------------------------------------


def log_study(client, parent: str, info: Mapping[str, Any], n_finished: int) -> None:
    """What a reviewer reads on an Optuna study's parent run (``info``: ``tuning.studies.describe_study``).

    Trial counts (metrics ``trials.*``), the best trial (its objective's metric, ``val_best.loss`` by default; tags ``best_trial``,
    ``best_run`` and ``best.<path>`` = its value of each searched path), and parameter importances (metrics
    ``importance.<path>``, the figure ``param_importances.png``) only where they mean something: two or more
    searched parameters and complete trials (tag ``importances``: why not, or the caveat of few trials).
    """
    counts = {runkeys.trials(k): info["counts"].get(k, 0) for k in ("complete", "pruned", "fail")}
    log_metrics(client, parent, {runkeys.trials("finished"): n_finished, **counts})
    best = info["best"]
    if best is None:
        return
    log_metrics(client, parent, {info.get("objective", DEFAULT_OBJECTIVE): best["value"]}, step=best["number"])
    tags = {"best_trial": str(best["number"]), "best_run": best["run_id"],
            **{runkeys.best_value(k): str(v) for k, v in best["params"].items()}}
    note = importance_note(info)
    shown = info["importances"] if len(info["importances"]) > 1 else {}  # one parameter: 1 by definition
    if shown:
        log_metrics(client, parent, {runkeys.importance(k): v for k, v in shown.items()})
    if note:
        tags["importances"] = note
    tags[TAG_NOTE] = describe_study(info, n_finished, shown, note)
    set_tags(client, parent, {k: v for k, v in tags.items() if v})  # several `tune` processes may end together
    if shown:
        with tempfile.TemporaryDirectory(prefix="bronchopose-") as tmp:
            path = importance_figure(shown, info["counts"].get("complete", 0), note,
                                     Path(tmp) / "param_importances")
            client.log_artifact(parent, str(path))


def describe_study(info: Mapping[str, Any], n_finished: int, importances: Mapping[str, float], note: str) -> str:
    """The study parent's description (Markdown): trial counts, the best trial and its values, importances."""
    c, best = info["counts"], info["best"]
    values = ", ".join(f"`{k}` = {text_figure(v)}" if isinstance(v, float) else f"`{k}` = {v}"
                       for k, v in best["params"].items())
    ranked = ", ".join(f"`{k}` {text_figure(v)}" for k, v in sorted(importances.items(), key=lambda kv: -kv[1]))
    return "\n\n".join([
        f"Optuna study **{info['study']}**: {n_finished} finished trials ({c.get('complete', 0)} complete, "
        f"{c.get('pruned', 0)} pruned), {c.get('fail', 0)} failed; each trial is a nested run.",
        f"Best: trial #{best['number']}, {info.get('objective', DEFAULT_OBJECTIVE)} {text_figure(best['value'])}"
        + (f", with {values}" if values else "")
        + " (apply it with `--use-tuned`).",
        *([f"Importances: {ranked}" + (f" ({note})" if note else "") + "; figure `param_importances.png`."]
          if ranked else [f"Importances: {note}."] if note else []),
    ])


IMPORTANCE_MIN_TRIALS = 10  # fewer complete trials: importances are shown with a caveat


def importance_note(info: Mapping[str, Any]) -> str:
    """Why a study's parameter importances mean nothing yet, or the caveat they come with ("": none)."""
    n, params = info["counts"].get("complete", 0), len((info["best"] or {}).get("params", {}))
    if info.get("importances_note"):
        return f"unavailable: {info['importances_note']}"
    if params < 2:
        return "not computed: one searched parameter (its importance is 1 by definition)" if params == 1 else ""
    if n < 2:
        return "not computed: fewer than 2 complete trials"
    if n < IMPORTANCE_MIN_TRIALS:
        return (f"indicative only: {n} complete trials (Optuna's importance estimate is unreliable below "
                f"{IMPORTANCE_MIN_TRIALS})")
    return ""


def importance_figure(importances: Mapping[str, float], n_trials: int, note: str, stem: Path) -> Path:
    """A horizontal bar chart of the importances (largest on top), the trial count and any caveat in its title."""
    import matplotlib.pyplot as plt  # lazy: matplotlib only where a study's figure is drawn

    names = sorted(importances, key=importances.get)
    fig, ax = plt.subplots(figsize=(6, 0.5 * len(names) + 1.4))
    ax.barh(names, [importances[k] for k in names], color="#4c72b0")
    ax.set_xlabel("importance (Optuna's default evaluator, normalised to sum to 1)")
    ax.set_title(f"parameter importances, {n_trials} complete trials" + (f"\n{note}" if note else ""), fontsize=9)
    return save_figure(fig, stem, ("png",))[0]
