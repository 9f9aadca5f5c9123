"""What a sweep looks like: the plan table, the live progress view, and ``bronchopose status``'s report.

Everything here reads the claims table (and, for metrics, the MLflow runs the
rows point at); nothing writes.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from rich import box
from rich.console import Console, Group
from rich.progress_bar import ProgressBar
from rich.table import Table
from rich.text import Text

from .. import cells, runkeys
from ..config import Config
from ..errors import BronchoError
from ..io import fmt_bytes, folder_bytes
from ..runs.client import ExperimentDeleted, client_for, redacted_uri, store_missing
from ..runs.parents import KIND_SWEEP, find_parent
from ..runs.records import deleted_runs_line, run_name
from ..runs.views import DAGGER
from .housekeeping import Checkpoint, inventory
from .plan import Plan, StageWalk, read_plan, source_of
from .record import deleted_finished, missing_line, missing_runs, overlay, rebuilt_count
from .selection import describe_selection
from .summary import TAG_STOPPED
from .damage import damage_line, future_line, future_s
from .storage import FAILED, FINISHED, PENDING, RUNNING, CellRow, SweepStore
from .tuning.rows import TRIALS_SUFFIX
from .launchers import names as launcher_names
from .launchers import launcher_class
from .launchers.base import words
from .worker import WorkerId, job_of

log = logging.getLogger(__name__)

# What status shows per finished cell, as the UI's headline view: the position ratio to the training mean and the
# skill against the better reference, per pair and accumulated (the paper's headline), † where it does not beat it
HEADLINE_COLUMNS = {"pair ratio": runkeys.ratio("pos_l2"), "pair skill": runkeys.skill("pos_l2"),
                    "acc ratio": runkeys.ratio("pos_l2", "acc"), "acc skill": runkeys.skill("pos_l2", "acc")}
TRIAL_VALUE = runkeys.best_of(runkeys.VAL_LOSS)  # shown for a study's trial rows (``tuning.rows``)
STYLE = {FINISHED: "green", RUNNING: "cyan", FAILED: "red", PENDING: "dim"}


def fmt_duration(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    s = int(round(seconds))
    if s < 60:
        return f"{seconds:.1f}s" if seconds < 10 else f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s % 3600 // 60:02d}m"


def is_stale(row: CellRow | None, now: float | None, stale_after_s: float | None) -> bool:
    """A running cell whose worker sent no heartbeat for ``stale_after_s`` (database clock ``now``): dead,
    its cell waits for the next worker to take it over (and resume its checkpoint)."""
    return (row is not None and row.state == RUNNING and now is not None and stale_after_s is not None
            and (row.heartbeat is None or row.heartbeat < now - stale_after_s))


@dataclass
class Progress:
    total: int
    finished: int
    running: int  # held by a live worker (stale ones are counted in ``stale``, not here)
    failed: int  # failed for good (no retry left)
    pending: int  # includes failed cells that will be retried
    mean_s: float | None  # mean runner time of finished cells
    eta_s: float | None
    stale: int = 0  # running cells whose worker is dead (no heartbeat for sweep.stale_after_s)
    damaged: int = 0  # rows set aside as damaged (``damage.py``): neither run nor waited for


def progress(plan: Plan, max_retries: int, workers: int, now: float | None = None,
             stale_after_s: float | None = None) -> Progress:
    every = [plan.rows.get(c.key) for c in plan.cells]
    rows = [r for r in every if r is None or r.damage is None]
    fin = [r for r in rows if r and r.state == FINISHED]
    stale = sum(1 for r in rows if is_stale(r, now, stale_after_s))
    running = sum(1 for r in rows if r and r.state == RUNNING) - stale
    failed = sum(1 for r in rows if r and r.state == FAILED and not r.retryable(max_retries))
    pending = len(rows) - len(fin) - running - stale - failed
    durations = [r.duration_s for r in fin if r.duration_s is not None]
    mean = sum(durations) / len(durations) if durations else None
    eta = None if mean is None else mean * (pending + running + stale) / max(1, workers)
    return Progress(len(every), len(fin), running, failed, pending, mean, eta, stale, len(every) - len(rows))


def summary_line(p: Progress) -> Text:
    t = Text()
    t.append(f"done {p.finished}/{p.total}", style="bold green")
    t.append(f"  running {p.running}", style="cyan")
    if p.stale:
        t.append(f"  stale {p.stale}", style="yellow")
    t.append(f"  failed {p.failed}", style="red" if p.failed else "")
    t.append(f"  pending {p.pending}", style="dim")
    if p.damaged:
        t.append(f"  damaged {p.damaged}", style="red")
    if p.finished and p.mean_s is not None:
        t.append(f"  ~{fmt_duration(p.mean_s)}/cell")
    if p.eta_s is not None and (p.pending or p.running):
        t.append(f"  ETA {fmt_duration(p.eta_s)}", style="bold")
    return t


def wide(console: Console) -> Console:
    """Piped output is not cut to 80 columns: run ids and cell labels stay whole for grep and logs."""
    return console if console.is_terminal else Console(width=max(console.width, 200), file=console.file,
                                                       no_color=console.no_color)


def plan_table(plan: Plan, max_retries: int, title: str = "") -> Table:
    heading = f"sweep {plan.sweep}" + (f", {title}" if title else "") + f": {len(plan.cells)} cells"
    table = Table(title=heading, title_justify="left", box=box.SIMPLE_HEAD)
    for col in ("#", "cell", "key", "state", "attempts"):
        table.add_column(col, justify="right" if col in ("#", "attempts") else "left",
                         no_wrap=col != "cell", overflow="ellipsis" if col == "cell" else "fold")
    for i, cell in enumerate(plan.cells, 1):
        row = plan.rows.get(cell.key)
        state = _state_label(row, max_retries)
        table.add_row(str(i), cell.label, cell.key, Text(state, style=STYLE.get(row.state if row else PENDING, "")),
                      str(row.attempts if row else 0))
    return table


def _state_label(row: CellRow | None, max_retries: int, now: float | None = None,
                 stale_after_s: float | None = None) -> str:
    if row is None:
        return "new"
    if row.damage is not None:
        return f"damaged ({str(row.state)[:20]})"
    if is_stale(row, now, stale_after_s):
        return "stale (worker lost, no heartbeat)"
    if row.state == FAILED and row.retryable(max_retries):
        return "failed (will retry)"
    return row.state


def live_view(plan: Plan, max_retries: int, workers: int, now: float | None = None) -> Group:
    """The parent's live status: summary, a bar, and what each worker is running."""
    p = progress(plan, max_retries, workers)
    bar = ProgressBar(total=max(1, p.total), completed=p.finished + p.failed, width=50)
    running = Table(box=None, show_header=False, padding=(0, 1))
    now = now if now is not None else time.time()
    for cell in plan.cells:
        row = plan.rows.get(cell.key)
        if row and row.state == RUNNING:
            since = fmt_duration(now - row.claimed_at) if row.claimed_at else "-"
            running.add_row(Text("▶", style="cyan"), cell.label, row.worker or "", since)
    return Group(summary_line(p), bar, *([running] if running.row_count else []))


