"""``fig-training-curves``: what each run learnt as it trained, from the metrics every validation logs.

Per run (one line each, labelled by its run name: the model's display name and coordinates, the UI's):
``val.ratio.pos_l2`` — validation pair position error ÷ the
training-mean predictor's on the same pairs, below 1 when the model beats that image-blind reference — and
``val.mode_gap`` — eval-mode ÷ batch-statistics loss on training batches (1: evaluation computes what training
optimised; training/batchnorm.py) — against the image pairs seen. Each run's test ratio
(``ratio.train_mean.pair.pos_l2``) is a hollow star at the step of the weights tested (``train.best_step``: the
best validation's, not the last step's). Reference lines, named in the legend: 1 on the ratio (the
training-mean predictor), 1 on the mode gap (eval mode computes what training optimised) and 1.10, the most
``bronchopose selftest``'s memorisation check accepts (training/batchnorm.py). Drawn when some run has at least two
validations with these metrics (older runs did not log them); the learning-curve profile's figure
(benchmarks/README.md, "Learning from scratch"). ``fig-training-curves.csv`` holds the same points (one row
per run and validation: step, pairs seen, both curves and the training loss logged at that step), so the
numbers quoted from a curve come from the report, not from a query of the store.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from pathlib import Path

import matplotlib.pyplot as plt

from .. import runkeys
from ..io import save_figure, write_text
from ..training.batchnorm import GAP_AT_MOST
from .collect import RunRecord

CURVES = (runkeys.VAL_RATIO, runkeys.VAL_MODE_GAP)
PAIRS = runkeys.train("pairs_seen")
TRAIN_LOSS = runkeys.TRAIN_LOSS
TEST = runkeys.HEADLINE
BEST_STEP = runkeys.train("best_step")  # the step whose weights were tested
FORMATS = ("png", "pdf")
History = Callable[[str, str], Sequence[tuple[int, float]]]  # (run id, metric) -> [(step, value)]


def history_loader(client) -> History:
    """(run id, metric) -> its logged (step, value) points, from MLflow."""
    def load(run_id: str, key: str) -> list[tuple[int, float]]:
        return sorted((m.step, m.value) for m in client.get_metric_history(run_id, key))
    return load


def curves(runs: Sequence[RunRecord], history: History) -> dict[str, dict[str, list[tuple[float, float]]]]:
    """label -> metric -> [(pairs seen, value)] for the runs with at least two validations of ``CURVES``."""
    out = {}
    for run in runs:
        pairs = dict(history(run.run_id, PAIRS))
        per = {key: [(pairs[s], v) for s, v in history(run.run_id, key) if s in pairs] for key in CURVES}
        if len(per[CURVES[0]]) >= 2:
            out[run.title] = per
    return out


def tested_at(run: RunRecord, history: History) -> float | None:
    """Pairs seen at the step of the run's tested weights (``train.best_step``; the last logged step where the run
    did not log it), None when no pairs count is logged."""
    pairs = dict(history(run.run_id, PAIRS))
    if not pairs:
        return None
    best = run.metrics.get(BEST_STEP)
    steps = sorted(pairs)
    if best is None:
        return pairs[steps[-1]]
    before = [s for s in steps if s <= best]
    return pairs[before[-1]] if before else pairs[steps[0]]


def curve_rows(runs: Sequence[RunRecord], history: History) -> list[tuple]:
    """(run, step, pairs seen, ratio, mode gap, training loss) per validation of the runs ``curves`` keeps; a
    value not logged at that step is None."""
    rows = []
    for run in sorted(runs, key=lambda r: r.title):
        per = {key: dict(history(run.run_id, key)) for key in (PAIRS, *CURVES, TRAIN_LOSS)}
        if len([s for s in per[CURVES[0]] if s in per[PAIRS]]) < 2:
            continue
        rows += [(run.title, step, per[PAIRS][step], ratio, per[CURVES[1]].get(step), per[TRAIN_LOSS].get(step))
                 for step, ratio in sorted(per[CURVES[0]].items()) if step in per[PAIRS]]
    return rows


def write_curve_csv(rows: Sequence[tuple], path: Path) -> Path:
    cell = lambda v: "" if v is None else (f"{v:.6g}" if isinstance(v, float) else str(v))  # noqa: E731
    head = ("run", "step", PAIRS, *CURVES, TRAIN_LOSS)
    return write_text(path, "".join(",".join(map(cell, r)) + "\n" for r in [head, *rows]))


def training_curves(runs: Sequence[RunRecord], history: History, out: Path, warnings: list[str]) -> list[Path]:
    """Write fig-training-curves (png, pdf and its points as csv; nothing when no run has two validations of
    the curve metrics)."""
    history = functools.lru_cache(maxsize=None)(history)  # the figure and the CSV read each history once
    data = curves(runs, history)
    if not data:
        return []
    table = write_curve_csv(curve_rows(runs, history), Path(out) / "fig-training-curves.csv")
    by_title = {r.title: r for r in runs}
    fig, (ratio_ax, gap_ax) = plt.subplots(1, 2, figsize=(11, 4))
    for label, per in sorted(data.items()):
        xs, ys = zip(*per[CURVES[0]])
        line, = ratio_ax.plot(xs, ys, marker="o", ms=3, lw=1.2, label=label)
        run = by_title[label]
        x = tested_at(run, history)
        if run.metrics.get(TEST) is not None and x is not None:  # hollow: stars that meet stay readable
            ratio_ax.plot([x], [run.metrics[TEST]], marker="*", ms=11, mfc="none", mew=1.3, color=line.get_color(),
                          ls="none", zorder=3)
        if per[CURVES[1]]:
            gx, gy = zip(*per[CURVES[1]])
            gap_ax.plot(gx, gy, marker="o", ms=3, lw=1.2, color=line.get_color(), label=label)
    ratio_ax.plot([], [], marker="*", ms=9, mfc="none", color="black", ls="none",
                  label="test ratio, at the tested weights' step")
    ratio_ax.axhline(1.0, color="black", lw=0.8, ls="--", label="1 = the training-mean predictor")
    gap_ax.axhline(1.0, color="black", lw=0.8, ls="--", label="1 = eval mode computes what training optimised")
    gap_ax.axhline(GAP_AT_MOST, color="grey", lw=0.8, ls=":",
                   label=f"{GAP_AT_MOST:.2f} = the most the memorisation self-test accepts")
    ratio_ax.set_ylabel("validation pair position L2 ÷ training mean's")
    gap_ax.set_ylabel("mode gap: eval-mode ÷ batch-statistics loss")
    for ax in (ratio_ax, gap_ax):
        ax.set_xlabel("image pairs seen")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    fig.suptitle("Training curves: every validation (☆ the run's test ratio, at the step of the weights tested)",
                 fontsize=9)
    fig.tight_layout()
    return [*save_figure(fig, Path(out) / "fig-training-curves", FORMATS), table]
