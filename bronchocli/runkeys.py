"""Every run metric key, built in one place, and the headline, defined once.

A run's metric keys are data: a store written by an earlier version is read with the same keys, so a key
built here never changes spelling. What runs log (training, its validations, the test evaluation) and what
reads them (``runs.views``: the description and the UI's saved view; ``report`` and ``track --best``;
``status``; a sweep's and a study's parent; ``tune``'s objectives) build their keys with these functions; no
module spells a key itself (``tests/test_runkeys.py`` greps the package for one). The metrics' own names
(``pos_l2``, ``ctf``, ...) come from ``registry.py``.

The families (what each means: docs/training.md, "MLflow"):

==================  ==============================================  ==========================
family              keys                                            built by
==================  ==============================================  ==========================
test evaluation     ``pair.pos_l2.mean``, ``acc.de.std``,           :func:`metric`
                    ``traj.ctf.mean``; a reference's:
                    ``train_mean.pair.pos_l2.mean``
test size           ``test.n_pairs``, ``test.n_trajectories``       :func:`count`
errors table        ``model.pair.pos_l2`` (trajectory_errors.csv)   :func:`column`
headline            ``ratio.train_mean.pair.pos_l2``,               :func:`ratio`, :func:`skill`
                    ``skill.pair.rot_l2``
prediction spread   ``pred.std.pos``, ``pred.std_ratio.rot``        :func:`spread`
validation          ``val_loss``, ``val.pos_l2``,                   :func:`val`, :func:`best_of`
                    ``val.ratio.pos_l2``; of the tested weights:
                    ``val_best.loss``, ``val_best.pos_l2``
evaluation          ``eval.mode_gap``, ``eval.time_s``; the         :func:`evaluation`
                    thresholds' params ``eval.ctf_angle``, ...
training            ``train.steps``, ``train.pairs_seen``, ...;     :func:`train`,
                    the torch threads at each validation            ``THREADS``,
                    ``threads``; each resume ``resumed_from_step``  ``RESUMED_FROM_STEP``
cost of learning    ``cost.pairs_to_0.90``, ...                     :func:`cost`
a sweep's parent    ``cells.planned``, ``cells.finished``,          :func:`cells`, :func:`best`
                    ``cells.failed``; a stage's best cell:
                    ``best.<stage>.val_best.loss``, ...
a study's parent    ``trials.complete``, ``trials.pruned``, ...;    :func:`trials`,
                    ``importance.<path>``; the objective            :func:`importance`
==================  ==============================================  ==========================

A parent's tags beside those metrics share their prefixes and are built here too: a stage's best cell and run
(``best.<stage>.cell``, ``best.<stage>.run``: :func:`best`) and a study's best value of each searched path
(``best.<path>``: :func:`best_value`).

The headline (``HEADLINE``) is the test pair position error divided by the training-mean reference's on the
same test pairs: below 1 beats predicting the training set's mean motion for every pair. "Headline" means
that one figure and nothing else. Runs log it with the other ratios and skills (``runs.views.reference_figures``);
the runs table sorts by it, ``track --best`` ranks by it, a sweep's parent shows it beside each stage's best
cell, ``train`` ends with it. :func:`headline` is the one computation of it (NaN unless the reference's error
is a positive finite number), from the two logged errors, so a run logged before the ratio was a metric has
one too.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

SCOPES = ("pair", "acc", "traj")  # per image pair / accumulated (trajectory endpoints) / per trajectory
MODEL = "model"  # the model's source in the errors table; its MLflow keys carry no source
REFERENCES = ("zero_motion", "train_mean")  # the image-blind references (training/evaluate.py)
SOURCES = (MODEL, *REFERENCES)
STATS = ("mean", "std")

VAL_LOSS = "val_loss"  # the validation loss, per validation (early stopping, the pruner)
TRAIN_LOSS = "train_loss"  # the training loss, per logged step
N_PARAMS = "n_params"  # the model's parameter count
THREADS = "threads"  # the torch threads a run trained with, at each validation (its core share may change)
RESUMED_FROM_STEP = "resumed_from_step"  # one value per resume, at step = the checkpoint's: the run's history


def _check(what: str, value: str | None, allowed: tuple[str | None, ...]) -> None:
    if value not in allowed:  # a caller's typo must not become a key nothing reads
        raise ValueError(f"{what} {value!r}: must be one of {', '.join(str(a) for a in allowed)}")


# -- the test evaluation -------------------------------------------------------------------------------


def metric(name: str, scope: str = "pair", stat: str = "mean", ref: str | None = None) -> str:
    """A test metric: ``pair.pos_l2.mean``; with ``ref`` a reference's (``train_mean.pair.pos_l2.mean``)."""
    _check("scope", scope, SCOPES)
    _check("stat", stat, STATS)
    _check("source", ref, (None, *SOURCES))
    return f"{'' if ref in (None, MODEL) else ref + '.'}{scope}.{name}.{stat}"


def count(scope: str) -> str:
    """The test set's size a scope's means are over: ``test.n_pairs`` (pair), ``test.n_trajectories``."""
    _check("scope", scope, SCOPES)
    return "test.n_pairs" if scope == "pair" else "test.n_trajectories"


def column(name: str, scope: str = "pair", source: str = MODEL) -> str:
    """A column of ``trajectory_errors.csv`` (one row per test trajectory): ``model.pair.pos_l2``."""
    _check("scope", scope, SCOPES)
    _check("source", source, SOURCES)
    return f"{source}.{scope}.{name}"