def fetch_metrics(cfg: Config, run_ids: Sequence[str]) -> dict[str, dict[str, Any]]:
    """Headline metrics and timing of each MLflow run (missing runs are skipped)."""
    if not run_ids or store_missing(cfg):  # a mistyped runs.uri: rows without metrics, no empty store made
        return {}
    client = client_for(cfg, reading=True)
    out: dict[str, dict[str, Any]] = {}
    for run_id in run_ids:
        try:
            run = client.get_run(run_id)
        except Exception:  # noqa: BLE001 - a run deleted or a store moved: show the row without metrics
            continue
        info = run.info
        out[run_id] = {
            "status": info.status,
            "duration_s": (info.end_time - info.start_time) / 1000 if info.end_time and info.start_time else None,
            "pairs_seen": run.data.metrics.get(runkeys.train("pairs_seen")),  # logged at every validation
            **{k: run.data.metrics.get(k) for k in (*HEADLINE_COLUMNS.values(), runkeys.HEADLINE, TRIAL_VALUE)},
        }
    return out


def status_table(plan: Plan, metrics: dict[str, dict[str, Any]], max_retries: int, budget_pairs: int | None = None,
                 now: float | None = None, ckpt_bytes: dict[str, int] | None = None,
                 stale_after_s: float | None = None) -> Table:
    """One row per cell. A running cell's duration is the time since it was claimed, with the share of its
    training budget (``budget_pairs`` image pairs) done at its last validation; ``ckpt_bytes`` (run id ->
    bytes of its checkpoint folder on this machine) adds a checkpoint column. With ``stale_after_s`` (and
    ``now`` on the database's clock) a running cell without a heartbeat that long shows as stale."""
    now = now if now is not None else time.time()
    table = Table(title=f"sweep {plan.sweep}", title_justify="left", box=box.SIMPLE_HEAD)
    launchers = sorted({w.launcher for r in plan.rows.values() if (w := WorkerId.parse(r.worker)) and w.job})
    with_jobs = bool(launchers)  # workers with a job of their launcher (a Slurm array task)
    trials = any(isinstance(c, cells.TrialCell) for c in plan.cells)  # a study's rows: each trial's value too
    cols = (("cell", "left"), ("state", "left"), ("tries", "right"), ("MLflow run", "left"), ("worker", "left"),
            *(((f"{'/'.join(_title(n) for n in launchers)} task", "left"),) if with_jobs else ()), ("duration", "right"),
            *((name, "right") for name in HEADLINE_COLUMNS), *(((TRIAL_VALUE, "right"),) if trials else ()))
    for col, just in cols:
        table.add_column(col, justify=just, no_wrap=col != "cell", overflow="ellipsis" if col == "cell" else "fold")
    if ckpt_bytes is not None:
        table.add_column("checkpoint", justify="right", no_wrap=True)
    for cell in plan.cells:
        row = plan.rows.get(cell.key)
        m = metrics.get(row.run_id, {}) if row and row.run_id else {}
        dur = m.get("duration_s") if row and row.state == FINISHED else None
        dur = row.duration_s if dur is None and row else dur
        shown = fmt_duration(dur)
        stale = is_stale(row, now, stale_after_s)
        if row and row.state == RUNNING and row.claimed_at and not stale:
            shown = fmt_duration(now - row.claimed_at)
            if budget_pairs and m.get("pairs_seen") is not None:
                shown += f", {min(1.0, m['pairs_seen'] / budget_pairs):.0%} trained"
        values = [
            _name(cell), Text(_state_label(row, max_retries, now, stale_after_s),
                             style="yellow" if stale else STYLE.get(row.state if row else PENDING, "")),
            str(row.attempts if row else 0), (row.run_id or "-") if row else "-",
            (row.worker or "-") if row and row.state == RUNNING else "",
            *(((job_of(row.worker) if row and row.state in (RUNNING, FINISHED, FAILED) else None) or "",)
              if with_jobs else ()),
            shown, *(_headline(name, m.get(key)) for name, key in HEADLINE_COLUMNS.items()),
            *((_num(m.get(TRIAL_VALUE)),) if trials else ()),
        ]
        if ckpt_bytes is not None:
            size = ckpt_bytes.get(row.run_id) if row and row.run_id else None
            values.append(fmt_bytes(size) if size is not None else "-")
        table.add_row(*values)
    return table


