"""User-facing errors: the CLI prints their message (no traceback) and exits with code 2.

Which failures a run can be resumed from is said here, once: a kind with
``resumable = True`` is a failure of the machine (a full disk, a busy
database), not of the run, so a FAILED run keeps its checkpoint and a retry
(the sweep's, or ``train --resume``) continues it. :func:`resumable` answers
for a live exception and for the ``failure_reason`` recorded for one
(``Type: message``, runs.contract.failure_reason), so the run that fails and the
sweep that reads its reason later ask the same classes. Resumable kinds are
defined in this module only (tests/test_errors.py), so a process that reads
reasons (``sweep gc``, ``status``) knows them all without importing torch.
"""

from __future__ import annotations


DEBUG_HINT = "; `bronchopose --debug ...` shows its traceback"  # after a one-line error whose cause is another's code


class BronchoError(Exception):
    """A problem with the user's input (file, flag, config value) that they can fix."""

    exit_code = 2
    resumable = False  # a failure of the machine, not of the run: keep the checkpoint, a retry resumes it


class ConfigError(BronchoError):
    """experiments.yaml (or a --set override) is malformed; the message lists every problem."""


class DataError(BronchoError):
    """A dataset on disk is missing, malformed or inconsistent."""


class Interrupted(BronchoError):
    """Ctrl-C stopped a command cleanly; the message says how to continue (exit code 130)."""

    exit_code = 130


class WriteFailed(BronchoError):
    """A file of the run (artifact, store, checkpoint) could not be written: disk full, I/O error, read-only."""

    resumable = True


class CheckpointWriteError(WriteFailed):
    """A checkpoint could not be written (disk full, I/O error); nothing half-written is left."""


class MlflowBusy(BronchoError):
    """The MLflow database stayed locked or unavailable for longer than ``runs.busy_timeout_s``."""

    resumable = True


class OutOfMemory(BronchoError):
    """An allocation failed (the machine's memory, the GPU's, or an address-space limit such as ``ulimit -v``)."""


# what allocators say: torch's CPU and CUDA allocators, C++, the dynamic loader mapping a library under ulimit -v
_ALLOCATION_FAILED = ("can't allocate memory", "cannot allocate memory", "out of memory", "bad_alloc",
                      "failed to map segment")
ENOMEM = 12  # errno.ENOMEM on every platform Python runs on


def out_of_memory(exc: BaseException) -> OutOfMemory | None:
    """``exc`` as one line when it is an allocation failure (MemoryError; torch's allocators raise RuntimeError
    "can't allocate memory" / "CUDA out of memory"; loading a native library under an address-space limit raises
    ImportError/OSError "failed to map segment" or ENOMEM), else None."""
    if isinstance(exc, OutOfMemory):
        return exc
    text = str(exc).strip()
    named = any(t in text.lower() for t in _ALLOCATION_FAILED)
    if not (isinstance(exc, MemoryError) or (isinstance(exc, RuntimeError) and named)
            or (isinstance(exc, (ImportError, OSError)) and (named or getattr(exc, "errno", None) == ENOMEM))):
        return None
    first = text.splitlines()[0] if text else type(exc).__name__
    return OutOfMemory(f"out of memory ({first[:300]}): this machine, or its address-space limit (`ulimit -v`), "
                       "cannot hold what the command needs; free memory, raise the limit, or ask for less "
                       "(train.batch_size, --workers)")


class MlflowUnreachable(BronchoError):
    """The MLflow server or database did not answer within ``runs.timeout_s`` (a sweep gives the cell back)."""

    resumable = True


def _kinds(cls: type[BaseException]) -> list[type[BaseException]]:
    return [cls] + [k for sub in cls.__subclasses__() for k in _kinds(sub)]


def resumable(failure: BaseException | str) -> bool:
    """Whether a failure (an exception, or the ``failure_reason`` recorded for one) can be resumed."""
    if isinstance(failure, BaseException):
        return bool(getattr(failure, "resumable", False))
    kind, sep, _ = failure.partition(":")
    return bool(sep) and any(k.__name__ == kind and getattr(k, "resumable", False) for k in _kinds(BronchoError))
