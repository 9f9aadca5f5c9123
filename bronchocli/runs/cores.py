"""Sharing the machine's cores between this project's processes: how many torch CPU threads each one takes.

Two commands started at once (two ``train``, a ``train`` beside a ``sweep``, a ``tune`` beside a ``profile``)
used to take every core each and ran five times slower together than either alone (issue 40). Now every
training process — ``train``, a sweep worker, a tune trial, ``selftest``, ``profile`` — holds a *claim*: one
small advisory file per process in the user's runtime folder (``$XDG_RUNTIME_DIR/bronchopose/cores``, else
``<tmp>/bronchopose-<uid>/cores``) naming its pid, its start tick, when it claimed and the threads it uses.
An entry whose process is gone (``processes.pid_alive``: the pid and its start tick) is ignored and removed,
so a killed process never holds cores.

The rule (``decide``), asked at the start of a run, after every validation and every ``RECHECK_S`` seconds of
training (``CoreShare.fresh``: a directory listing, so a run started alone gives back cores within seconds of
another one starting, not at its next validation):

* an explicit count (``train.threads``, ``--threads``) always wins, and is held against the others;
* otherwise the cores left by the explicit claims are split evenly between the sharing claims, this one
  included; the remainder goes one each to the oldest claims; never fewer than one thread;
* a sweep's or tune's worker (``WORKERS_ENV``: how many workers its command runs here) takes at most
  cores / workers, so a sweep's workers never take more than the machine while a sibling is still starting.

What a run got and why is in its params: ``threads`` and ``threads.source``.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import time
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

from .. import io
from .processes import pid_alive, process_start

if TYPE_CHECKING:  # the annotation only: deciding threads needs no config
    from ..config import Config

log = logging.getLogger(__name__)
WORKERS_ENV = "BRONCHOPOSE_CPU_WORKERS"  # set in a sweep's / tune's worker processes: its command's workers here
SUFFIX = ".json"
RECHECK_S = 5.0  # how old a decision may be while training (CoreShare.fresh)


def machine_cores() -> int:
    """The cores this process may run on (its CPU affinity: a Slurm or taskset allocation), else all of them."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # macOS, Windows
        return max(1, os.cpu_count() or 1)


def workers_here(env: Mapping[str, str] | None = None) -> int | None:
    """How many workers this process's sweep or tune runs on this machine (None: not a worker; bad: None)."""
    value = (os.environ if env is None else env).get(WORKERS_ENV, "")
    return int(value) if value.isdigit() and int(value) > 0 else None


def claims_folder(env: Mapping[str, str] | None = None) -> Path:
    """The user's folder of claims: ``$XDG_RUNTIME_DIR/bronchopose/cores``, else ``<tmp>/bronchopose-<uid>``."""
    env = os.environ if env is None else env
    runtime = env.get("XDG_RUNTIME_DIR")
    if runtime and Path(runtime).is_dir():
        return Path(runtime) / "bronchopose" / "cores"
    user = os.getuid() if hasattr(os, "getuid") else os.environ.get("USERNAME", "user")
    return Path(tempfile.gettempdir()) / f"bronchopose-{user}" / "cores"


@dataclass(frozen=True)
class Claim:
    """One process's entry: ``threads`` None while it has not decided yet (it counts as sharing)."""

    token: str  # the file's stem: pid plus a random part (two claims of one process stay apart)
    pid: int
    start: str  # the process's start tick ("?": unknown)
    since: float  # when it claimed (time.time()): the oldest claims get the remainder
    threads: int | None = None
    explicit: bool = False

    def order(self) -> tuple[float, str]:
        return (self.since, self.token)

    def to_json(self) -> dict:
        return {"pid": self.pid, "start": self.start, "since": self.since, "threads": self.threads,
                "explicit": self.explicit}

    @classmethod
    def from_json(cls, token: str, data: Mapping) -> Claim:
        threads = data.get("threads")
        return cls(token, int(data["pid"]), str(data.get("start", "?")), float(data["since"]),
                   int(threads) if threads is not None else None, bool(data.get("explicit", False)))


@dataclass(frozen=True)
class Decision:
    """The threads a process takes and why (``threads.source``)."""

    threads: int
    source: str

    def params(self) -> dict[str, str]:
        return {"threads": str(self.threads), "threads.source": self.source}


def _plural(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 'es' if word.endswith('s') else 's'}"


