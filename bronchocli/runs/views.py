"""What a run shows when it is reviewed in the MLflow UI: comparable params, headline metrics, source, parents.

MLflow's compare view, parallel coordinates and "show diff only" work on
params, so a run logs as params what tells runs apart, not the whole config:

* the cell's coordinates (arch, rot_loss, population, fold, seed, pose_frame,
  train_trajectories; a coordinate that is None is left out);
* the run settings (``config.RUN_SECTIONS`` without ``dataset``, which the
  dataset input identifies) that differ from the built-in defaults, plus every
  ``tune.space`` path and ``model.pretrained``: what a tuned or hand-edited
  run changed (speed settings such as ``train.threads`` included: they
  explain timing differences).

The evaluation's constants (``eval_params``: the CTF thresholds and the RPE gap,
``EVAL_PARAMS``) are params too, logged with the test metrics they were computed
with; runs logged before they were params have them as metrics of the same name,
and ``config_value`` reads either.

The full resolved config stays the ``config.yaml`` artifact; the splits and
dataset settings (the same on every run of a sweep) go on the sweep's parent
run, beside what its plan ran (``sweep/summary.py``: stages and cells, not the
config's grid lists, which stages and selections override). The coordinates stay tags too: report, status and the
sweep find runs by tags.

Reference figures (``reference_figures``): the image-blind references as ratios,
``ratio.<ref>.<eval>.<m> = error / reference error`` for both references, and
``skill.<eval>.<m> = 1 - error / reference error`` against the better
(lower-error) of the two, as the report's skill figures define it (one name
per figure: a skill against one reference is 1 - its ratio, so it is not
logged). ``ratio.train_mean.pair.pos_l2`` (``HEADLINE``) is the figure the
README quotes and the runs table's sort key. They are logged before the other
test metrics.

The runs table (``runs_table_url``, what ``bronchopose ui`` prints) opens on a
saved view of the experiment (``headline_view``): MLflow 3 reads a view from
the experiment tag ``mlflow.sharedViewState.<key>`` named by the URL's
``viewStateShareKey`` (JSON of its search facets -- ``searchFilter``,
``orderByKey``, ``orderByAsc``, ... -- and table state -- ``selectedColumns``,
``columnWidths``, ...), stored in the saved-view envelope its "Views > Save as
new view" writes (``saved_view``), so its Views menu lists it by name. The view shows
the runs that trained (no sweep/study/selection parents, so nothing is nested
and collapsed), one row per run sorted by the headline, best first, with the
headline figures as columns (logged to 4 significant digits: MLflow shows a
metric whole): the accumulated position ratio (the paper's headline scope)
beside the per-pair one, the skills of both, and the ``vs_references`` tag
(``verdict``: † where a scope does not beat the better reference); its "Chart" view opens with the training and validation curves
as the first section, the headline figures a point per run the second
(``chart_sections``). ``bronchopose ui`` also stores the view as the
experiment's table state in a browser that has none, and a run page's chart
layout (``run_page_layout``: ``uiapp``). Run names (``records.run_name``) are the model's
one name and the seed first, within the name column's width (``RUN_NAME_WIDTH``).

Parent runs are in ``parents.py``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping

from .. import registry, runkeys
from ..cells import Cell
from ..config import RUN_SECTIONS, Config
from .records import flatten

# the backbone and its initialisation: params even at their defaults (the paper's B0, random)
# Logged by every run even at their defaults: what tells models apart, and what a missing param would misname
# (a run logged before train.rot_scale existed trained with DE/CE unscaled; the default now is label_std).
ALWAYS = ("model.backbone", "model.pretrained", "train.rot_scale")
# Constants of the test evaluation (config eval:), params of every FINISHED run (metrics on runs logged before).
EVAL_PARAMS = tuple(runkeys.evaluation(k) for k in ("ctf_position", "ctf_position_mm", "ctf_angle", "rpe_gap"))
PARENT_SECTIONS = ("name", "splits", "dataset")  # shown as params on a sweep's parent (the plan: sweep/summary.py)

REFERENCES = runkeys.REFERENCES
HEADLINE_EVALS = ("pair", "acc")
HEADLINE_METRICS = ("pos_l2", "rot_l2")
README_RATIO = runkeys.HEADLINE  # pair position error / the training-mean reference's (runkeys.py)
HEADLINE = README_RATIO  # the runs table's sort key (lower is better)
# Metric columns of the runs table's view. MLflow shows a group's columns sorted by name (a saved column order
# is not applied when the table opens), so these are chosen to sort headline first. Every one is comparable across
# rows (ratios and skills against the image-blind references): no loss, whose scale differs between rotation losses
# (CE, DE and MSE losses rank runs differently from the headline).
# The paper's headline is the accumulated position error: its ratio and skill sit beside the per-pair ones (the
# accumulated ratio sorts first), and the tag ``TAG_VERDICT`` marks with † a figure that does not beat the references.
ACC_RATIO = runkeys.ratio("pos_l2", "acc")
VIEW_METRICS = (ACC_RATIO, README_RATIO, runkeys.skill("pos_l2", "acc"), runkeys.skill("pos_l2"))
TAG_VERDICT = "vs_references"  # "pair ✓ · acc †": per headline scope, whether the run beats the better reference
DAGGER = "†"  # does not beat the better image-blind reference (skill <= 0), as the report's tables mark it
BEATS = "✓"
# The charts. MLflow 3.17 makes one chart per metric, sorted by name, in one "Model metrics" section (a metric
# named "prefix/name" gets a section "prefix"; ours have none): the curves among ~160 one-value bars. A chart
# layout is what MLflow saves of them: the runs table's Chart view keeps it in the view (compareRunSections and
# compareRunCharts of the experiment's saved state), a run's page in the browser's localStorage only (nothing on
# the server presets it: `bronchopose ui`'s page stores ``run_page_layout`` where a run has none, ``uiapp``).
# Each opens on the training and validation curves, then what MLflow appends (isAccordionReordered keeps the
# order). The losses are drawn on a log axis: runs of different rotation losses (CE, DE, MSE) differ in scale.
CURVE_METRICS = (runkeys.TRAIN_LOSS, runkeys.VAL_LOSS, runkeys.VAL_RATIO, runkeys.VAL_MODE_GAP)
LOG_SCALE = (runkeys.TRAIN_LOSS, runkeys.VAL_LOSS)
CURVES_SECTION = "Training and validation curves"
HEADLINE_SECTION = "Headline (test, vs the image-blind references)"
# The view's headline charts: scatter plots, a point per run (a bar chart's axis starts at 0 and hides differences
# of ratios near 1): position against rotation skill, and the position ratio to either reference
HEADLINE_SCATTERS = ((README_RATIO, ACC_RATIO), (runkeys.skill("pos_l2"), runkeys.skill("pos_l2", "acc")))
RUN_NAME_WIDTH = 290  # px: "+ConvRNN MSE+DE · s0 · pers · world" whole (model, loss and seed at least)
HEADLINE_DIGITS = 4  # significant digits of the logged ratios and skills (MLflow shows a metric's value whole)
VIEW_KEY = "bronchopose-headline"
VIEW_NAME = "Headline: best first"  # its name in the runs table's Views menu
SHARED_VIEW_TAG = "mlflow.sharedViewState."  # MLflow's prefix; the URL's viewStateShareKey names the rest
PARENT_KINDS = ("sweep", "study", "selection")  # run_kind tags of runs that did not train


# -- params -------------------------------------------------------------------------------------------


def cell_params(cell: Cell) -> dict[str, str]:
    """The cell's coordinates as params (None left out: MLflow shows a missing param as blank)."""
    return {k: str(v) for k, v in cell.coords().items() if v is not None}


