"""Rendering one trajectory's frames; runs in the generator's process or in a worker process.

A ``RenderTask`` carries its camera poses and a ``FrameSink`` (the dataset
writer the generator hands it: this package writes no files itself). Each
process keeps one ``FrameRenderer`` (one OpenGL context) for the surface it
last rendered and replaces it when a task for another patient arrives, so
tasks sorted by patient load each surface about once per worker. Frames the
sink already has are not rendered again (resumption); their digests are read
back so the dataset fingerprint covers them too. ``RenderProgress`` is the
generator's progress bar.
"""

from __future__ import annotations

import ctypes
import os
import signal
import time
from dataclasses import dataclass
from typing import Callable, Iterable, Protocol

import numpy as np
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from .. import interrupts
from ..config import Realism
from ..io import read_polydata

Callback = Callable[[int, int], None]  # (frames done, frames total)


class FrameSink(Protocol):
    """Where rendered frames go (picklable: it travels to worker processes with its task)."""

    def exists(self, name: str) -> bool: ...

    def digest(self, name: str) -> bytes: ...

    def write(self, name: str, frame: np.ndarray) -> bytes:
        """Store ``frame`` (H x W x 3 uint8) as ``name``; return its content digest."""
        ...


@dataclass
class RenderTask:
    """The frames of one trajectory: their names in the sink and the camera for each."""

    patient: str
    lobe: str
    trajectory: int
    sink: FrameSink
    surface: str  # prepared lumen surface (.vtp), mm
    filenames: list[str]  # names in the sink
    position_mm: np.ndarray  # (N, 3)
    rotation: np.ndarray  # (N, 3, 3)
    radius_mm: np.ndarray  # (N,)
    width: int
    fov_deg: float
    realism: Realism

    def missing(self) -> int:
        """Frames of this task not on disk yet."""
        return sum(not self.sink.exists(f) for f in self.filenames)


_CURRENT: dict = {}  # {"key": (surface, width, fov, realism), "renderer": FrameRenderer}


PR_SET_PDEATHSIG = 1  # linux/prctl.h


def die_with_parent(parent_pid: int) -> None:
    """Have the kernel kill this process when its parent dies (Linux ``PR_SET_PDEATHSIG``): a killed
    ``data generate`` leaves no worker rendering on. Elsewhere (no prctl) nothing changes."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):
        return
    if os.getppid() != parent_pid:  # the parent died before the request was in place
        os._exit(1)


def init_worker(threads: int | None, parent_pid: int | None = None) -> None:
    """Process-pool initializer: bound the software rasteriser's threads so workers do not oversubscribe, and
    die with the parent (``parent_pid``: the process that started the pool).

    A terminal's Ctrl-C (or hang-up) reaches the whole process group: workers ignore it and
    the parent stops them (no traceback from every worker).
    """
    for s in interrupts.STOP_SIGNALS:
        if s != signal.SIGTERM:  # SIGTERM is how the parent stops them
            signal.signal(s, signal.SIG_IGN)
    if parent_pid is not None and hasattr(os, "getppid"):
        die_with_parent(parent_pid)
    if threads:
        os.environ.setdefault("LP_NUM_THREADS", str(threads))


def _renderer(task: RenderTask):
    from .scene import FrameRenderer  # lazy: the OpenGL context loads only in rendering processes

    key = (task.surface, task.width, task.fov_deg, task.realism)
    if _CURRENT.get("key") != key:
        close_renderer()
        surface = read_polydata(task.surface)
        _CURRENT["renderer"] = FrameRenderer(surface, width=task.width, fov_deg=task.fov_deg, realism=task.realism)
        _CURRENT["key"] = key
    return _CURRENT["renderer"]


def close_renderer() -> None:
    """Release this process's renderer (its OpenGL context), if any."""
    renderer = _CURRENT.pop("renderer", None)
    _CURRENT.pop("key", None)
    if renderer is not None:
        renderer.close()


def run_task(task: RenderTask, on_frame: Callable[[bool], None] | None = None) -> tuple[list[bytes], int]:
    """Render the task's missing frames into its sink; returns (digest per frame, frames rendered).

    ``on_frame(rendered)`` is called after each frame (``rendered`` False when the sink already had it).
    """
    digests, rendered = [], 0
    for i, name in enumerate(task.filenames):
        rendered_now = not task.sink.exists(name)
        if not rendered_now:
            digests.append(task.sink.digest(name))
        else:
            frame = _renderer(task).render(task.position_mm[i], task.rotation[i], task.radius_mm[i])
            digests.append(task.sink.write(name, frame))
            rendered += 1
        if on_frame is not None:
            on_frame(rendered_now)
    return digests, rendered


class RenderProgress:
    """A rich progress bar (frames done / total, rendering fps) that also feeds the callback."""

    def __init__(self, pending: Iterable[RenderTask], total: int, show: bool, callback: Callback | None) -> None:
        self.total = total
        self.done = total - sum(t.missing() for t in pending)
        self.rendered, self.start = 0, time.perf_counter()
        self.callback, self.bar = callback, None
        if show:
            self.bar = Progress(TextColumn("rendering"), BarColumn(), MofNCompleteColumn(), TextColumn("frames"),
                                TextColumn("{task.fields[fps]}"), TimeElapsedColumn(), TimeRemainingColumn())
            self.task = self.bar.add_task("render", total=self.total, completed=self.done, fps="")

    def __enter__(self) -> "RenderProgress":
        if self.bar is not None:
            self.bar.start()
        return self

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.stop()

    def advance(self, rendered: int) -> None:
        """``rendered`` more frames are on disk (frames found on disk were counted at the start)."""
        if not rendered:
            return
        self.rendered += rendered
        self.done += rendered
        if self.bar is not None:
            fps = self.rendered / max(time.perf_counter() - self.start, 1e-9)
            self.bar.update(self.task, advance=rendered, fps=f"{fps:.0f} fps")
        if self.callback is not None:
            self.callback(self.done, self.total)
