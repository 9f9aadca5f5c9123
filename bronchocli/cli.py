"""The `bronchopose` command line: registers the commands (one module each in ``commands/``, thin layers over
``bronchocli.api``) and turns whatever escapes one into one line and an exit code (``BronchoError``: 2; a stop
signal: the shell's code for it; ``--debug``: the traceback after the line)."""

from __future__ import annotations

import errno
import functools
import signal
import sys
import traceback
from typing import Optional

import typer
from rich.text import Text

from . import __version__, extras, interrupts, pathcheck, urls
from .commands import config as config_cmd
from .commands import data as data_cmd
from .commands import launcher_flags
from .commands import profile as profile_cmd
from .commands import report as report_cmd
from .commands import selftest as selftest_cmd
from .commands import status as status_cmd
from .commands import sweep as sweep_cmd
from .commands import track as track_cmd
from .commands import train as train_cmd
from .commands import tune as tune_cmd
from .commands import ui as ui_cmd
from .commands import weights as weights_cmd
from .commands.common import err_console
from .errors import BronchoError, Interrupted, out_of_memory
from .runs.contract import RunInterrupted

app = typer.Typer(
    name="bronchopose",
    help="Vision-based bronchoscopy pose estimation: synthetic data, BronchoPose models, "
    "MLflow-tracked sweeps, Optuna tuning and the paper's tables.",
    no_args_is_help=True,
    add_completion=True,  # --install-completion / --show-completion; choices complete from their enums
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)

# The one explicit list of commands (name -> function); tests check it against --help.
COMMANDS = {
    "config": config_cmd.config,
    "train": train_cmd.train,
    "ui": ui_cmd.ui,
    "tune": tune_cmd.tune,
    "report": report_cmd.report,
    "profile": profile_cmd.profile,
    "status": status_cmd.status,
    "track": track_cmd.track,
    "selftest": selftest_cmd.selftest,
}
# Commands whose flags include the launchers' options (name -> command class; ``commands/launcher_flags.py``).
CLASSES = {"tune": launcher_flags.command(helps=tune_cmd.HELPS)}
# Command groups with subcommands (name -> Typer app).
GROUPS: dict[str, typer.Typer] = {"data": data_cmd.app, "sweep": sweep_cmd.app, "weights": weights_cmd.app}

def _interruptible(fn):
    """``fn`` with a KeyboardInterrupt it lets through (Ctrl-C, SIGTERM, SIGHUP: ``interrupts``) raised as
    ``Interrupted`` (Typer would turn it into a silent exit 130): one line, the signal's exit code."""

    @functools.wraps(fn)
    def command(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except KeyboardInterrupt:
            raise Interrupted("nothing was left half-written; run the same command again to continue") from None

    return command


for _name, _fn in COMMANDS.items():
    app.command(name=_name, cls=CLASSES.get(_name))(_interruptible(_fn))
for _name, _group in GROUPS.items():
    for _info in _group.registered_commands:
        _info.callback = _interruptible(_info.callback)
    app.add_typer(_group, name=_name)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"bronchopose {__version__}")
        raise typer.Exit()


_DEBUG: list[bool] = [False]  # --debug: an error's one line is followed by its traceback