def _run_settings(cfg: Config) -> dict[str, str]:
    data = cfg.model_dump(mode="json")
    sig = {k: data[k] for k in RUN_SECTIONS if k != "dataset"}
    sig["data"].pop("cache_dir", None)  # where frames are cached: a path, not a setting of the run
    return flatten(sig)


def run_params(cfg: Config, cell: Cell) -> dict[str, str]:
    """What a run logs as params: coordinates, run settings that differ from the defaults, tuned paths, and
    ``ALWAYS`` (what tells models apart even at its default)."""
    ours = _run_settings(cfg)
    defaults = _run_settings(Config(name=cfg.name))
    keep = set(cfg.tune.space) | set(ALWAYS)
    out = {k: v for k, v in ours.items() if k in keep or defaults.get(k) != v}
    return {**out, **cell_params(cell)}


def eval_params(cfg: Config) -> dict[str, str]:
    """The evaluation's constants as params (``EVAL_PARAMS``, every one, defaults included): what the tracking
    table's caption states. Logged with the test metrics (the values they were computed with)."""
    values = flatten({"eval": cfg.eval.model_dump(mode="json")})
    return {k: values[k] for k in EVAL_PARAMS}


def config_value(params: Mapping[str, str], metrics: Mapping[str, float], key: str) -> float | None:
    """A numeric constant a run logged as the param ``key``, or, on runs logged before it was a param, as the
    metric ``key``; None when it has neither (or the param is not a number)."""
    if key in params:
        try:
            return float(params[key])
        except ValueError:
            return None
    value = metrics.get(key)
    return None if value is None else float(value)


