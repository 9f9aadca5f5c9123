"""How the command that submits a sweep's workers stays with them: a launcher's ``Session``.

The driver (``sweep.launch``) submits workers through a launcher and then watches the claims table. What it does
while it watches depends on where the workers live, and that is the launcher's to say, not the driver's to test:
the driver makes one ``Session`` per command (``Launcher.Session(launcher)``) and calls every method below
unconditionally. The default is a batch system's (Slurm, a plugin): workers outlive the command, so

- every stage is submitted at once, a later stage's workers waiting (``after``) for the earlier ones and settling
  their selections themselves: ``to_submit`` walks the whole plan and ``rows`` re-reads it on every refresh;
- a worker that ended with cells left was cancelled or timed out: a new one is submitted (``gives_up`` False);
- the sweep's parent run is RUNNING without this process (``open_parent``), Ctrl-C stops the watch only
  (``interrupted``), and ``--detach``, ``sweep cancel`` and ``status --repair`` apply (``outlives_command``).

The local launcher's workers are the command's own child processes (``launchers.local.LocalSession``): one stage
at a time, each selection read once by this process, no replacement of a worker that ended with cells left
(another would meet the same error), the parent run held by this process, Ctrl-C stopping the workers.

A session also carries what messages call the launcher's workers (``title``, ``job_word``, ``task_word``) and the
watch's hooks (``wait``, ``tick``, ``follow``, ``stopped``, ``exit_codes``, ``poll_s``).
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any, ClassVar

from rich.console import Console

from ..config import Stage

if TYPE_CHECKING:
    from .launchers.base import Launcher, Workers
    from .plan import Plan, Step

# 130: Ctrl-C or SIGINT/SIGTERM stopped the command or a worker (the worker loop's too). This module imports nothing
# of the sweep stack at import time: the launchers' registry reads it, and listing their options (the command
# line's flags) must not load MLflow or SQLAlchemy.
EXIT_INTERRUPTED = 130


class Session:
    """The command's side of a launcher whose workers outlive it (see the module). One per command; the block
    ``with session:`` is where the workers are submitted and watched."""

    outlives_command: ClassVar[bool] = True  # --detach, `sweep cancel`, `status --repair` apply to its workers
    title: ClassVar[str] = ""  # how messages name the launcher ("Slurm"; default: its name)
    job_word: ClassVar[str] = ""  # one submission in messages ("Slurm array job"; default: "<title> job")
    task_word: ClassVar[str] = "worker"  # one worker in messages ("task")
    poll_s: ClassVar[float] = 1.0  # how often the watch asks ``active``

    def __init__(self, launcher: Launcher):
        self.launcher = launcher

    @classmethod
    def words(cls, name: str) -> tuple[str, str, str]:
        """(title, job word, task word) for a launcher called ``name``."""
        title = cls.title or name
        return title, cls.job_word or f"{title} job", cls.task_word

    # -- the block the workers are submitted and watched in -------------------------------------------------------
    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: Any) -> None:
        return None

    def open_parent(self, client: Any, parent: str) -> None:
        """The sweep's parent run RUNNING while its workers run (again RUNNING when the sweep is submitted again)."""
        client.update_run(parent, "RUNNING")

    # -- what to submit, what to read --------------------------------------------------------------------------
    def to_submit(self, walk: Any, steps: Iterable[Step]) -> list[tuple[Stage, int]]:
        """The stages to size submissions for, with their cells left, from the walk's ``steps`` (settled and
        printed as they are taken). Default: every stage, later ones waiting for the earlier ones' workers."""
        for _ in steps:  # every stage whose source is done is settled (and printed) first
            pass
        return walk.work_left()

    def rows(self, walk: Any) -> Plan:
        """The known cells' rows on a refresh of the watch: re-read (workers settle later stages' selections)."""
        return walk.rows()

    def gives_up(self, open_stage: str | None, submitted: Sequence[str]) -> bool:
        """Workers are gone with cells left in ``open_stage``, for which this command submitted (``submitted``):
        end the watch (True) rather than submit again. Default: submit again (they were cancelled or timed out)."""
        return False

    def interrupted(self, console: Console) -> int:
        """Ctrl-C reached the watch: its exit code (default: stop watching; the workers go on)."""
        title = self.words(self.launcher.name)[0]
        console.print(f"stopped watching: the {title} jobs go on (`bronchopose sweep cancel` stops them)")
        return EXIT_INTERRUPTED  # the command stopped (130), the sweep did not

    # -- the watch's hooks -------------------------------------------------------------------------------------
    def submitted(self, job: str, n: int, stage: str, after: Sequence[str]) -> str:
        """The line that says a submission was made."""
        _, job_word, task_word = self.words(self.launcher.name)
        return (f"submitted {job_word} {job}: {n} {task_word}(s) for stage {stage}"
                + (f", after job(s) {', '.join(after)}" if after else ""))

    def wait(self, timeout: float) -> None:
        """Until something may have changed (default: ``timeout`` seconds)."""
        time.sleep(timeout)

    def tick(self, active: Sequence[Workers]) -> None:
        """Called on every refresh of the watch with what ``active`` listed."""

    def follow(self, queued: Sequence[str], earlier: Sequence[str]) -> None:
        """Make the ``queued`` later-stage submissions wait for the ``earlier`` ones too (a re-submitted stage)."""

    @property
    def stopped(self) -> bool:
        """This command told its workers to stop (the local launcher's Ctrl-C): the sweep is interrupted."""
        return False

    def exit_codes(self) -> list[int | None]:
        """How the workers that ended since the last call exited, where the launcher can tell (default: none)."""
        return []


class AttachedSession(Session):
    """Workers that are this command's own processes (see the module): one stage at a time, each selection read
    once here, no replacement of a worker that ended with cells left, the parent run held by this process."""

    outlives_command = False

    def open_parent(self, client: Any, parent: str) -> None:
        from ..runs.parents import start_parent  # lazy: see EXIT_INTERRUPTED

        start_parent(client, parent)  # RUNNING, with this process: `status --repair` ends it if we are killed

    def to_submit(self, walk: Any, steps: Iterable[Step]) -> list[tuple[Stage, int]]:
        """The first stage with cells left; a later stage is decided only once those before it are done."""
        from .plan import cells_left, ensure_rows  # lazy: see EXIT_INTERRUPTED

        retries = walk.cfg.sweep.max_retries
        for step in steps:
            if step.cells and cells_left(ensure_rows(walk.cfg, walk.store, step.cells, sweep=walk.sweep), retries):
                return [(step.stage, 1)]
        return []

    def rows(self, walk: Any) -> Plan:
        """This process settles each stage as it submits it: the known cells' rows, no selection read again."""
        from .plan import read_plan  # lazy: see EXIT_INTERRUPTED

        return read_plan(walk.store, walk.sweep, walk.known_cells())

    def gives_up(self, open_stage: str | None, submitted: Sequence[str]) -> bool:
        """Its workers wait for cells held elsewhere, so one that ended with cells left of a stage this command
        submitted ended for a reason a new one would meet too (an error, a full disk)."""
        return open_stage in submitted

    def interrupted(self, console: Console) -> int:
        raise KeyboardInterrupt from None  # the workers were stopped in the session's block; the command exits 130
