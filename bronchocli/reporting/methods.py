"""The Methods page the tables' captions point to ("as in Methods"): ``methods.md`` and ``methods.tex`` in reports/.

``bronchopose report`` writes it beside the tables it writes (``write_methods``), in the same formats, so a
reviewer who reads a caption finds the page it names in the same folder, and a paper can paste it. It is made
from the code's own definitions, not typed prose that could drift from them:

* the metrics (which, their units and direction) from ``registry.py``; what each measures from the docstring of
  the function that computes it (``metrics.py``); the std convention from ``metrics.Stat``;
* the image-blind references and their names from ``runkeys.REFERENCES`` / ``aggregate.REFERENCES``;
* the interval level, α, the seed and patient minimums, the zero shift from ``stats`` and ``sample``; the
  estimands' names from ``estimand.ESTIMAND_NAMES``; the marks from ``table_model``; the "ignores its input"
  share from ``judge.IGNORES_RATIO``.

The words around them live here and only here: docs/reports.md points to the page instead of repeating it.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .. import metrics, registry
from ..io import write_text
from ..metrics import Stat
from .aggregate import REFERENCES
from .captions import METHODS_PAGE
from .estimand import ESTIMAND_NAMES
from .judge import IGNORES_RATIO
from .latex import PREAMBLE, escape
from .stats import ALPHA, LEVEL, MIN_PATIENTS, MIN_SEEDS, PATIENT, TRAJECTORY, ZERO_SHIFT
from .table_model import IGNORES, MISSING, NOSKILL, TIE

Block = tuple[str, object]  # ("h", title) | ("p", text) | ("items", [text, ...]) | ("table", (header, rows))


def _pct(x: float) -> str:
    return f"{100 * x:g} %"


def definition(spec: registry.MetricSpec) -> str:
    """What a metric measures: the first paragraph of its function's docstring, else its label and unit."""
    fn = spec.function if callable(spec.function) else getattr(metrics, spec.function, None)
    doc = inspect.getdoc(fn) if fn is not None else None
    if not doc:
        return f"{spec.label} ({spec.unit})"
    text = " ".join(doc.split("\n\n")[0].split())
    head, sep, rest = text.partition(": ")
    return rest[0].upper() + rest[1:] if sep and head in (spec.label, spec.name.upper()) else text


def _metric_rows() -> list[list[str]]:
    rows = []
    for spec in registry.metric_specs(per="pose", table="paper"):
        unit = spec.symbol or spec.unit
        rows.append([spec.label, definition(spec), unit, "higher" if spec.higher_is_better else "lower"])
    return rows