def parent_params(cfg: Config) -> dict[str, str]:
    """A sweep's settings shared by every cell, for its parent run (what the plan ran: ``sweep/summary.py``). The
    CSV import's column names (``dataset.csv``) only where the dataset is a CSV import: elsewhere they are settings
    nothing read."""
    data = cfg.dump()
    sections = {k: data[k] for k in PARENT_SECTIONS if k in data}
    dataset = sections.get("dataset")
    if isinstance(dataset, dict) and dataset.get("format") != "csv":
        sections["dataset"] = {k: v for k, v in dataset.items() if k != "csv"}
    return flatten(sections)


# -- metrics ------------------------------------------------------------------------------------------


def reference_figures(metrics: Mapping[str, float]) -> dict[str, float]:
    """Ratios against both references and skills against the better one, README ratio first (missing inputs:
    left out)."""
    out: dict[str, float] = {}
    for ev in HEADLINE_EVALS:
        for m in HEADLINE_METRICS:
            if runkeys.metric(m, ev) not in metrics:
                continue
            ratios = {r: runkeys.ratio_value(metrics, m, ev, r) for r in REFERENCES}
            out |= {runkeys.ratio(m, ev, r): v for r, v in ratios.items() if v is not None}
            known = [metrics[runkeys.metric(m, ev, ref=r)] for r, v in ratios.items() if v is not None]
            if known:
                out[runkeys.skill(m, ev)] = 1.0 - metrics[runkeys.metric(m, ev)] / min(known)
    first = {k: out[k] for k in (README_RATIO, runkeys.skill("pos_l2"), runkeys.skill("rot_l2")) if k in out}
    return {**first, **out}


def verdict(metrics: Mapping[str, float]) -> str:
    """The ``TAG_VERDICT`` of a run's test metrics: per headline scope (pair, acc), ``BEATS`` where its position
    error is below the better image-blind reference's (skill > 0), ``DAGGER`` where not, as the report's tables
    mark a row (there with a paired test over the seeds' trajectories; here one run's means): "pair ✓ · acc †"."""
    h = reference_figures(metrics)
    parts = [f"{ev} {BEATS if h[k] > 0 else DAGGER}" for ev in HEADLINE_EVALS
             if (k := runkeys.skill("pos_l2", ev)) in h and math.isfinite(h[k])]
    return " · ".join(parts)


def rounded(value: float, digits: int = HEADLINE_DIGITS) -> float:
    """``value`` to ``digits`` significant digits (a float whose shortest form has no more)."""
    return float(f"{value:.{digits}g}") if math.isfinite(value) else value


def ordered_metrics(metrics: Mapping[str, float]) -> list[dict[str, float]]:
    """The test metrics in logging batches: headline ratios/skills (rounded to ``HEADLINE_DIGITS``: the runs table
    shows them as logged; the errors they come from keep every digit) and the headline errors, then the rest."""
    head = {k: rounded(v) for k, v in reference_figures(metrics).items()}
    errors = [runkeys.metric(m, ev) for ev in HEADLINE_EVALS for m in HEADLINE_METRICS]
    head |= {k: metrics[k] for k in errors if k in metrics}
    rest = {k: v for k, v in metrics.items() if k not in head}
    return [head, rest]


