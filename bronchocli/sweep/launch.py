"""``bronchopose sweep run`` with any launcher: the one driver. Prepare the shared state, print the plan,
submit what the launcher's queued and running workers do not cover, and (unless ``--detach``) watch the table
until they are gone, moving on to the next stage and topping up when workers ended with cells left; ``cancel``
stops them. The launcher is the protocol (``launchers.base``); nothing here names one. ``drive`` (submit, then
watch) is the part that does not know the sweep's parent run: ``tune`` drives a study's trial rows through it.

A worker works the stages up to the one it was submitted for (``STAGE_ENV``), never a later one, so each
stage counts the workers labelled with it. What depends on where the workers live is the launcher's ``Session``
(``sweep.session``), made once per command and asked unconditionally: which stages to submit now (a batch
system's: all, later ones waiting for the earlier ones; the local launcher's: one at a time), what to re-read on
a refresh, whether workers that ended with cells left are replaced, how the parent run is held and what Ctrl-C
does (the local launcher's stops its workers in the session's block; a detached one's stops the watch only).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

from rich.console import Console
from rich.live import Live

from .. import interrupts, urls
from ..cells import Selection
from ..config import Config, Stage
from ..errors import DEBUG_HINT, BronchoError
from ..runs.client import client_for, experiment_id
from ..runs.parents import set_parent_status, sweep_parent
from ..runs.contract import failure_reason
from ..runs.records import TAG_FAILURE, set_tags
from . import summary
from .launchers import reference
from .launchers.base import Launcher, Workers, job_order, state_of, submission_id, words
from .plan import Plan, Step, StageWalk, cells_left, claimable_now, ensure_rows, prepare_walk, read_plan
from .session import Session
from .planview import final, print_plan, report_workers, stage_title, waits_line
from .selection import describe_selection
from .status import live_view, progress, summary_line
from .storage import RUNNING, SweepStore
from .worker import EXIT_INTERRUPTED, job_of

log = logging.getLogger(__name__)

CANCEL_CHECK_S = 10.0  # how often a watch asks whether the sweep was cancelled while its workers run


def runnable_now(walk: StageWalk, stage: Stage, active: Sequence[Workers]) -> int:
    """Cells of ``stage`` workers can work on now: claimable ones (pending, retryable, a dead worker's once its
    claim is stale) plus those held by a live worker. A cell whose worker is gone but whose claim is not stale yet
    counts only once it goes stale: a worker submitted earlier would find nothing to claim and exit."""
    cfg = walk.cfg
    plan = read_plan(walk.store, walk.sweep, walk.cells(stage) or [])
    claimable = claimable_now(plan, cfg.sweep.max_retries, walk.store.db_now(), cfg.sweep.stale_after_s)
    live = {t.id for t in active}
    held = sum(1 for c in plan.cells if c.key not in claimable and (r := plan.rows.get(c.key)) is not None
               and r.state == RUNNING and ((job := job_of(r.worker)) is None or job in live))
    return len(claimable) + held


def print_stage(walk: StageWalk, stage: Stage, console: Console) -> None:
    """A stage's cells with their state and counts (``sweep plan``'s table)."""
    cells = walk.cells(stage)
    if cells:
        print_plan(console, read_plan(walk.store, walk.sweep, cells), walk.cfg, None,
                   stage_title(stage, len(walk.stages)), walk.store)


@dataclass
class Submitted:
    """What this command's submissions found: the stages it submitted workers for, and the stage that waits (cells
    of its source are not done: excluded by ``--only``, or running elsewhere), if the last walk stopped there."""

    stages: list[str] = field(default_factory=list)
    waiting: Step | None = None


def _steps(walk: StageWalk, console: Console, record: Submitted) -> Iterator[Step]:
    """The walk's steps as they are taken: each stage whose source is done settled (and printed); the stage that
    waits recorded (``record.waiting``), not given."""
    record.waiting = None
    for step in walk.steps():
        if step.settled is not None:
            console.print(describe_selection(step.settled), highlight=False)
            ensure_rows(walk.cfg, walk.store, walk.cells(step.stage, mine=False) or [], sweep=walk.sweep)
            print_stage(walk, step.stage, console)
        if step.waits:
            record.waiting = step
        else:
            yield step


def _submit(launcher: Launcher, n: int, stage: str, after: Sequence[str]) -> str:
    """``launcher.submit``: the submission's id; any exception of the launcher's own code is one line naming it
    (``--debug``: its traceback), which the sweep's parent run ends FAILED with (``launch``)."""
    try:
        job = launcher.submit(n, stage, after)
    except BronchoError:
        raise
    except Exception as exc:  # noqa: BLE001 - a plugin's submission may raise anything: one line naming it
        raise BronchoError(f"launcher {launcher.name}: submitting {n} worker(s) for stage {stage} failed: "
                           f"{failure_reason(exc)}{DEBUG_HINT}") from exc
    return submission_id(launcher, job)


