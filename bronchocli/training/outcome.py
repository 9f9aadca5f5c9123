"""What ``bronchopose train`` (and ``bronchocli.api.train``) gives back: the cell, its run and whether it was
trained now, without importing torch."""

from __future__ import annotations

from dataclasses import dataclass

from .. import runkeys
from ..cells import Cell
from ..runs.contract import RunResult


@dataclass(frozen=True)
class TrainResult:
    """One cell's run: the one trained now (``trained``), or the FINISHED run it already had (not trained again)."""

    cell: Cell
    experiment: str  # the MLflow experiment (the config's ``experiment_name``)
    run: RunResult
    trained: bool = True

    @property
    def run_id(self) -> str:
        return self.run.run_id

    @property
    def ok(self) -> bool:
        return self.run.status == "FINISHED"

    @property
    def metrics(self) -> dict[str, float]:
        return self.run.metrics

    def errors(self, metric: str = "pos_l2", evaluation: str = "pair") -> dict[str, float]:
        """The test error of the model and of both image-blind references (``runkeys.SOURCES``), where logged."""
        out = {}
        for ref in runkeys.SOURCES:
            key = runkeys.metric(metric, evaluation, ref=ref)
            if key in self.run.metrics:
                out[ref] = self.run.metrics[key]
        return out

    @property
    def headline(self) -> float:
        """The headline (``runkeys.headline``, its one computation): pair position error ÷ the training-mean
        predictor's; NaN when either is not logged or the reference's is not a positive finite number."""
        return runkeys.headline(self.metrics)

    def summary(self) -> str:
        """The one line ``bronchopose train`` ends with."""
        if not self.trained:
            return (f"cell {self.cell.label} (key {self.cell.key}) already has a FINISHED run {self.run_id} in "
                    f"experiment {self.experiment}: not trained again (--again trains another run)")
        if not self.ok:
            return f"run {self.run_id} {self.run.status}: {self.run.failure_reason}"
        m, e = self.metrics, self.errors()
        return (f"run {self.run_id} FINISHED in {self.run.duration_s:.1f} s ({m[runkeys.train('steps')]:.0f} steps, "
                f"{m[runkeys.train('pairs_seen')]:.0f} pairs seen) — pair pos L2 {e[runkeys.MODEL]:.3f} vox "
                f"({self.headline:.2f} x the training-mean predictor's {e['train_mean']:.3f}, zero motion "
                f"{e['zero_motion']:.3f}), accumulated pos L2 {m[runkeys.metric('pos_l2', 'acc')]:.2f} vox")
