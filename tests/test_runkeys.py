"""Run metric keys: one builder (``bronchocli/runkeys.py``) spells every key, and no other module spells one.

The keys are data (a store written before is read with them), so the builder is checked against the literal
keys runs have logged, and the package is scanned for a key spelled outside it: a string constant (an f-string's
text with ``{}`` where its values go; docstrings aside: they describe) that starts a key of a metric family.
"""

from __future__ import annotations

import ast
import math
import re
from pathlib import Path

import pytest

from test_architecture import _docstrings  # the one definition: docstrings are prose, not keys

from bronchocli import runkeys
from bronchocli.config import Config
from bronchocli.runs.records import flatten

PACKAGE = Path(__file__).resolve().parents[1] / "bronchocli"
NAME = r"(?:[a-z_]|\{\})"  # a key's next character: a name, or an f-string's value
START = r"(?:(?<![\w.{}])|(?<=\{\}\.))"  # a key starts a word, or follows an f-string value's dot ("{}.pair.")
FAMILIES = re.compile(
    rf"{START}(?:(?:model|zero_motion|train_mean)\.)?(?:pair|acc|traj)\.{NAME}"  # test metrics, errors table
    rf"|{START}(?:ratio|skill|val|val_best|cost)\.{NAME}"  # headline, validation, cost of learning
    rf"|{START}(?:pred\.std|test\.n_)"  # prediction spread, test size
    rf"|{START}(?:cells|best|trials|importance)\.{NAME}"  # a sweep's and a study's parent run
    r"|\{\}\.(?:mean|std)\b"  # a mean or std built from parts: f"{scope}.{m}.mean"
)
SECTIONED = re.compile(rf"{START}(train|eval)\.([a-z_]+|\{{\}})")  # train.* / eval.*: a metric or a config path
# metric keys without a family
BARE = {runkeys.VAL_LOSS, runkeys.TRAIN_LOSS, runkeys.N_PARAMS, runkeys.THREADS, runkeys.RESUMED_FROM_STEP}

# Where a key-shaped literal is allowed, each with its reason (module path relative to bronchocli/, literal).
ALLOWED = {
    ("runkeys.py", None): "the builder itself",
    ("config/sections.py", "val_loss"): "a name of tune.objective's choices (what a trial minimises), not a key",
    ("sweep/tuning/trial.py", "val_loss"): "the same choice name, as the key of OBJECTIVES",
    ("models/__init__.py", "n_params"): "the name of the function models exports (__all__), not a key",
    ("config/grid.py", "threads"): "the config field train.threads (NOT_IN_KEY), not a key",
    ("diagnostics/speed.py", "threads"): "a field of speed_settings.json's measurement record, not a key",
    ("runs/cores.py", "threads"): "a field of a core claim's JSON and the run param threads (with threads.source)",
}


def config_paths() -> set[str]:
    """Every dotted config path (``train.lr``, ``eval.ctf_angle``): a ``train.``/``eval.`` literal that is one is a
    setting, not a metric key."""
    return set(flatten(Config(name="x").model_dump(mode="json")))


def _texts(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, text) of every string constant outside docstrings; an f-string as one text with ``{}`` for values."""
    docs, inside, out = _docstrings(tree), set(), []
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr):
            parts = []
            for v in node.values:
                inside.add(id(v))
                parts.append(v.value if isinstance(v, ast.Constant) and isinstance(v.value, str) else "{}")
            out.append((node.lineno, "".join(parts)))
        elif isinstance(node, ast.FormattedValue) and node.format_spec is not None:
            inside.add(id(node.format_spec))
    for node in ast.walk(tree):
        if (isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs
                and id(node) not in inside):
            out.append((node.lineno, node.value))
    return out


def key_literals(source: str, paths: set[str]) -> list[tuple[int, str]]:
    """(line, literal) of every metric key a module's source spells (module doc)."""
    found = []
    for line, text in _texts(ast.parse(source)):
        hits = [m.group(0) for m in FAMILIES.finditer(text)]
        hits += [m.group(0) for m in SECTIONED.finditer(text)
                 if m.group(0) not in paths and not any(p.startswith(m.group(0) + ".") for p in paths)]
        hits += [text] if text in BARE else []
        found += [(line, text) for _ in hits[:1]]
    return found


def _allowed(module: str, text: str) -> bool:
    return (module, None) in ALLOWED or (module, text) in ALLOWED