def submit_missing(walk: StageWalk, launcher: Launcher, console: Console, record: Submitted | None = None, *,
                   session: Session | None = None) -> list[str]:
    """Submit workers for what the queued/running ones will not cover; returns the new submissions (none: covered);
    ``record`` gets the stage of each, and the stage that waits.

    The first stage with cells left wants a worker per cell runnable now (``runnable_now``, at most
    ``launcher.capacity``); a later stage's submission waits (``after``) for the ones before it, and one queued
    for a later stage is made to wait for an earlier stage's new submission too (``session.follow``). Which
    stages are sized now is the session's answer (``Session.to_submit``; ``session``: the command's, else a new
    one)."""
    session = session or launcher.Session(launcher)
    record = record if record is not None else Submitted()
    # Workers being stopped (scancel: COMPLETING until their processes are gone) claim nothing more: not cover.
    active = [t for t in launcher.active() if not t.ending]
    submitted: list[str] = []
    earlier: list[str] = []  # submissions labelled with an earlier stage (queued, running or just submitted)
    first = True
    for stage, left in session.to_submit(walk, _steps(walk, console, record)):
        mine = [t for t in active if t.stage == stage.name]
        if submitted and (queued := sorted({t.job for t in mine if t.state == "PENDING"}, key=job_order)):
            session.follow(queued, earlier)
        if left:
            have = sum(t.count for t in mine)
            if first:
                want = launcher.capacity(runnable_now(walk, stage, active))
                if not want and not have:  # only cells of dead workers whose claims are not stale yet: wait
                    break
            else:
                want = launcher.capacity(left)
            if want > have:
                job = _submit(launcher, want - have, stage.name, () if first else earlier)
                console.print(session.submitted(job, want - have, stage.name, () if first else earlier),
                              highlight=False)
                submitted.append(job)
                earlier.append(job)
                record.stages.append(stage.name)
            first = False
        earlier += sorted({t.job for t in mine} - set(earlier), key=job_order)
    return submitted


def launch(cfg: Config, store: SweepStore, only: Selection, launcher: Launcher, *, detach: bool,
           console: Console, retry_failed: bool = False) -> int:
    """``bronchopose sweep run``: prepare the shared state, print the plan, submit workers for what is missing, and
    (unless ``detach``) watch the table until the sweep's workers are gone; exit code 0 (every cell FINISHED), 1
    (some FAILED, or workers gone with cells left), 130 (stopped). The caller has checked once what would refuse
    the sweep (``entry.run``: paths, ``launcher.check()``, the storage answering) before anything was created.

    The sweep's parent MLflow run (its cells nest under it) is RUNNING while the sweep runs, with the plan and
    its selections; when the watch ends, the outcome (``summary.record_parent``). The session holds it
    (``Session.open_parent``): workers that die with this command make it this process's, which ``status
    --repair`` ends if the command is killed."""
    console.print(f"[bold]sweep[/] {cfg.name} {launcher.describe()}  storage {store.redacted}  MLflow "
                  f"{urls.redact(cfg.paths.mlflow_uri)}  experiment {cfg.experiment_name}"
                  + (f"  hyperparameters {cfg.tune.applied}" if cfg.tune.applied else ""), highlight=False)
    walk, _ = prepare_walk(cfg, store, only, retry_failed=retry_failed)
    client = client_for(cfg)
    parent = sweep_parent(client, cfg, experiment_id(client, cfg))  # the cells nest under it
    session = launcher.Session(launcher)
    session.open_parent(client, parent)
    set_tags(client, parent, {summary.TAG_LAUNCHER: reference(type(launcher)),  # `status` can ask its workers
                              summary.TAG_WATCHER: summary.watcher_tag(detach)})
    summary.uncancel(client, parent)  # an explicit run: a `sweep cancel` before it no longer holds
    code: int | None = None
    try:
        code = drive(walk, launcher, console, detach=detach, session=session,
                     cancelled=lambda: summary.cancelled(client, parent),
                     resubmitted=lambda: summary.reopen(client, parent),  # a top-up after its last worker stopped it
                     submitted=lambda: summary.record_parent(client, parent, walk))  # the plan on the parent run
        return code
    except Exception as exc:  # a submission that failed (or the watch): the parent run ends FAILED, saying why
        try:
            client.set_tag(parent, TAG_FAILURE, failure_reason(exc))
        except Exception as tag_exc:  # noqa: BLE001 - the command's own error is what matters
            log.warning("could not record on the sweep's parent run why it failed: %s", tag_exc)
        set_parent_status(client, parent, 1)
        raise
    finally:
        if not detach and (code is not None or session.stopped):
            code = 1 if code is None else code  # this command failed: its workers were stopped
            summary.record_parent(client, parent, walk, finished=True)
            if code != EXIT_INTERRUPTED or session.stopped:  # stopped watching only: the workers go on
                set_parent_status(client, parent, code)  # the sweep's parent run ends FINISHED, FAILED or KILLED