def decide(cores: int, me: Claim, others: Sequence[Claim], *, explicit: int | None = None,
           explicit_from: str = "train.threads", workers: int | None = None) -> Decision:
    """The threads ``me`` takes on ``cores`` cores beside the live claims ``others`` (the rule of the module doc)."""
    if explicit is not None:
        return Decision(int(explicit), f"explicit ({explicit_from})")
    held = sum(o.threads or 0 for o in others if o.explicit)
    sharing = sorted([o for o in others if not o.explicit] + [me], key=Claim.order)
    base, extra = divmod(max(0, cores - held), len(sharing))
    share = max(1, base + (1 if sharing.index(me) < extra else 0))
    source = f"share of {_plural(cores, 'core')} with {_plural(len(others) + 1, 'process')}"
    if held:
        source += f" ({held} held by explicit ones)"
    if workers:
        pin = max(1, cores // workers)
        if pin < share:
            return Decision(pin, f"worker pin: {_plural(cores, 'core')} / {workers} workers of its command")
    return Decision(share, source)


def live_claims(folder: Path, *, skip: str | None = None) -> list[Claim]:
    """The claims in ``folder`` whose process lives (``skip``: one's own token); dead ones' files are removed."""
    out = []
    try:
        paths = sorted(folder.glob("*" + SUFFIX))
    except OSError:
        return []
    for path in paths:
        if path.stem == skip:
            continue
        try:
            claim = Claim.from_json(path.stem, json.loads(path.read_text()))
        except (OSError, ValueError, KeyError, TypeError):  # vanished, or being replaced: not a claim now
            continue
        if pid_alive(claim.pid, claim.start):
            out.append(claim)
        else:
            path.unlink(missing_ok=True)  # a dead process's entry: stale, never counted
    return out


class CoreShare:
    """This process's claim: ``with CoreShare(...) as share`` registers it, ``share.check()`` decides (again),
    leaving the block removes it. A folder that cannot be written leaves the process deciding alone (advisory:
    never a reason to fail a run)."""

    def __init__(self, explicit: int | None = None, *, explicit_from: str = "train.threads",
                 workers: int | None = None, folder: Path | None = None, cores: int | None = None) -> None:
        self.explicit, self.explicit_from, self.workers = explicit, explicit_from, workers
        self.folder = claims_folder() if folder is None else Path(folder)
        self.cores = cores or machine_cores()
        self.me = Claim(f"{os.getpid()}-{uuid.uuid4().hex[:8]}", os.getpid(), process_start(), time.time(),
                        explicit, explicit is not None)
        self.decision: Decision | None = None
        self.decided_at: float | None = None  # time.monotonic() of the last decision
        self._registered = False

    @property
    def path(self) -> Path:
        return self.folder / (self.me.token + SUFFIX)

    def _write(self) -> None:
        try:
            self.folder.mkdir(parents=True, exist_ok=True, mode=0o700)
            if hasattr(os, "getuid") and self.folder.stat().st_uid != os.getuid():
                raise PermissionError(f"{self.folder} belongs to another user")
            io.write_json(self.path, self.me.to_json())
            self._registered = True
        except OSError as exc:
            log.warning("CPU threads decided alone: the claims folder %s is not writable (%s)", self.folder, exc)

    def __enter__(self) -> CoreShare:
        self._write()
        return self

    def __exit__(self, *exc) -> None:
        if self._registered:
            self.path.unlink(missing_ok=True)

    def check(self) -> Decision:
        """Decide from the live claims now; the entry says the new count when it changed."""
        others = live_claims(self.folder, skip=self.me.token)
        self.decided_at = time.monotonic()
        self.decision = decide(self.cores, self.me, others, explicit=self.explicit,
                               explicit_from=self.explicit_from, workers=self.workers)
        if self.me.threads != self.decision.threads:
            self.me = replace(self.me, threads=self.decision.threads)
            if self._registered:
                self._write()
        return self.decision

    def fresh(self, max_age_s: float = RECHECK_S, clock=time.monotonic) -> int:
        """The threads to use now: the last decision while it is younger than ``max_age_s``, else decided again
        (asked at every training step: a clock read, and a directory listing every few seconds)."""
        if self.decision is None or self.decided_at is None or clock() - self.decided_at >= max_age_s:
            self.check()
            self.decided_at = clock()
        return self.threads

    @property
    def threads(self) -> int:
        """The count decided last (deciding now when none was)."""
        return (self.decision or self.check()).threads


def for_run(cfg: Config) -> CoreShare:
    """The claim of a training run: ``train.threads`` when set, else a share (a worker's capped by its command's
    workers on this machine)."""
    return CoreShare(cfg.train.threads, workers=workers_here())
