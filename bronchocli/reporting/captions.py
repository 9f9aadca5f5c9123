"""What a table says in words: a caption a journal would print, footnotes for the marks it uses, its source.

A table carries three texts (``table_model.Table``):

* ``caption`` — at most three sentences (``caption``): what is compared; what a
  cell is, the estimand in words; n with the unit of the evaluation (pairs,
  trajectories or frames) and the direction of the columns. The method
  (estimands, metrics, references, interval construction, tests) is the Methods
  page the report writes beside the tables (``methods.py``: methods.md,
  methods.tex), referenced by one phrase (``METHODS``) that the rendered
  caption links to that page (``methods_pointer``);
* footnotes (``footnotes``) — one per mark that appears in the table (bold,
  bold ≈, †, ‡, —), plus the notes the builder attached because they apply
  (rows with means only, latency definitions, differing numerics);
* ``source`` — where the numbers come from (sweep, seeds, budget,
  initialisation, numerics): printed after the footnotes, outside the table
  float of the LaTeX file.

Captions and footnotes name no internal key (tags, params, metric keys, file
paths): ``tests/reporting/test_captions.py`` fails when one does.
"""

from __future__ import annotations

from collections import Counter
from typing import Sequence

from .. import registry, runkeys
from ..runs.records import TAG_FINGERPRINT, TAG_INIT
from .collect import LOSS, RunRecord, stop_reasons
from .estimand import estimand_phrase
from .stats import ALPHA, MIN_SEEDS
from .table_model import IGNORES, MISSING, NOSKILL, TIE, Row, Table, cell_texts, marks

METHODS = "intervals and tests as in Methods"
METHODS_PAGE = "methods"  # the page METHODS refers to: methods.md / methods.tex beside the tables (methods.py)
POINTERS = {"md": f"[Methods]({METHODS_PAGE}.md)", "tex": f"Methods ({METHODS_PAGE}.tex)",
            "text": f"Methods ({METHODS_PAGE}.md)"}


def methods_pointer(text: str, fmt: str) -> str:
    """A rendered caption whose "as in Methods" names the page it refers to, in the table's format: a link to
    methods.md in Markdown, methods.tex in LaTeX, "(methods.md)" in the terminal. The caption itself (the
    table's model, checked for internal names) keeps the plain phrase."""
    return text.replace(METHODS, METHODS.replace("Methods", POINTERS[fmt]))
WHAT = {
    "accumulated": "the last-pose error of each test trajectory, its predicted relative poses chained from the true "
                   "first pose",
    "pair": "the error of each predicted relative pose between consecutive frames",
    "trajectory": "each test trajectory's tracking metric, its predicted relative poses chained from the true "
                  "first pose and every frame scored",
}
ERRORS = {"accumulated": "the errors of each test trajectory's last pose after chaining", "pair": "per-pair errors"}


def _span(values: Sequence[float], fmt: str = "{:,.0f}") -> str:
    lo, hi = min(values), max(values)
    return fmt.format(lo) if lo == hi else f"{fmt.format(lo)}–{fmt.format(hi)}"


def _model_rows(rows: Sequence[Row]) -> list[Row]:
    return [r for r in rows if r.kind == "model" and r.info.get("replicates")]


def seeds_phrase(rows: Sequence[Row]) -> str:
    """'3 seeds', '1 seed', '3–5 seeds' over the model rows with runs."""
    reps = [r.info["replicates"] for r in _model_rows(rows)]
    return f"{_span(reps)} seed{'s' if max(reps) > 1 else ''}" if reps else "the seeds"


