"""Which failures can be resumed: one table (the error kinds' ``resumable``), asked by the run and the sweep."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from bronchocli import errors
from bronchocli.errors import MlflowBusy, resumable
from bronchocli.runs.contract import failure_reason
from bronchocli.training import checkpoint

PACKAGE = Path(errors.__file__).parent
# Failures of the machine (docs/training.md, "Faults"): a FAILED run keeps its checkpoint and a retry resumes it.
MACHINE = {"WriteFailed", "CheckpointWriteError", "MlflowBusy", "MlflowUnreachable"}


@pytest.mark.parametrize("exc, expected", [
    (checkpoint.WriteFailed("/runs/x: No space left on device"), True),
    (checkpoint.CheckpointWriteError("/runs/x/last.pt: could not write the checkpoint"), True),
    (MlflowBusy("database is locked for 60 s"), True),
    (checkpoint.BadCheckpoint("/runs/x/last.pt: not a checkpoint of this run"), False),
    (errors.ConfigError("bad value"), False),
    (FloatingPointError("loss is nan"), False),
    (ValueError(""), False),
])
def test_an_exception_and_its_recorded_reason_give_the_same_answer(exc, expected):
    assert resumable(exc) is expected
    assert resumable(failure_reason(exc)) is expected  # what the sweep reads back from the run's tag


@pytest.mark.parametrize("reason", ["WriteFailedSoon: x", "WriteFailed", "", "KILLED: WriteFailed: x",
                                    "Interrupted: SIGINT"])
def test_other_reasons_are_not_resumable(reason):
    assert not resumable(reason)


def test_the_resumable_kinds_are_those_of_the_machine_and_all_live_in_errors_py():
    found = {}
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and any(
                    isinstance(s, ast.Assign) and [getattr(t, "id", None) for t in s.targets] == ["resumable"]
                    and getattr(s.value, "value", None) is True for s in node.body):
                found[node.name] = path.name
    assert found == {"WriteFailed": "errors.py", "MlflowBusy": "errors.py",  # a reader needs no torch
                     "MlflowUnreachable": "errors.py"}

    def kinds(cls):
        return [cls] + [k for sub in cls.__subclasses__() for k in kinds(sub)]

    assert {k.__name__ for k in kinds(errors.BronchoError) if k.resumable} == MACHINE  # subclasses inherit it


def test_a_reason_under_no_kind_of_errors_py_is_not_resumable():
    assert resumable("MlflowBusy: database is locked")
    assert not resumable("TrackingBusy: database is locked")  # no kind of that name (0.1.0 renamed none)
    assert not resumable("TrackingUnreachable: no answer")