def ratio(name: str, scope: str = "pair", ref: str = "train_mean") -> str:
    """A test error ÷ a reference's: ``ratio.train_mean.pair.pos_l2``."""
    _check("scope", scope, SCOPES)
    _check("reference", ref, REFERENCES)
    return f"ratio.{ref}.{scope}.{name}"


def skill(name: str, scope: str = "pair") -> str:
    """1 - a test error ÷ the better reference's: ``skill.pair.pos_l2``."""
    _check("scope", scope, SCOPES)
    return f"skill.{scope}.{name}"


def ratio_value(metrics: Mapping[str, float], name: str, scope: str = "pair", ref: str = "train_mean"
                ) -> float | None:
    """The value :func:`ratio` names, from the two logged means; None when either is missing or the reference's
    is not a positive finite number."""
    err, base = metrics.get(metric(name, scope)), metrics.get(metric(name, scope, ref=ref))
    if err is None or base is None or not (math.isfinite(base) and base > 0):
        return None
    return err / base


def spread(part: str, relative: bool = False) -> str:
    """How much the predictions vary over the test pairs (``part``: pos or rot): ``pred.std.pos``; ``relative``:
    ÷ the ground truth's (``pred.std_ratio.pos``)."""
    _check("part", part, ("pos", "rot"))
    return f"pred.{'std_ratio' if relative else 'std'}.{part}"


# -- the headline ----------------------------------------------------------------------------------------

HEADLINE_METRIC, HEADLINE_SCOPE, HEADLINE_REFERENCE = "pos_l2", "pair", "train_mean"
HEADLINE = ratio(HEADLINE_METRIC, HEADLINE_SCOPE, HEADLINE_REFERENCE)  # lower is better, < 1 beats the reference
HEADLINE_ERROR = metric(HEADLINE_METRIC, HEADLINE_SCOPE)  # the error it divides (voxels)


def headline(metrics: Mapping[str, float]) -> float:
    """A run's headline from its logged errors (module doc); NaN when it cannot be computed."""
    value = ratio_value(metrics, HEADLINE_METRIC, HEADLINE_SCOPE, HEADLINE_REFERENCE)
    return math.nan if value is None else value


# -- validation, evaluation, training, cost --------------------------------------------------------------


def val(name: str) -> str:
    """A metric of every validation: ``val.pos_l2``, ``val.ratio.pos_l2``, ``val.mode_gap``."""
    return f"val.{name}"


VAL_RATIO = val(f"ratio.{HEADLINE_METRIC}")  # the headline on the validation pairs (÷ the training mean's)
VAL_MODE_GAP = val("mode_gap")  # eval-mode ÷ batch-statistics loss on training batches (training/batchnorm.py)


def val_name(key: str) -> str | None:
    """What follows ``val.`` in a validation key (``val.pos_l2`` -> ``pos_l2``); None for any other key."""
    head, dot, rest = key.partition(".")
    return rest if head == "val" and dot else None


def val_best(name: str) -> str:
    """A validation metric of the weights that were tested (the best validation): ``val_best.pos_l2``."""
    return f"val_best.{name}"


def val_best_name(key: str) -> str | None:
    """What follows ``val_best.`` (``val_best.pos_l2`` -> ``pos_l2``); None for any other key."""
    head, dot, rest = key.partition(".")
    return rest if head == "val_best" and dot else None


def best_of(key: str) -> str:
    """The run metric that keeps a validation key's value at the tested weights: ``val.pos_l2`` ->
    ``val_best.pos_l2``, ``val_loss`` -> ``val_best.loss``."""
    name = "loss" if key == VAL_LOSS else val_name(key)
    if not name:
        raise ValueError(f"{key!r}: not a validation key (val_loss or val.<name>)")
    return val_best(name)


def evaluation(name: str) -> str:
    """A figure of the test evaluation (``eval.mode_gap``, ``eval.time_s``) or one of its settings, logged as a
    param (``eval.ctf_angle``: the config path of that setting)."""
    return f"eval.{name}"


def train(name: str) -> str:
    """A figure of training: ``train.steps``, ``train.pairs_seen``, ``train.best_step``, ..."""
    return f"train.{name}"


def cost(what: str, target: float) -> str:
    """The cost of learning (training/cost.py): ``what`` (pairs, step, core_s) until the validation headline
    first reached ``target``: ``cost.pairs_to_0.90``."""
    _check("cost", what, ("pairs", "step", "core_s"))
    return f"cost.{what}_to_{target:.2f}"


# -- the parent runs: a sweep's, a study's ---------------------------------------------------------------

CELL_STATES = ("planned", "finished", "failed")
TRIAL_STATES = ("finished", "complete", "pruned", "fail")


def cells(state: str) -> str:
    """A sweep parent's count of its planned cells (``planned``) or of those in a state: ``cells.finished``."""
    _check("cells", state, CELL_STATES)
    return f"cells.{state}"


def best(stage: str, name: str) -> str:
    """A sweep parent's figure of ``stage``'s best cell by validation (``best.personalized.val_best.loss``, its
    headline, its error), or the tag naming that cell or its run (``name`` ``cell``, ``run``)."""
    return f"best.{stage}.{name}"


def best_value(path: str) -> str:
    """A study parent's tag: the best trial's value of a searched config path (``best.train.lr``)."""
    return f"best.{path}"


def trials(state: str) -> str:
    """A study parent's trial count: ``trials.finished`` (pruned or complete), ``trials.complete``, ..."""
    _check("trials", state, TRIAL_STATES)
    return f"trials.{state}"


def importance(path: str) -> str:
    """A study parent's importance of a searched config path (``importance.train.lr``)."""
    return f"importance.{path}"