def n_text(rows: Sequence[Row], evaluation: str, folds: Sequence[str] = ()) -> str:
    """'n = 3 seeds × 24 test trajectories (538 pairs)' with the evaluation's unit: pairs per pair, one final pose
    per trajectory accumulated, frames for tracking; the held-out patients for cross-subject."""
    model = _model_rows(rows)
    if not model:
        return ""
    trajs = [r.info["trajectories"] for r in model if r.info.get("trajectories")]
    pairs = [r.info["pairs"] for r in model if r.info.get("pairs")]
    text = f"n = {seeds_phrase(rows)}"
    if trajs:
        text += f" × {_span(trajs)} test trajectories"
        if folds:
            text += f" of {len(folds)} held-out patient{'s' if len(folds) > 1 else ''}"
        if evaluation == "pair" and pairs:
            text += f" ({_span(pairs)} pairs)"
        elif evaluation == "trajectory" and pairs:
            text += f" ({_span(pairs)} scored frames)"
        elif evaluation == "accumulated":
            text += " (one final pose each)"
    elif folds:
        text += f" ({len(folds)} held-out patients)"
    return text


def direction_text(higher: Sequence[str] = ()) -> str:
    return "lower is better" + (f" except {', '.join(higher)}" if higher else "")


def caption(what: str, rows: Sequence[Row], evaluation: str, unit: str, *, folds: Sequence[str] = (),
            higher: Sequence[str] = (), cell: str = "", direction: str = "") -> str:
    """The three sentences: ``what`` is compared; a cell (``cell``: what it holds, default the mean over seeds of
    the evaluation's error) with its estimand; n, direction (default: lower is better except ``higher``) and the
    method phrase."""
    cell = cell or f"mean over {seeds_phrase(rows)} of {WHAT[evaluation]}"
    estimand = estimand_phrase(unit, rows)
    second = f"Cells: {cell} [95% interval]" + (f", {estimand}" if estimand else "") + "."
    third = "; ".join(p for p in (n_text(rows, evaluation, folds), direction or direction_text(higher), METHODS)
                      if p)
    third = third if third.startswith("n = ") else third[0].upper() + third[1:]
    return " ".join([what.rstrip(".") + ".", second, third + "."])


def _columns_with(table: Table, mark: str) -> list[str]:
    mk = marks(table)
    return [c.title for j, c in enumerate(table.columns) if any(mark in row[j] for row in mk)]


def footnotes(table: Table) -> list[tuple[str, str]]:
    """(mark, text) for every mark that appears in the table, then the builder's notes (``table.notes``)."""
    mk = marks(table)
    used = {m for row in mk for cell in row for m in cell}
    out: list[tuple[str, str]] = []
    if "best" in used:
        out.append(("bold", f"significantly better than every other model row of its column (paired tests, "
                            f"Holm-adjusted, α = {ALPHA:g})."))
    if "tie" in used:
        reps = sorted({r.info["replicates"] for r in _model_rows(table.rows) if not r.info.get("refused")})
        at = f" at {'/'.join(map(str, reps))} seed{'s' if reps != [1] else ''}" if reps else ""
        out.append((f"bold{TIE}", f"tied for best: not significantly different from the lowest mean; no single "
                                  f"best{at} in {', '.join(_columns_with(table, 'tie')).rstrip('.')}."))
    if "noskill" in used:
        out.append((NOSKILL, "does not beat the better image-blind reference (paired comparison on the same test "
                             "units)."))
    if any("ignores" in r.flags for r in table.rows):
        out.append((IGNORES, "the model ignores its input: its predictions vary less than 5% of the ground "
                             "truth's."))
    texts = cell_texts(table)
    if any(t == MISSING for row, ts in zip(table.rows, texts) if row.kind == "model" for t in ts):
        out.append((MISSING, "no finished run (see the warnings)."))
    return out + [("", n) for n in table.notes]


def fixed_seeds_note(rows: Sequence[Row]) -> str:
    """Rows with fewer than MIN_SEEDS seeds among rows with more: their estimand is their trained models."""
    model = _model_rows(rows)
    few = [r for r in model if r.info["replicates"] < MIN_SEEDS]
    if not few or len(few) == len(model):
        return ""
    if all(r.info["replicates"] == 1 for r in few):
        return (f"Rows with one seed ({', '.join(r.name for r in few)}): about that one trained model, the interval "
                f"covers new test units only, not new seeds.")
    return (f"Rows with fewer than {MIN_SEEDS} seeds ({', '.join(r.name for r in few)}): about those trained "
            f"models (seeds fixed), the interval covers new test units only, not new seeds.")