def interrupted_line(then: str) -> str:
    """``interrupted: SIGTERM received (scancel, requeue or preemption); <then>``: the signal that stopped the
    command, by name and what sends it (a worker that stopped on its own: said so)."""
    last = interrupts.last()
    if last is None:
        return f"[bold yellow]interrupted:[/] a worker was stopped; {then}"
    meaning = interrupts.meaning(last)
    return f"[bold yellow]interrupted:[/] {interrupts.name(last)} received{f' ({meaning})' if meaning else ''}; {then}"


def drive(walk: StageWalk, launcher: Launcher, console: Console, *, detach: bool, cancelled: Callable[[], bool],
          resubmitted: Callable[[], object] = lambda: None, submitted: Callable[[], object] = lambda: None,
          cancel_hint: str = "`bronchopose sweep cancel`", resume_hint: str = "`bronchopose sweep run`",
          what: str | None = None, session: Session | None = None) -> int:
    """Inside the launcher's session (``session``, else a new one): print the stages, submit workers for what is
    missing (then ``submitted``), and unless ``detach`` (0 once submitted) watch until they are gone (``watch``'s
    exit code). ``walk``: a sweep's ``StageWalk``, or anything walked alike (a study's trial rows:
    ``tuning.launch.StudyWalk``)."""
    session = session or launcher.Session(launcher)
    with session:  # the local launcher's Ctrl-C stops its workers; a failure stops them first
        for stage in walk.stages:
            print_stage(walk, stage, console)
        record = Submitted()
        if not submit_missing(walk, launcher, console, record, session=session):
            tasks = launcher.active()
            console.print(f"nothing new to submit: {sum(t.count for t in tasks)} {words(type(launcher))[2]}(s) of "
                          "this sweep queued or running" if tasks else "nothing left to run")
        submitted()
        if detach:
            console.print(f"detached: `bronchopose status` shows progress, {cancel_hint} stops the workers")
            return 0
        return watch(walk, launcher, console, cancelled, resubmitted, record,
                     (what or f"sweep {walk.sweep}", cancel_hint, resume_hint), session=session)


def cancel(launcher: Launcher, console: Console, *, dry_run: bool = False) -> int:
    """``bronchopose sweep cancel``: stop every worker of this sweep (running ones release their cells);
    ``dry_run``: only list them, each job with its state, workers and logs."""
    cfg, what = launcher.cfg, f"{words(type(launcher))[0]} job"
    jobs = launcher.cancel(dry_run=dry_run)
    ids = ", ".join(j.id for j in jobs)
    if not jobs:
        console.print(f"no {what} of sweep {cfg.name} is queued or running")
    elif dry_run:
        console.print(f"dry run: would cancel {what}(s) {ids} of sweep {cfg.name}; nothing cancelled")
        for job in jobs:
            logs, workers = job.logs(), job.workers()  # one listing of its workers for both figures
            n = sum(w.count for w in workers)
            console.print(f"  {job.id}: {state_of(workers)}, {n} {words(type(launcher))[2]}(s)"
                          + (f", logs {', '.join(str(p) for p in logs)}" if logs else ""), highlight=False,
                          soft_wrap=True)
    else:
        console.print(f"cancelled {what}(s) {ids} of sweep {cfg.name}: running cells are released "
                      "(their runs resume from the checkpoint when the sweep is run again)")
    return 0


def _table_state(plan: Plan, claimable: set[str]) -> tuple:
    """What changes whenever a worker claims, releases, finishes or fails a cell (row versions), or a dead
    worker's claim goes stale (the cells claimable now)."""
    return tuple(sorted((k, r.version) for k, r in plan.rows.items())), tuple(sorted(claimable))


def _open_stage(walk: StageWalk, plan: Plan, retries: int) -> str | None:
    """The first stage with cells left (or not known yet), by the rows of ``plan``; None: every stage is done."""
    for stage in walk.stages:
        cells = walk.cells(stage)
        if cells is None or cells_left(Plan(plan.sweep, cells, plan.rows), retries):
            return stage.name
    return None