def text_figure(value: float, digits: int = HEADLINE_DIGITS) -> str:
    """A figure as the platform writes it into text the UI shows (run and parent descriptions): ``digits``
    significant digits, trailing zeros kept (``0.8400``, ``12.30``, ``1235``), "n/a" for NaN."""
    if not math.isfinite(value):
        return "n/a" if math.isnan(value) else str(value)
    text = f"{value:#.{digits}g}"
    return text[:-1] if text.endswith(".") else text


def describe(cell: Cell, metrics: Mapping[str, float] | None = None, dataset: str = "", backbone: str | None = None,
             init: str | None = None) -> str:
    """The run's description (``mlflow.note.content``, Markdown): the model's one name (``registry.model_name``:
    ``backbone`` and ``init`` as the run's), population and seed first, then, once done, its result (the headline first, figures at ``HEADLINE_DIGITS`` significant
    digits), then the setting; the cell's key and the metric keys last, never the first words a reviewer reads."""
    who = (f"**{registry.model_name(cell.arch, cell.rot_loss, backbone, init)}**, {cell.population}"
           + (f" (test patient {cell.fold})" if cell.fold else "") + f", seed {cell.seed}")
    setting = (f"{cell.pose_frame}-frame relative poses"
               + (f", {cell.train_trajectories} training trajectories per patient and lobe"
                  if cell.train_trajectories else "") + (f"; dataset {dataset}" if dataset else "")
               + f"; cell `{cell.label}`.")
    if not metrics or runkeys.HEADLINE_ERROR not in metrics:
        return f"{who}: {setting}"
    h = reference_figures(metrics)

    def ratio(scope: str, ref: str = "train_mean") -> str:
        return text_figure(h.get(runkeys.ratio("pos_l2", scope, ref), math.nan))

    def skill(name: str, scope: str = "pair") -> str:
        return text_figure(h.get(runkeys.skill(name, scope), math.nan))

    error, acc_error = (text_figure(metrics.get(k, math.nan)) for k in (runkeys.HEADLINE_ERROR,
                                                                         runkeys.metric("pos_l2", "acc")))
    lines = [
        f"{who}: pair position error **{ratio('pair')} ×** the training-mean reference's (the headline: below 1 "
        f"beats predicting the training set's mean motion for every pair; lower is better); accumulated "
        f"(whole trajectories, last pose) **{ratio('acc')} ×**.",
        f"Test: pair position error {error} vox ({ratio('pair', 'zero_motion')} × "
        f"zero motion's); skill vs the better reference: position {skill('pos_l2')}, rotation {skill('rot_l2')}; "
        f"accumulated position error {acc_error} vox "
        f"({ratio('acc', 'zero_motion')} × zero motion's, skill {skill('pos_l2', 'acc')}).",
        f"{setting[0].upper()}{setting[1:]} Headline metric: `{HEADLINE}`.",
    ]
    return "\n\n".join(lines)


# -- the UI ------------------------------------------------------------------------------------------------


def _column(kind: str, name: str) -> str:
    return f"{kind}.`{name}`"  # MLflow's canonical column/sort key (makeCanonicalSortKey)


def _line(metric: str, section: str) -> dict:
    """A chart of one metric per step, as MLflow's RunsChartsLineCardConfig serialises it."""
    return {"uuid": f"bronchopose-line-{metric}", "type": "LINE", "runsCountToCompare": 10, "metricSectionId": section,
            "deleted": False, "isGenerated": False, "displayName": metric, "metricKey": metric, "lineSmoothness": 0,
            "xAxisScaleType": "linear", "scaleType": "log" if metric in LOG_SCALE else "linear", "range": {},
            "xAxisKey": "step", "selectedXAxisMetricKey": "", "yAxisKey": "metric", "yAxisExpressions": [],
            "ignoreOutliers": False, "useGlobalXaxisKey": True, "useGlobalLineSmoothing": True}


def _scatter(x: str, y: str, section: str) -> dict:
    """A point per run, ``x`` against ``y`` (MLflow's RunsChartsScatterCardConfig; axes fit the points)."""
    return {"uuid": f"bronchopose-scatter-{x}-{y}", "type": "SCATTER", "runsCountToCompare": 100,
            "metricSectionId": section, "deleted": False, "isGenerated": False,
            "xaxis": {"key": x, "type": "METRIC"}, "yaxis": {"key": y, "type": "METRIC"}}