def scan(package: Path, paths: set[str]) -> list[str]:
    """``module:line: literal`` for every key spelled in ``package`` outside ``ALLOWED``."""
    out = []
    for path in sorted(package.rglob("*.py")):
        module = path.relative_to(package).as_posix()
        out += [f"{module}:{line}: {text!r}" for line, text in key_literals(path.read_text(), paths)
                if not _allowed(module, text)]
    return out


def test_no_module_spells_a_metric_key_outside_the_builder():
    found = scan(PACKAGE, config_paths())
    assert not found, ("metric keys spelled outside bronchocli/runkeys.py (build them with runkeys; a literal "
                       "that is not a key goes in ALLOWED with its reason):\n" + "\n".join(found))


def test_every_allowed_literal_is_still_there():
    """The allow-list stays short: an entry whose literal is gone is removed, not kept."""
    spelled = {(path.relative_to(PACKAGE).as_posix(), text) for path in PACKAGE.rglob("*.py")
               for _, text in key_literals(path.read_text(), config_paths())}
    stale = [entry for entry in ALLOWED if entry[1] is not None and entry not in spelled]
    assert not stale, stale


@pytest.mark.parametrize("planted", [
    'KEY = "pair.pos_l2.mean"',
    'KEY = "train_mean.pair.pos_l2.mean"',
    'def f(m):\n    return f"val_best.{m}"',
    'def f(ev, m):\n    return f"{ev}.{m}.mean"',
    'def f(source, m):\n    return f"{source}.pair.{m}"',
    'KEY = "ratio.zero_motion.pair.pos_l2"',
    'KEY = "skill.pair.rot_l2"',
    'KEY = "val.ratio.pos_l2"',
    'def f(t):\n    return f"cost.pairs_to_{t:.2f}"',
    'KEY = "train.pairs_seen"',
    'KEY = "eval.mode_gap"',
    'KEY = "pred.std_ratio.pos"',
    'KEY = "test.n_pairs"',
    'def f(m):\n    return m.get("val_loss")',
    'def f(text):\n    raise ValueError(f"{text}: ranked by val_best.loss")',  # a key inside a message
    'KEY = "cells.finished"',  # a sweep's parent run
    'def f(stage, by):\n    return f"best.{stage}.{by}"',
    'def f(stage):\n    p = f"best.{stage}."\n    return p',
    'def f(k):\n    return f"trials.{k}"',  # a study's parent run
    'KEY = "trials.pruned"',
    'def f(path):\n    return {f"importance.{path}": 1.0}',
    'def f(client, run, step):\n    client.log_metric(run, "resumed_from_step", step)',
    'VALUES = {"threads": 2.0}',
])
def test_the_scan_finds_a_planted_key(planted, tmp_path):
    package = tmp_path / "bronchocli"
    (package / "reporting").mkdir(parents=True)
    doc = '"""Names pair.pos_l2.mean in its doc (allowed)."""'
    (package / "reporting" / "planted.py").write_text(f"{doc}\n\n{planted}\n")
    (package / "runkeys.py").write_text(f"{planted}\n")  # the builder may spell it
    found = scan(package, config_paths())
    assert len(found) == 1 and found[0].startswith("reporting/planted.py:"), found


@pytest.mark.parametrize("innocent", [
    '"""A docstring naming pair.pos_l2.mean and val_best.loss."""',
    'PATH = "train.lr"',  # a config path
    'MSG = f"train.batch_size {1}: too large"',  # a config path in a message
    'WHERE = "eval.ctf_angle"',  # the threshold's config path (also its param's name)
    'TEXT = "GMAC per image pair. ms b1"',  # prose
    'TEXT = "the ratio. Below 1 is better"',
    'NAME = "pos_l2"',
])
def test_the_scan_leaves_settings_prose_and_docstrings_alone(innocent):
    assert key_literals(innocent + "\n", config_paths()) == []


# -- the builder spells the keys runs have logged (an older store is read with them) ------------------


def test_test_evaluation_keys():
    assert runkeys.metric("pos_l2") == "pair.pos_l2.mean"
    assert runkeys.metric("rot_l2", "acc", "std") == "acc.rot_l2.std"
    assert runkeys.metric("ctf", "traj") == "traj.ctf.mean"
    assert runkeys.metric("pos_l2", ref="train_mean") == "train_mean.pair.pos_l2.mean"
    assert runkeys.metric("de", "acc", ref="zero_motion") == "zero_motion.acc.de.mean"
    assert runkeys.metric("de", ref="model") == "pair.de.mean"
    assert (runkeys.count("pair"), runkeys.count("acc"), runkeys.count("traj")) == (
        "test.n_pairs", "test.n_trajectories", "test.n_trajectories")
    assert runkeys.column("pos_l2") == "model.pair.pos_l2"
    assert runkeys.column("ate", "traj", "train_mean") == "train_mean.traj.ate"
    assert (runkeys.spread("pos"), runkeys.spread("rot", relative=True)) == ("pred.std.pos", "pred.std_ratio.rot")