def watch(walk: StageWalk, launcher: Launcher, console: Console, cancelled: Callable[[], bool] = lambda: False,
          resubmitted: Callable[[], object] = lambda: None, record: Submitted | None = None,
          hints: tuple[str, str, str] | None = None, *, session: Session | None = None) -> int:
    """The live view of the table while the sweep's workers run (``session.tick`` on every refresh: Slurm starts
    requeued tasks without its hold). When none is left: the next stage's workers once a stage is done; a top-up
    when workers ended with cells left (unless ``session.gives_up``) but progress was made since the last
    submission (a cancelled worker's released cell), waiting for a dead worker's claim to go stale first (a worker
    submitted before would find nothing to claim), then ``resubmitted`` (the parent RUNNING again). Workers
    stopped by this command (``session.stopped``) end it with 130; Ctrl-C is the session's
    (``session.interrupted``). ``session``: the command's (``drive``'s), else a new one."""
    session = session or launcher.Session(launcher)
    cfg = walk.cfg
    retries, stale_s = cfg.sweep.max_retries, cfg.sweep.stale_after_s
    record = record if record is not None else Submitted()  # what this command submitted, what waits
    live = Live(console=console, refresh_per_second=2) if console.is_terminal else None
    title, _, task_word = words(type(launcher))
    last_line, plan, asked = "", session.rows(walk), time.monotonic()
    seen_at_submit = _table_state(plan, claimable_now(plan, retries, walk.store.db_now(), stale_s))
    if live is not None:
        live.start()
    try:
        while True:
            try:
                plan, now = session.rows(walk), walk.store.db_now()
                tasks = launcher.active()
            except BronchoError as exc:  # a storage or scheduler hiccup must not end the watch
                log.warning("%s", exc)
                session.wait(session.poll_s)
                continue
            n = sum(t.count for t in tasks)
            if live is not None:
                live.update(live_view(plan, retries, max(1, n), now))
            elif (line := summary_line(progress(plan, retries, max(1, n), now, stale_s)).plain
                  + f"  {task_word}s {n}") != last_line:
                console.print(line, highlight=False)
                last_line = line
            session.tick(tasks)
            if not tasks:
                report_workers(console, session.exit_codes(), launcher.logs(cfg))
                if session.stopped:  # on stderr, worded as every command's interruption (train, report, ...)
                    Console(stderr=True).print(interrupted_line("running cells were released; run the same command "
                                                                "again to resume"), highlight=False, soft_wrap=True)
                    return EXIT_INTERRUPTED
            if not tasks or time.monotonic() - asked > CANCEL_CHECK_S:  # never a top-up after a cancel
                asked = time.monotonic()
                if cancelled():
                    what, cancel_hint, resume_hint = hints or (f"sweep {walk.sweep}", "`bronchopose sweep cancel`",
                                                               "`bronchopose sweep run`")
                    console.print(f"[yellow]{what} was cancelled[/] ({cancel_hint}): nothing is submitted again; "
                                  f"{resume_hint} resumes it", highlight=False)
                    return EXIT_INTERRUPTED
            if not tasks:
                left = cells_left(plan, retries)
                if not left and walk.complete:
                    break
                if session.gives_up(_open_stage(walk, plan, retries), record.stages):
                    return final(console, plan, retries)  # its workers ended with cells left: a new one would too
                claimable = claimable_now(plan, retries, now, stale_s)
                if left and not claimable:  # a dead worker's cell: claimable once its claim is stale, not before
                    session.wait(session.poll_s)
                    continue
                # workers ended with cells left (a stage done, a cancelled one gave its cell back, a stage was
                # selected, a dead one's claim went stale): submit again, but only when the table moved since the
                # last submission (workers that crash at start would otherwise be resubmitted for ever)
                now_seen = _table_state(plan, claimable)
                if now_seen == seen_at_submit or not submit_missing(walk, launcher, console, record, session=session):
                    if record.waiting is not None and not left:  # the walk stops at a stage that cannot start
                        console.print(waits_line(record.waiting), highlight=False)
                        return final(console, session.rows(walk), retries)
                    console.print(f"[yellow]no {title} {task_word} of sweep {cfg.name} is left and "
                                  f"{left} cell(s) are not done[/]; see the logs ({launcher.describe()}) and run the "
                                  "command again")
                    return 1
                seen_at_submit = now_seen
                try:
                    resubmitted()  # the sweep's last worker may have ended its parent run: RUNNING again
                except Exception as exc:  # noqa: BLE001 - a busy store must not end a watch
                    log.warning("could not reopen the sweep's parent run: %s", exc)
            session.wait(session.poll_s)
    except KeyboardInterrupt:
        return session.interrupted(console)
    finally:
        if live is not None:
            live.stop()
    return final(console, plan, retries)
