"""The typed results of the work calls that the layers below return as plain data: a tuning study's state, a
sweep's outcome. (``TrainResult``, ``ReportResult`` and ``SweepState`` live beside the code that makes them.)"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..sweep.status import SweepState


@dataclass(frozen=True)
class StudyResult:
    """An Optuna study of ``bronchopose tune``: trial counts by state, the best trial, parameter importances."""

    study: str
    objective: str  # what the trials minimise (tune.objective: val_loss, val_ratio or cost)
    counts: dict[str, int]  # trials per state: complete, pruned, fail, running, waiting
    best_number: int | None = None  # None: no completed trial yet
    best_value: float | None = None
    best_params: dict[str, Any] = field(default_factory=dict)
    best_run_id: str | None = None  # the best trial's MLflow run
    importances: dict[str, float] = field(default_factory=dict)  # empty with fewer than 2 completed trials

    @classmethod
    def from_info(cls, info: dict[str, Any]) -> StudyResult:
        """From ``sweep.tuning.studies.describe_study``'s description."""
        best = info.get("best") or {}
        return cls(info["study"], info.get("objective", ""), dict(info["counts"]), best.get("number"),
                   best.get("value"), dict(best.get("params", {})), best.get("run_id"),
                   dict(info.get("importances", {})))


class SweepResult:
    """What ``bronchopose sweep run`` ended with: its exit code (0 every cell FINISHED, 1 some FAILED, 130
    interrupted; a detached sweep: 0 once submitted) and the sweep's state after it (``state.cells()``: read from
    the claims table and MLflow when first asked)."""

    def __init__(self, exit_code: int, read_state: Callable[[], SweepState]) -> None:
        self.exit_code = exit_code
        self._read_state = read_state

    @property
    def ok(self) -> bool:
        return self.exit_code == 0

    @cached_property
    def state(self) -> SweepState:
        return self._read_state()

    def __repr__(self) -> str:
        return f"SweepResult(exit_code={self.exit_code})"