def test_headline_keys():
    assert runkeys.HEADLINE == runkeys.ratio("pos_l2") == "ratio.train_mean.pair.pos_l2"
    assert runkeys.HEADLINE_ERROR == "pair.pos_l2.mean"
    assert runkeys.ratio("pos_l2", ref="zero_motion") == "ratio.zero_motion.pair.pos_l2"
    assert runkeys.skill("rot_l2", "acc") == "skill.acc.rot_l2"


def test_validation_training_and_cost_keys():
    assert runkeys.val("pos_l2") == "val.pos_l2" and runkeys.VAL_RATIO == "val.ratio.pos_l2"
    assert runkeys.VAL_MODE_GAP == "val.mode_gap"
    assert runkeys.best_of("val.ratio.pos_l2") == "val_best.ratio.pos_l2"
    assert runkeys.best_of("val_loss") == "val_best.loss"
    assert runkeys.val_name("val.mode_gap") == "mode_gap" and runkeys.val_name("val_best.x") is None
    assert runkeys.val_best_name("val_best.pos_l2") == "pos_l2" and runkeys.val_best_name("val.pos_l2") is None
    assert runkeys.evaluation("mode_gap") == "eval.mode_gap" and runkeys.train("best_step") == "train.best_step"
    assert runkeys.cost("pairs", 0.9) == "cost.pairs_to_0.90" and runkeys.cost("core_s", 0.85) == "cost.core_s_to_0.85"
    with pytest.raises(ValueError, match="not a validation key"):
        runkeys.best_of("pair.pos_l2.mean")


def test_parent_run_keys():
    assert [runkeys.cells(s) for s in runkeys.CELL_STATES] == ["cells.planned", "cells.finished", "cells.failed"]
    assert runkeys.best("personalized", "val_best.loss") == "best.personalized.val_best.loss"
    assert runkeys.best("sota", "run") == "best.sota.run" and runkeys.best_value("train.lr") == "best.train.lr"
    assert [runkeys.trials(s) for s in runkeys.TRIAL_STATES] == [
        "trials.finished", "trials.complete", "trials.pruned", "trials.fail"]
    assert runkeys.importance("model.dropout") == "importance.model.dropout"
    assert (runkeys.THREADS, runkeys.RESUMED_FROM_STEP) == ("threads", "resumed_from_step")
    with pytest.raises(ValueError, match="trials 'failed'"):
        runkeys.trials("failed")


def test_a_misspelt_part_is_refused_not_turned_into_a_key_nothing_reads():
    with pytest.raises(ValueError, match="scope 'pairs'"):
        runkeys.metric("pos_l2", "pairs")
    with pytest.raises(ValueError, match="reference 'train'"):
        runkeys.ratio("pos_l2", ref="train")


def test_the_headline_is_the_pair_position_error_over_the_training_means():
    m = {"pair.pos_l2.mean": 0.42, "train_mean.pair.pos_l2.mean": 0.5}
    assert runkeys.headline(m) == pytest.approx(0.84)
    assert math.isnan(runkeys.headline({"pair.pos_l2.mean": 0.42}))
    assert math.isnan(runkeys.headline({**m, "train_mean.pair.pos_l2.mean": 0.0}))
    assert math.isnan(runkeys.headline({**m, "train_mean.pair.pos_l2.mean": math.nan}))


@pytest.mark.parametrize("reference", [0.5, 0.0, -0.5, math.inf, math.nan, None])
def test_train_results_headline_is_the_one_headline(reference):
    """``TrainResult.headline`` (what ``train`` ends with, ``api.train`` returns) is ``runkeys.headline``: the same
    edge rule (NaN unless the reference's error is a positive finite number), not a division of its own."""
    from bronchocli.runs.contract import RunResult
    from bronchocli.training.outcome import TrainResult

    metrics = {"pair.pos_l2.mean": 0.42, **({} if reference is None else {"train_mean.pair.pos_l2.mean": reference})}
    cell = Config(name="x").cell(arch="baseline", rot_loss="mse", population="personalized")
    result = TrainResult(cell, "x", RunResult("r", "FINISHED", metrics))
    expected = runkeys.headline(metrics)
    assert result.headline == pytest.approx(expected, nan_ok=True)
    assert (reference == 0.5) == math.isfinite(result.headline)