def budget_text(runs: Sequence[RunRecord]) -> str:
    """Optimiser steps, pairs seen, epochs and stop reasons of the runs behind a table."""
    if not runs:
        return ""

    def got(name: str) -> list[float]:
        return [float(r.metrics[name]) for r in runs if name in r.metrics]

    steps, seen, epochs = (got(runkeys.train(k)) for k in ("steps", "pairs_seen", "epochs"))
    parts = []
    if steps:
        parts.append(f"{_span(steps)} optimiser steps")
    if seen:
        parts.append(f"{_span(seen)} pairs seen (batch × steps)")
    if epochs:
        parts.append(f"{_span(epochs, '{:.1f}')} epochs")
    reasons = Counter(stop_reasons(runs))
    stop = ", ".join(f"{k} {v}" for k, v in sorted(reasons.items()))
    text = "Budget per run: " + (", ".join(parts) if parts else "not logged")
    return text + f"; stop reasons: {stop}."


def init_text(runs: Sequence[RunRecord]) -> str:
    """How the runs' backbones were initialised (their init tag): random, ImageNet or a file."""
    if not runs:
        return ""
    seen = Counter(r.tag(TAG_INIT) for r in runs)
    parts = []
    for init, n in sorted(seen.items()):
        if init == "random":
            what = "random weights (no pretrained backbone)"
        elif init.startswith("imagenet:"):
            what = f"ImageNet weights (the file {init.split(':', 1)[1]})"  # torchvision's or a package's
        elif init.startswith("file:"):
            what = f"weights from the file {init.split(':', 1)[1]}"
        else:
            what = "not recorded (runs made before the init tag: random unless model.pretrained was set)"
        parts.append(what + (f" ({n} of {len(runs)} runs)" if len(seen) > 1 else ""))
    return "Backbone initialisation: " + "; ".join(parts) + "."


def rot_scale_text(runs: Sequence[RunRecord]) -> str:
    """How the runs trained with a bounded rotation loss (DE, CE: not ``scaled`` in the registry) weighed it
    (``train.rot_scale``): in units of one label std, or as the paper writes it (runs logged before the setting
    existed trained so). Empty without such runs."""
    names = registry.rot_loss_names()
    bounded = [r for r in runs if r.identity[LOSS] in names and not registry.rot_loss(r.identity[LOSS]).scaled]
    if not bounded:
        return ""
    seen = Counter(r.params.get("train.rot_scale", "none") for r in bounded)
    words = {"label_std": "divided by their value at one label std of error, as MSE's squared errors are "
                          "(train.rot_scale label_std)",
             "none": "as the paper writes them, unscaled (train.rot_scale none)"}
    parts = [words.get(k, k) + (f" ({n} of {len(bounded)} runs)" if len(seen) > 1 else "")
             for k, n in sorted(seen.items())]
    return "Rotation losses DE and CE: " + "; ".join(parts) + "."


FINGERPRINT_CHARS = 12  # of the dataset's SHA-256 fingerprint: enough to tell datasets apart in a source line


def dataset_text(runs: Sequence[RunRecord]) -> str:
    """Which dataset the runs trained and were tested on: its fingerprint (dataset.json's, the runs' tag).

    The same config and seed give the same poses on every host (docs/reproduction.md, "One seed, one
    dataset"); a reader who regenerates the data compares this with ``bronchopose data stats``'s fingerprint.
    """
    if not runs:
        return ""
    seen = Counter(r.tag(TAG_FINGERPRINT)[:FINGERPRINT_CHARS] or "not recorded" for r in runs)
    if len(seen) == 1:
        return f"Dataset fingerprint {next(iter(seen))}."
    each = "; ".join(f"{fp} ({n} of {len(runs)} runs)" for fp, n in sorted(seen.items()))
    return f"Dataset fingerprints differ between runs (not one dataset): {each}."
