"""Issue 58, item 1: the driver asks a launcher's Session and never tests what kind of launcher it drives."""

from __future__ import annotations

import ast
import inspect

import pytest

from bronchocli.sweep import launch
from bronchocli.sweep.launchers import LocalLauncher, SlurmLauncher
from bronchocli.errors import BronchoError
from bronchocli.sweep.launchers import register
from bronchocli.sweep.launchers.base import Job, Launcher
from bronchocli.sweep.session import AttachedSession, Session

# what used to be mode flags of the launcher (and the one that remains, on its Session): no driver condition names them
MODE_NAMES = {"detachable", "defers", "resubmits", "runs_command", "outlives_command"}


def _conditions(tree: ast.AST) -> list[ast.AST]:
    tests = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.If, ast.IfExp, ast.While, ast.Assert)):
            tests.append(node.test)
        elif isinstance(node, ast.comprehension):
            tests.extend(node.ifs)
        elif isinstance(node, ast.BoolOp):
            tests.extend(node.values)
    return tests


def _names_in(expr: ast.AST) -> set[str]:
    out = set()
    for node in ast.walk(expr):
        if isinstance(node, ast.Attribute):
            out.add(node.attr)
        elif isinstance(node, ast.Name):
            out.add(node.id)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            out.add(node.value)
    return out


def test_the_driver_has_no_condition_on_what_kind_of_launcher_it_drives():
    tree = ast.parse(inspect.getsource(launch))
    named = set().union(*(_names_in(t) for t in _conditions(tree)))
    assert not named & MODE_NAMES, named & MODE_NAMES
    # nor on the launcher's identity: its class, its name, an isinstance test
    assert not named & {"isinstance", "LocalLauncher", "SlurmLauncher", "LocalSession", "AttachedSession", "local",
                        "slurm"}, named
    source = inspect.getsource(launch)
    assert all(f".{flag}" not in source for flag in MODE_NAMES)  # not read anywhere in the driver


def test_the_planted_mode_condition_is_seen():
    """The reader above can fail: the condition the driver used to have is found in a planted copy."""
    planted = ast.parse("def f(launcher):\n    if not launcher.defers and x:\n        return 1\n")
    assert set().union(*(_names_in(t) for t in _conditions(planted))) & MODE_NAMES == {"defers"}


def test_the_launchers_say_where_their_workers_live_through_their_session():
    assert LocalLauncher.Session.outlives_command is False and issubclass(LocalLauncher.Session, AttachedSession)
    assert SlurmLauncher.Session.outlives_command is True and Launcher.Session is Session
    for flag in MODE_NAMES:
        assert not hasattr(Launcher, flag), flag  # moved to the session (or gone), not left beside it


def _implementable(cls: type) -> tuple[set[str], set[str]]:
    """The members of ``cls`` an author may write (declared here, not ``typing.final``, not private) and the
    required ones (abstract methods, and class variables declared without a value)."""
    members = {name for name, value in vars(cls).items()
               if not name.startswith("_") and not getattr(value, "__final__", False)
               and not getattr(getattr(value, "fget", None), "__final__", False)}
    members |= set(vars(cls).get("__annotations__", {}))  # declared class variables (``name``)
    members.add("__init__")  # a launcher may take what it needs
    required = {name for name in members if getattr(getattr(cls, name, None), "__isabstractmethod__", False)}
    required |= {name for name in vars(cls).get("__annotations__", {}) if not hasattr(cls, name)}
    return members, required


def test_the_protocol_is_small_three_methods_and_a_name_required():
    """submitit's shape: the executor submits and lists; the Job it returns owns cancel (and state, logs)."""
    members, required = _implementable(Launcher)
    assert len(members) <= 12 and required == {"name", "submit", "active"}, (sorted(members), required)
    assert "Job" in members and "cancel" not in members and "jobs" not in members  # provided: every Job's cancel
    job_members, job_required = _implementable(Job)
    assert job_required == {"cancel"} and {"logs", "state", "workers"} <= job_members, (job_members, job_required)
    assert len(required - {"name"} | {f"Job.{m}" for m in job_required}) <= 3  # three methods to write in all


def test_a_launcher_whose_job_cannot_cancel_is_refused_in_one_line(monkeypatch):
    from bronchocli.sweep import launchers

    monkeypatch.setattr(launchers, "_LAUNCHERS", dict(launchers._LAUNCHERS))

    class Silent(Launcher):  # forgot its Job: cancel would stop nothing
        name = "silent"
        submit = active = lambda self, *a, **k: []  # noqa: E731

    with pytest.raises(BronchoError) as refused:
        register(Silent)
    assert str(refused.value).startswith("launcher silent: its Job must be a launchers.Job subclass that writes "
                                         "cancel()") and "\n" not in str(refused.value)
    assert "silent" not in launchers.names()


def test_the_member_count_can_fail():
    class Grown(Launcher):  # a protocol that grew its old flags back would be counted
        detachable = True
        defers = False
        resubmits = False
        poll_s = 1.0

        def supervised(self): ...

    members, _ = _implementable(Grown)
    assert {"detachable", "defers", "resubmits", "poll_s", "supervised"} <= members


def test_listing_the_launchers_options_loads_no_sweep_stack():
    """`sweep run --help` builds its flags from the launchers' parameters: the registry, its protocol and the
    built-in launchers import without MLflow, SQLAlchemy, Optuna or torch (it took ~10x `train --help` when they
    did). A fresh process: nothing imported before."""
    import subprocess
    import sys

    probe = ("import sys; from bronchocli.sweep.launchers import parameters; names = sorted(parameters()); "
             "heavy = sorted({m.split('.')[0] for m in sys.modules} & {'mlflow', 'sqlalchemy', 'optuna', 'torch'}); "
             "print(names, heavy)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "['gpus', 'per_gpu', 'workers'] []", out