@app.callback()
def _root(
    version: Optional[bool] = typer.Option(
        None, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
    debug: bool = typer.Option(False, "--debug", help="After an error's one line, print its traceback (a plugin's "
                               "import, a launcher's submission)."),
) -> None:
    """Vision-based bronchoscopy pose estimation research platform."""
    _DEBUG[0] = debug


def _error(message: str) -> None:
    # Every message may quote a setting, and a URL setting may carry a password: never print it.
    err_console.print(Text.assemble(("error: ", "bold red"), urls.redact(message)), highlight=False, soft_wrap=True)


def _choice_error(exc: Exception) -> str | None:
    """A bad value of a choice option, worded like every other bad value: ``--arch 'x': must be one of a, b``.

    Typer (pinned < 0.30 in pyproject) checks Literal choices itself; its message is rebuilt from the option's
    choices and the rejected value. None when ``exc`` is something else (then Typer's own message is shown).
    """
    param = getattr(exc, "param", None)
    choices = getattr(getattr(param, "type_descriptor", None), "choices", None)
    if not choices or not getattr(getattr(param, "type_descriptor", None), "is_choice", False):
        return None
    cause = exc.__cause__
    errors = cause.errors() if hasattr(cause, "errors") else []
    if not errors or "input" not in errors[0]:
        return None
    flag = max(param.opts, key=len)  # what the user typed, e.g. --pose-frame
    return f"{flag} {errors[0]['input']!r}: must be one of {', '.join(str(c) for c in choices)}"


def _usage_error(exc: Exception) -> int:
    """A bad flag or argument (click's UsageError): one line naming it and where help is, exit code 2."""
    if type(exc).__name__ == "NoArgsIsHelpError":  # the help was printed already
        return int(getattr(exc, "exit_code", 2))
    if (choice := _choice_error(exc)) is not None:
        _error(choice)
        return 2
    ctx = getattr(exc, "ctx", None)
    message = " ".join(exc.format_message().split())  # type: ignore[attr-defined]
    hint = f" (see `{ctx.command_path} --help`)" if ctx is not None else ""
    _error(f"{message}{hint}")
    return int(getattr(exc, "exit_code", 2))


# errno values of an OSError that are the user's path or file system, not a bug: one line and exit 2.
PATH_ERRNOS = {errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.ENAMETOOLONG,
               errno.ELOOP, errno.ENOSPC, errno.EDQUOT, errno.EEXIST}


def main(argv: list[str] | None = None) -> None:
    """The console script: run a command; a user error is one line on stderr and its exit code (2, or 130)."""
    try:
        with interrupts.as_keyboard_interrupts():  # SIGTERM and SIGHUP stop a command as Ctrl-C does
            code = app(args=argv, prog_name="bronchopose", standalone_mode=False)
    except (Interrupted, RunInterrupted) as exc:  # Ctrl-C, SIGTERM, SIGHUP; a training run's KILLED line
        by = "" if interrupts.name() in str(exc) else _by()  # "SIGTERM received at step 5/8" names it already
        err_console.print(Text.assemble((f"interrupted{by}: ", "bold yellow"), urls.redact(str(exc))),
                          highlight=False, soft_wrap=True)
        raise SystemExit(interrupts.exit_code(exc.exit_code)) from None
    except BronchoError as exc:
        _error(str(exc))
        if _DEBUG[0]:
            traceback.print_exception(exc, file=sys.stderr)
        raise SystemExit(exc.exit_code) from None
    except typer.Abort:  # click's: a KeyboardInterrupt (Ctrl-C, SIGTERM, SIGHUP) or a prompt's end of input
        if interrupts.last() is None:  # end of input at a prompt: nothing to say
            raise SystemExit(130) from None
        _interrupted()
    except KeyboardInterrupt:  # a Ctrl-C (SIGTERM, SIGHUP) outside a run's own handling (start-up, between trials)
        _interrupted()
    except typer.TyperException as exc:
        if not hasattr(exc, "format_message"):
            raise
        raise SystemExit(_usage_error(exc)) from None
    except ImportError as exc:  # an optional dependency met without an explicit check: name the extra
        missing = extras.from_import_error(exc, "this command") or out_of_memory(exc)  # or: loaded under ulimit -v
        if missing is None:
            raise
        _error(str(missing))
        raise SystemExit(missing.exit_code) from None
    except OSError as exc:  # a path problem no check caught (read-only, missing, a file for a folder): one line
        if (oom := out_of_memory(exc)) is not None:
            _error(str(oom))
            raise SystemExit(2) from None
        if pathcheck.is_loop(exc) and getattr(exc, "filename", None):
            _error(str(pathcheck.loop_error(exc.filename, "path")))
            raise SystemExit(2) from None
        if exc.errno not in PATH_ERRNOS or not getattr(exc, "filename", None):
            raise
        _error(f"{exc.filename}: {exc.strerror or exc}; check the path and its permissions")
        raise SystemExit(2) from None
    except (RuntimeError, MemoryError) as exc:  # a symlink loop no setting's check met, or an allocation failed
        if pathcheck.is_loop(exc):  # Path.resolve's "Symlink loop from '...'"
            _error(str(pathcheck.loop_error(str(exc).partition(" from ")[2].strip("'\"") or "a path", "path")))
        elif (oom := out_of_memory(exc)) is not None:  # the failed allocation is gone: memory to say so is back
            _error(str(oom))
        else:
            raise
        raise SystemExit(2) from None
    except Exception as exc:  # a SQLite store found damaged mid-command (its header passed the check at opening)
        if (damaged := urls.damaged_message(exc)) is None:
            raise
        _error(damaged)
        raise SystemExit(2) from None
    if isinstance(code, int) and not isinstance(code, bool) and code:  # typer.Exit(n) of a command
        raise SystemExit(interrupts.exit_code(code) if code == 130 else code)


def _interrupted() -> None:
    """A command stopped by a signal it does not handle itself: one line, the shell's exit code of the signal."""
    err_console.print(Text.assemble((f"interrupted{_by()}", "bold yellow"), ": nothing was left half-written; "
                                    "run the same command again to continue"), highlight=False)
    raise SystemExit(interrupts.exit_code())


def _by() -> str:
    """`` by SIGTERM``: the stop signal that interrupted the command, when it was not Ctrl-C."""
    last = interrupts.last()
    return "" if last is None or last == signal.SIGINT else f" by {interrupts.name(last)}"


if __name__ == "__main__":  # `python -m bronchocli.cli ...` runs the command line too (it used to exit 0 silently)
    main()