def _sections(sections: dict[str, str]) -> list[dict]:
    return [{"uuid": uuid, "name": name, "display": True, "isReordered": True, "deleted": False, "isGenerated": False}
            for uuid, name in sections.items()]


def chart_sections() -> dict:
    """The view's charts: the training and validation curves (``CURVE_METRICS``) first, then the headline figures
    (``HEADLINE_SCATTERS``)."""
    return {"isAccordionReordered": True,  # MLflow keeps these sections' order, adding any other after them
            "compareRunSections": _sections({"bronchopose-curves": CURVES_SECTION,
                                             "bronchopose-headline": HEADLINE_SECTION}),
            "compareRunCharts": [*(_line(m, "bronchopose-curves") for m in CURVE_METRICS),
                                 *(_scatter(x, y, "bronchopose-headline") for x, y in HEADLINE_SCATTERS)]}


def run_page_layout() -> dict:
    """A run page's "Model metrics" charts as MLflow 3.17 saves them for a run (RunPage's chartUIState, MLflow's
    defaults besides the charts): the training and validation curves first; MLflow adds a chart of every other
    metric after them (isAccordionReordered), in its own sections."""
    return {"isAccordionReordered": True, "autoRefreshEnabled": True,
            "globalLineChartConfig": {"xAxisKey": "step", "lineSmoothness": 0, "selectedXAxisMetricKey": ""},
            "compareRunSections": _sections({"bronchopose-curves": CURVES_SECTION}),
            "compareRunCharts": [_line(m, "bronchopose-curves") for m in CURVE_METRICS]}


def headline_view() -> dict:
    """The saved view the link opens: runs that trained, best headline first, one row per run with the headline
    figures as columns (rounded: ``HEADLINE_DIGITS``), and the charts of ``chart_sections``. Not grouped: MLflow
    shows a group's mean with every digit of the sum it computes, and draws groups rather than runs."""
    metrics = [_column("metrics", m) for m in VIEW_METRICS]
    verdict = _column("tags", TAG_VERDICT)
    return {
        "searchFilter": " and ".join(f"tags.run_kind != '{k}'" for k in PARENT_KINDS),
        "orderByKey": _column("metrics", HEADLINE),
        "orderByAsc": True,
        "selectedColumns": [*metrics, verdict],
        # MLflow applies widths to the columns listed in columnOrder only (its order inside a group is ignored)
        "columnOrder": [_column("attributes", "Run Name"), *metrics, verdict],
        "columnWidths": {_column("attributes", "Run Name"): RUN_NAME_WIDTH,  # model, loss and seed whole
                         **{c: 24 + 7 * len(m) for c, m in zip(metrics, VIEW_METRICS)},  # headers whole
                         verdict: 24 + 7 * len(TAG_VERDICT)},
        "groupBy": None,
        "useGroupedValuesInCharts": False,  # the charts draw runs
        **chart_sections(),  # the Chart view: the training and validation curves first, then the headline
    }


def saved_view(view: dict, created_ms: int, name: str = VIEW_NAME) -> str:
    """The value of the experiment tag ``SHARED_VIEW_TAG + VIEW_KEY``: MLflow 3.17's saved-view envelope (what its
    runs table's "Views > Save as new view" writes: ``name``, ``createdAt``/``updatedAt`` in ms and the view's JSON
    as the string ``state``), so the view is listed by name in the table's Views menu as well as opened by the
    link's ``viewStateShareKey``."""
    return json.dumps({"name": name, "createdAt": created_ms, "updatedAt": created_ms, "state": json.dumps(view)})


def runs_table_fragment(experiment_id: str, view: str | None = VIEW_KEY) -> str:
    """The UI route (a URL's fragment) of the experiment's runs table in the model-training view, on ``view``."""
    route = f"#/experiments/{experiment_id}/runs?workflowType=machine_learning"
    return route + (f"&viewStateShareKey={view}" if view else "")


def runs_table_url(base: str, experiment_id: str, view: str | None = VIEW_KEY) -> str:
    """The experiment's runs table in MLflow 3's model-training view (not the GenAI overview), on ``view``."""
    return f"{base.rstrip('/')}/{runs_table_fragment(experiment_id, view)}"