def _name(cell: cells.Cell) -> str:
    """A cell as ``status`` shows it: its run's name (records.run_name: model, loss and seed first), a study's
    trial slot before it."""
    name = run_name(cell)
    return f"trial {cell.trial} · {name}" if isinstance(cell, cells.TrialCell) else name


def _title(launcher: str | None) -> str:
    """How messages name a launcher ("Slurm"); a name no longer registered as it is."""
    return words(launcher_class(launcher))[0] if launcher in launcher_names() else str(launcher)


def _num(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


def _headline(column: str, v: float | None) -> str:
    """A headline figure at 4 significant digits, as the UI shows it; a skill that does not beat the better
    image-blind reference (<= 0) marked † (views.DAGGER)."""
    if v is None:
        return "-"
    return f"{v:.4g}" + (f" {DAGGER}" if column.endswith("skill") and not v > 0 else "")


def failures(plan: Plan) -> list[tuple[str, str]]:
    return [(c.label, plan.rows[c.key].failure_reason or "unknown") for c in plan.cells
            if c.key in plan.rows and plan.rows[c.key].state == FAILED]


def _stored_plan(store: SweepStore, name: str) -> tuple[Plan, list[CellRow]]:
    """The stored cells of sweep ``name``, and the rows that name no cell (damaged: shown as lines only)."""
    rows = store.rows(name) if store.exists() else []
    if not rows:
        known = ", ".join(store.sweeps()) if store.exists() else ""
        raise BronchoError(f"--sweep {name}: no such sweep in storage {store.redacted} (stored: {known or 'none'})")
    stored, unnamed = [], []
    for r in rows:
        try:
            stored.append(cells.make(**r.coords, key=r.cell_key))
        except (BronchoError, TypeError) as exc:  # coords that name no cell: set aside like any damaged row
            unnamed.append(replace(r, damage=r.damage or f"coords name no cell ({exc})"))
    return Plan(name, stored, {r.cell_key: r for r in rows if r not in unnamed}), unnamed


@dataclass(frozen=True)
class CellOutcome:
    """One cell of a sweep as ``status`` shows it: its claims row (MLflow's view overlaid) and its run's metrics."""

    label: str
    key: str
    state: str  # pending, running, finished or failed (the claims row's; no row: pending)
    attempts: int
    run_id: str | None
    failure_reason: str | None
    metrics: dict[str, Any]  # the run's status, duration_s, pairs_seen and headline errors (fetch_metrics)

    @property
    def headline(self) -> float | None:
        """The run's headline (runkeys.HEADLINE: pair position error ÷ the training mean's), where logged."""
        return self.metrics.get(runkeys.HEADLINE)


@dataclass
class SweepState:
    """What ``bronchopose status`` knows about a sweep: its plan with the claims rows (MLflow's view overlaid),
    each run's metrics, the checkpoints held here, and the lines it says before and after the table."""

    cfg: Config
    plan: Plan
    metrics: dict[str, dict[str, Any]]
    held: list[Checkpoint]
    now: float | None  # the database's clock (heartbeats are on it)
    before: list[str]  # rich-markup lines printed before the table
    after: list[str]

    def cells(self) -> list[CellOutcome]:
        out = []
        for c in self.plan.cells:
            row = self.plan.rows.get(c.key)
            out.append(CellOutcome(c.label, c.key, row.state if row else PENDING, row.attempts if row else 0,
                                   row.run_id if row else None, row.failure_reason if row else None,
                                   dict(self.metrics.get(row.run_id, {})) if row and row.run_id else {}))
        return out


def sweep_state(cfg: Config, store: SweepStore, name: str, show_all: bool) -> SweepState:
    """The state of sweep ``name``: the config's plan (or, with ``show_all`` or another name, every stored cell)."""
    before: list[str] = []
    if not store.exists():
        before.append(f"no claims table in storage {store.redacted} (new, or lost): cells FINISHED in MLflow are "
                      "shown finished and the next sweep records them there")
        if name != cfg.name:
            return SweepState(cfg, Plan(name, [], {}), {}, [], None, before, [])
    unnamed: list[CellRow] = []
    if show_all or name != cfg.name:
        plan, unnamed = _stored_plan(store, name)
    else:
        walk = StageWalk(cfg, store)
        for sp in walk.plans():
            if sp.selection is not None:
                before.append(describe_selection(sp.selection))
            elif sp.cells is None:
                before.append(f"stage {sp.stage.name}: waits for stage {source_of(cfg, sp.stage).name}")
        plan = read_plan(store, name, walk.known_cells())
        stale = len(store.rows(name)) - len(plan.rows) if store.exists() else 0
        if stale > 0:
            before.append(f"[dim]{stale} stored cell(s) of sweep {name} belong to another version of the config "
                          f"(--all shows them)[/]")
    try:
        deleted = deleted_finished(cfg, plan.sweep, plan.rows)  # runs deleted by hand: their cells are not done
    except ExperimentDeleted:
        raise
    except Exception as exc:  # noqa: BLE001 - a view: an MLflow store away shows the claims table alone
        log.warning("could not read MLflow's deleted runs: %s", exc)
        deleted = {}
    if deleted:
        before.append(f"[yellow]deleted[/] {deleted_runs_line(len(deleted), plan.sweep, cfg.experiment_name)}: "
                      "shown pending")
    rows, known = overlay(cfg, plan.sweep, plan.cells, plan.rows, deleted)
    if known:
        before.append(f"{known} cell(s) FINISHED in MLflow but not in the claims table: shown finished (never "
                      "trained again; the next sweep records them there)")
    plan = Plan(plan.sweep, plan.cells, rows)
    rebuilt = rebuilt_count(rows) - known
    if rebuilt > 0:
        before.append(f"{rebuilt} cell(s) recorded from their FINISHED MLflow runs: the claims table was rebuilt "
                      "from MLflow (new, lost, or behind)")
    with_runs = [plan.rows[c.key].run_id for c in plan.cells if c.key in plan.rows and plan.rows[c.key].run_id]
    missing = set(missing_runs(cfg, with_runs))
    held = inventory(cfg, store if store.exists() else None)
    now = store.db_now() if store.exists() else None
    after = [summary_line(progress(plan, cfg.sweep.max_retries, 1, now, cfg.sweep.stale_after_s)).markup]
    after += [f"[red]failed[/] {label}: {reason}" for label, reason in failures(plan)]
    if (line := stopped_line(cfg, plan.sweep)) is not None:
        after.append(f"[yellow]stopped[/] {line}")
    after += [f"[yellow]given back[/] {label}: {reason}" for label, reason in given_back(plan)]
    after += list(row_lines(plan, unnamed, store.redacted, now, cfg.sweep.stale_after_s))
    after += [f"[yellow]missing[/] {missing_line(row, redacted_uri(cfg))}" for c in plan.cells
              if (row := plan.rows.get(c.key)) is not None and row.run_id in missing]
    after += [checkpoint_line(held), disk_line(cfg)]
    if name == cfg.name and store.exists():
        after += study_lines(store)
    return SweepState(cfg, plan, fetch_metrics(cfg, with_runs), held, now, before, after)


def study_lines(store: SweepStore) -> list[str]:
    """A line per tuning study whose trial rows the claims table holds (``tuning.rows``): how to see them."""
    out = []
    for sweep in (s for s in store.sweeps() if s.endswith(TRIALS_SUFFIX)):
        states = [r.state for r in store.rows(sweep)]
        counts = ", ".join(f"{states.count(st)} {st}" for st in (FINISHED, RUNNING, FAILED, PENDING) if st in states)
        out.append(f"[dim]study {sweep.removesuffix(TRIALS_SUFFIX)}: {len(states)} trial row(s) ({counts}); "
                   f"`bronchopose status --sweep {sweep}` lists them[/]")
    return out


def show_status(cfg: Config, store: SweepStore, name: str, show_all: bool, console: Console) -> SweepState:
    """``bronchopose status``: the plan's cells (or every stored cell) with state, run, duration, metrics; returns
    what it showed."""
    state = sweep_state(cfg, store, name, show_all)
    for line in state.before:
        console.print(line, highlight=False, soft_wrap=True)
    if not store.exists() and name != cfg.name:
        return state
    console.print(status_table(state.plan, state.metrics, cfg.sweep.max_retries,
                               cfg.train.steps * cfg.train.pairs_per_step, now=state.now,
                               ckpt_bytes={c.run_id: c.bytes for c in state.held},
                               stale_after_s=cfg.sweep.stale_after_s))
    for line in state.after:
        console.print(line, highlight=False, soft_wrap=True)
    return state


def stopped_line(cfg: Config, sweep: str) -> str | None:
    """One line when the sweep's parent run was ended by its last worker with cells not done (its workers were
    stopped outside bronchopose: ``stagework.settle_parent``): which run, how it ended, why, what to do."""
    try:
        if store_missing(cfg):
            return None
        client = client_for(cfg, reading=True)
        exp = client.get_experiment_by_name(cfg.experiment_name)
        parent = find_parent(client, exp.experiment_id, KIND_SWEEP, sweep) if exp is not None else None
        run = client.get_run(parent) if parent is not None else None
    except Exception as exc:  # noqa: BLE001 - a view: an MLflow store away shows the claims table alone
        log.warning("could not read the sweep's parent run: %s", exc)
        return None
    if run is None or run.info.status == "RUNNING" or not (reason := run.data.tags.get(TAG_STOPPED)):
        return None
    return f"sweep {sweep}: its parent run {parent} ended {run.info.status}: {reason}"


def row_lines(plan: Plan, unnamed: Sequence[CellRow], where: str, now: float | None,
              stale_after_s: float) -> list[str]:
    """A line per claims row that is not as this code writes it: damaged (set aside), a heartbeat from the
    future, a worker id of another form (``damage.py``)."""
    out = [f"[red]damaged[/] {damage_line(r, where)}" for r in [*plan.damaged(), *unnamed]]
    for c in plan.cells:
        row = plan.rows.get(c.key)
        if row is None or row.damage is not None:
            continue
        if (ahead := future_s(row, now)) is not None:
            out.append(f"[yellow]clock[/] {future_line(row, ahead, stale_after_s)}")
        if row.state == RUNNING and row.worker and WorkerId.parse(row.worker) is None:
            out.append(f"[yellow]foreign[/] claims row {row.sweep}/{row.cell_key} ({row.label}): worker "
                       f"{row.worker[:80]!r} is not this project's form (host:pid [launcher job] [gpuN]); the "
                       f"claim is honoured while its heartbeat is fresh and taken over once it is "
                       f"sweep.stale_after_s ({stale_after_s:g} s) old; `bronchopose status --repair` does not "
                       "touch it")
    return out


def given_back(plan: Plan) -> list[tuple[str, str]]:
    """Pending cells that carry a reason: released by a worker (e.g. the MLflow database was busy)."""
    return [(c.label, plan.rows[c.key].failure_reason) for c in plan.cells
            if c.key in plan.rows and plan.rows[c.key].state == PENDING and plan.rows[c.key].failure_reason]


def checkpoint_line(held: Sequence[Checkpoint]) -> str:
    """One line: checkpoint folders on this machine, their total, and what no live cell needs."""
    if not held:
        return "checkpoints: none on this machine"
    spare = [c for c in held if not c.needed]
    waste = sum(c.bytes for c in spare) + sum(c.waste for c in held)
    text = f"checkpoints: {len(held)} folder(s), {fmt_bytes(sum(c.bytes for c in held))} in all"
    if waste:
        text += (f"; {fmt_bytes(waste)} ({len(spare)} folder(s)) needed by no live cell: "
                 "`bronchopose sweep gc` frees it")
    return text


def disk_line(cfg: Config) -> str:
    """One line: the size of this machine's local stores (docs/sweep.md, "Disk")."""
    folders = (("MLflow artifacts", cfg.paths.artifacts), ("checkpoints", cfg.paths.checkpoints),
               ("frame caches", cfg.paths.cache))
    return "disk: " + ", ".join(f"{name} {fmt_bytes(folder_bytes(path) if path.is_dir() else None)} "
                                f"({_short(path)})" for name, path in folders)


def _short(path: Path) -> str:
    try:
        return str(path.relative_to(Path.cwd()))
    except ValueError:
        return str(path)