def blocks() -> list[Block]:
    """The page's content, one list for both formats."""
    zero, mean = (REFERENCES[k] for k in ("zero_motion", "train_mean"))
    level = _pct(LEVEL)
    std = "divisor n" if Stat.of(np.array([0.0, 2.0])).std == 1.0 else "divisor n − 1"  # what Stat computes
    return [
        ("h", "Methods"),
        ("p", "This page defines what every table of this report shows; the captions' “as in Methods” refers to "
              "it. It is written by the report from the definitions in the code that computed the tables."),
        ("h", "Estimands"),
        ("p", "A model predicts the relative pose ΔP = (Δx, Δy, Δz, Δα, Δβ, Δγ) between two consecutive frames of "
              "a test trajectory. Every error is scored in two ways:"),
        ("items", [
            "Per pair: the error of each predicted relative pose against the true one; a run's figure is the mean "
            "over all pairs of all its test trajectories.",
            "Accumulated: the predicted relative poses are chained from the true first pose along the whole "
            "trajectory (summed for world-frame relative poses, composed for camera-frame ones) and only the last "
            "pose is scored; a run's figure is the mean over its test trajectories.",
        ]),
        ("p", "A table cell is the mean over training seeds of these run-level figures (for a cross-subject row, "
              "the runs of one seed over the held-out patients count as one replicate). Its interval and tests "
              f"are about one of two estimands, which the caption names: “{ESTIMAND_NAMES[TRAJECTORY]}” (new "
              "seeds and new test trajectories of the patients tested; personalized tables) or "
              f"“{ESTIMAND_NAMES[PATIENT]}” (new seeds, patients and their trajectories; cross-subject tables)."),
        ("h", "Metrics and units"),
        ("table", (["Metric", "Definition", "Unit", "Better"], _metric_rows())),
        ("p", f"Position errors are in voxels of the airway volume (millimetres where a table says so, from each "
              f"patient's voxel spacing), rotation L2 in degrees, DE in radians, CE unitless. Where a run logs a "
              f"mean ± std over pairs or trajectories, the std is the population standard deviation ({std})."),
        ("h", "Image-blind references, ratios and skill"),
        ("items", [
            f"{zero}: every relative pose is zero (the camera does not move).",
            f"{mean}: every relative pose is the mean relative pose of the training set, in the run's pose frame.",
        ]),
        ("p", "Both are scored like a model, with the same metrics on the same test trajectories, and end every "
              "table. A ratio is a model's error divided by a reference's on the same test units (below 1 beats "
              f"it). Skill = 1 − error ÷ the error of the better reference (the lower mean): 0 is no better than an "
              "image-blind model, 1 is perfect, negative is worse than the reference."),
        ("h", "Intervals"),
        ("p", f"Each cell's {level} interval is for its estimand, from variance components estimated by moments "
              "(no resampling): a seed part per row, a unit part (test trajectories, or patients for a new "
              "patient, each trajectory first averaged into its patient) shared by rows that share their units, "
              "with Satterthwaite's degrees of freedom. Errors (positive, right-skewed) take Cox's lognormal-mean "
              f"interval on the log scale (errors with exact zeros: log(error + c), c = {ZERO_SHIFT:g} × the cell "
              "mean), shares in % the logit scale, skill the log-ratio scale by the delta method, so a skill "
              "interval never exceeds 1."),
        ("p", f"Rows with fewer than {MIN_SEEDS} seeds are read for their trained models (seeds fixed): the "
              f"interval covers new test units only. A new-patient estimand resting on fewer than {MIN_PATIENTS} "
              f"patients shows means only ({MISSING} for what is not computed): no interval, no mark, no skill."),
        ("h", "Tests and marks"),
        ("items", [
            "Bold: in each column every two model rows are compared by a paired t test on their shared test "
            f"units (Welch-Satterthwaite, two-sided), Holm-adjusted over all pairs at α = {ALPHA:g}; a row is "
            "bold when it is significantly better than every other row.",
            f"Bold with {TIE}: tied for best, not significantly different from the lowest mean; no single best is "
            "claimed in that column.",
            f"{NOSKILL}: the row has not shown that it learnt anything from the images. Its one paired comparison "
            "with the better reference on their shared test units (skill on the log-ratio scale for errors, the "
            f"difference for shares) has a {level} interval that does not lie above 0 (per cell, no "
            "multiplicity correction; the skill figures colour their bars by the same verdict). A row with means "
            f"only is marked {NOSKILL} when its interval does not lie below the better reference's mean.",
            f"{IGNORES} after a label: the model ignores its input; its predictions vary less than "
            f"{_pct(IGNORES_RATIO)} of the ground truth's.",
        ]),
    ]


def to_markdown() -> str:
    out: list[str] = []
    for kind, body in blocks():
        if kind == "h":
            out += [("# " if body == "Methods" else "## ") + str(body), ""]
        elif kind == "p":
            out += [str(body), ""]
        elif kind == "items":
            out += [f"- {item}" for item in body] + [""]  # type: ignore[union-attr]
        else:
            header, rows = body  # type: ignore[misc]
            out += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
            out += ["| " + " | ".join(r) + " |" for r in rows] + [""]
    return "\n".join(out)


def to_latex() -> str:
    """A document pdflatex compiles (the tables' preamble); the section between the ``% --- methods`` markers is
    what a paper pastes (``\\label{sec:methods}``)."""
    out: list[str] = [PREAMBLE + "% --- methods begins"]
    for kind, body in blocks():
        if kind == "h":
            out += [r"\section{Methods}\label{sec:methods}" if body == "Methods" else
                    rf"\subsection*{{{escape(str(body))}}}", ""]
        elif kind == "p":
            out += [escape(str(body)), ""]
        elif kind == "items":
            out += [r"\begin{itemize}"] + [rf"\item {escape(i)}" for i in body] + [r"\end{itemize}", ""]  # type: ignore[union-attr]
        else:
            header, rows = body  # type: ignore[misc]
            out += [r"\begin{tabular}{@{}lp{0.55\linewidth}ll@{}}", r"\toprule",
                    " & ".join(escape(h) for h in header) + r" \\", r"\midrule"]
            out += [" & ".join(escape(c) for c in r) + r" \\" for r in rows] + [r"\bottomrule", r"\end{tabular}", ""]
    return "\n".join(out + ["% --- methods ends", r"\end{document}", ""])


RENDERERS: dict[str, Callable[[], str]] = {"md": to_markdown, "tex": to_latex}


def write_methods(out: Path, suffixes: tuple[str, ...] | list[str]) -> list[Path]:
    """``methods.<suffix>`` under ``out`` for each table format written."""
    return [write_text(Path(out) / f"{METHODS_PAGE}.{s}", RENDERERS[s]()) for s in suffixes]
