"""Numbers with one source (benchmarks/docblocks.py): every generated span of README.md, CONTRIBUTING.md, docs/
and benchmarks/README.md equals what its results file gives; every results file names its machine, date and
command; the check catches a changed figure, a changed block line and an unknown reference; ``--write``
regenerates; no document points outside the repository; the README keeps what a newcomer and CI need."""

from __future__ import annotations

import importlib.util
import json
import re
import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


@pytest.fixture(scope="module")
def docblocks():
    spec = importlib.util.spec_from_file_location("docblocks", ROOT / "benchmarks" / "docblocks.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["docblocks"] = module
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


def test_every_generated_span_equals_its_results_file(docblocks):
    results = docblocks.load_results()
    diffs = docblocks.check(docblocks.documents(), results)
    assert not diffs, "re-measure, or run `python benchmarks/docblocks.py --write`:\n" + "\n".join(diffs)


def test_the_quoting_documents_hold_generated_spans(docblocks):
    """The README's figures, the benchmarks' Summary and the calibration block are generated, not typed."""
    text = {p.relative_to(ROOT).as_posix(): p.read_text(encoding="utf-8") for p in docblocks.documents()}
    assert "<!-- numbers: summary -->" in text["benchmarks/README.md"]
    assert "<!-- numbers: calibration -->" in text["docs/reports.md"]
    assert len(docblocks.INLINE.findall(text["README.md"])) >= 10


def test_every_results_file_names_machine_date_and_command(docblocks):
    files = sorted((ROOT / "benchmarks" / "results").glob("*.json"))
    assert len(files) >= 10
    for path in files:
        data = json.loads(path.read_text(encoding="utf-8"))
        for key in ("title", "machine", "date", "command", "figures"):
            assert data.get(key), f"{path.name}: no {key}"
        assert re.fullmatch(r"\d{4}-\d{2}-\d{2}", data["date"]), path.name


def _project(tmp_path: Path, doc: str, figures: dict) -> tuple[Path, Path]:
    results = tmp_path / "results"
    results.mkdir()
    (results / "job.json").write_text(json.dumps(
        {"title": "t", "machine": "2-core test CPU", "date": "2026-01-02", "command": "python bench.py",
         "summary": {"figure": "the job", "result": "**1.50 s**"}, "figures": figures}))
    path = tmp_path / "doc.md"
    path.write_text(doc, encoding="utf-8")
    return results, path


def test_check_names_a_changed_inline_figure_and_write_restores_it(docblocks, tmp_path):
    results_dir, doc = _project(tmp_path, "took <!-- n: job/figures/total_s as dur -->12 min 8 s<!-- /n --> and "
                                          "<!-- n: job/figures/ratios as range .3f -->0.830–0.845<!-- /n -->.\n",
                                {"total_s": 727.5, "ratios": [0.845, 0.843, 0.830]})
    results = docblocks.load_results(results_dir, tmp_path / "none.json")
    assert docblocks.check([doc], results, tmp_path) == []
    doc.write_text(doc.read_text().replace("12 min 8 s", "11 min"), encoding="utf-8")
    diffs = docblocks.check([doc], results, tmp_path)
    assert len(diffs) == 1 and "job/figures/total_s" in diffs[0] and "'11 min'" in diffs[0] \
        and "'12 min 8 s'" in diffs[0]
    assert docblocks.write([doc], results, tmp_path) == [doc]
    assert "took <!-- n: job/figures/total_s as dur -->12 min 8 s<!-- /n -->" in doc.read_text()
    assert docblocks.check([doc], results, tmp_path) == []


def test_check_names_a_changed_block_line(docblocks, tmp_path):
    results_dir, doc = _project(tmp_path, "x\n<!-- numbers: summary -->\n<!-- /numbers -->\ny\n", {"total_s": 1.5})
    results = docblocks.load_results(results_dir, tmp_path / "none.json")
    assert docblocks.check([doc], results, tmp_path)  # an empty block is not the table
    docblocks.write([doc], results, tmp_path)
    assert "| 2026-01-02 | 2-core test CPU | the job | `python bench.py` | **1.50 s** |" in doc.read_text()
    assert docblocks.check([doc], results, tmp_path) == []
    doc.write_text(doc.read_text().replace("**1.50 s**", "**1.40 s**"), encoding="utf-8")
    assert [d for d in docblocks.check([doc], results, tmp_path) if "block summary" in d]


def test_a_lines_block_shows_the_recorded_lines_and_names_a_drifted_one(docblocks, tmp_path):
    table = ["| Model | Position |", "|---|---|", "| OffsetNet | **1.52 [1.42, 1.63]** |"]
    results_dir, doc = _project(tmp_path, "x\n<!-- numbers: lines job/figures/table -->\n<!-- /numbers -->\n",
                                {"table": table, "scalar": 1.5})
    results = docblocks.load_results(results_dir, tmp_path / "none.json")
    assert docblocks.check([doc], results, tmp_path)  # empty: not the recorded lines
    docblocks.write([doc], results, tmp_path)
    assert "\n".join(table) in doc.read_text() and docblocks.check([doc], results, tmp_path) == []
    doc.write_text(doc.read_text().replace("1.52", "1.50"), encoding="utf-8")
    assert [d for d in docblocks.check([doc], results, tmp_path) if "block lines" in d]
    doc.write_text("<!-- numbers: lines job/figures/scalar -->\n<!-- /numbers -->\n", encoding="utf-8")
    assert "not a list of lines" in docblocks.check([doc], results, tmp_path)[0]


def test_a_ratio_of_two_figures_is_computed_per_element(docblocks, tmp_path):
    results_dir, doc = _project(tmp_path, "<!-- n: job/figures/slow ÷ job/figures/fast as range .1f -->x<!-- /n -->× and "
                                          "<!-- n: job/figures/total_s ÷ job/figures/half as .1f -->x<!-- /n -->×\n",
                                {"slow": [732.4, 763.4], "fast": [251.1, 251.2], "total_s": 3.0, "half": 1.5})
    results = docblocks.load_results(results_dir, tmp_path / "none.json")
    docblocks.write([doc], results, tmp_path)
    assert doc.read_text().startswith("<!-- n: job/figures/slow ÷ job/figures/fast as range .1f -->2.9–3.0<!-- /n -->×")
    assert "-->2.0<!-- /n -->×" in doc.read_text()
    doc.write_text("<!-- n: job/figures/slow ÷ job/figures/total_s -->1<!-- /n -->\n")
    assert "can divide two numbers or two lists" in docblocks.check([doc], results, tmp_path)[0]


def test_unknown_references_and_incomplete_results_files_are_named(docblocks, tmp_path):
    results_dir, doc = _project(tmp_path, "<!-- n: job/figures/missing -->1<!-- /n -->\n", {"total_s": 1.5})
    results = docblocks.load_results(results_dir, tmp_path / "none.json")
    assert "no key 'figures/missing' in job" in docblocks.check([doc], results, tmp_path)[0]
    doc.write_text("<!-- n: nofile/x -->1<!-- /n -->\n<!-- numbers: nosuch -->\n<!-- /numbers -->\n")
    assert "unknown block 'nosuch'" in docblocks.check([doc], results, tmp_path)[0]
    (results_dir / "bad.json").write_text(json.dumps({"title": "t", "date": "2026-01-02", "figures": {"a": 1}}))
    with pytest.raises(docblocks.NumbersError, match=r"bad.json: missing machine, command"):
        docblocks.load_results(results_dir, tmp_path / "none.json")


def test_formats(docblocks):
    assert docblocks.fmt(1939, "dur") == "32 min 19 s"
    assert docblocks.fmt(28.6, "dur") == "28.6 s"
    assert docblocks.fmt(6776.4, "dur") == "1 h 53 min"  # 1 h 52 min 56 s rounds up, is not floored
    assert docblocks.fmt(6739.0, "dur") == "1 h 52 min"
    assert docblocks.fmt(3599, "dur") == "1 h 0 min" and docblocks.fmt(119.6, "dur") == "2 min 0 s"
    assert docblocks.fmt([0.98, 0.965, 0.974], "range .3f") == "0.965–0.980"
    assert docblocks.fmt([251.1338, 251.2073], "range .0f") == "251"  # ends that print alike: printed once
    assert docblocks.fmt([299.7981, 301.3049], "range .0f") == "300–301"
    assert docblocks.fmt([0.98, 0.965], "join .3f") == "0.980 / 0.965"
    assert docblocks.fmt(1.753983547542414, ".2f") == "1.75"
    with pytest.raises(docblocks.NumbersError):
        docblocks.fmt({"a": 1}, "")


def test_the_command_line_checks_the_repository_and_fails_on_a_drifted_copy(docblocks, tmp_path, monkeypatch,
                                                                            capsys):
    assert docblocks.main([]) == 0
    copy = tmp_path / "repo"
    for part in ("README.md", "docs", "benchmarks", "bronchocli/speed_settings.json"):
        src, dst = ROOT / part, copy / part
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copytree(src, dst) if src.is_dir() else shutil.copy(src, dst)
    text = (copy / "README.md").read_text(encoding="utf-8")
    m = docblocks.INLINE.search(text)
    (copy / "README.md").write_text(text[:m.start("text")] + "9" + m["text"] + text[m.end("text"):], encoding="utf-8")
    monkeypatch.setattr(docblocks, "ROOT", copy)
    monkeypatch.setattr(docblocks, "RESULTS", copy / "benchmarks" / "results")
    monkeypatch.setattr(docblocks, "SPEED_SETTINGS", copy / "bronchocli" / "speed_settings.json")
    capsys.readouterr()
    assert docblocks.main([]) == 1
    assert "README.md:" in capsys.readouterr().out


OUTSIDE = re.compile(r"\.\./shared|/work/|DEVELOPERS|developers' guide|DESIGN\.md|DESIGN §|"
                     r"/tmp/[\w.-]+\.(?:sh|py)\b|(?:script|note)s?\b[^.\n]{0,40}\bnot kept\b|set-up notes|setup notes")


# what the repository holds as text: its code, tests, docs, benchmarks, CI and config (raw logs of a run, which
# record the paths of the machine they ran on, are not pointers)
TEXT = ("*.py", "*.md", "*.sh", "*.yaml", "*.yml", "*.toml", "run")
LOGS = ("benchmarks/gpu-*/*", "benchmarks/results/*.txt")


def repository_text() -> list[Path]:
    out = [p for p in ROOT.iterdir() if p.is_file() and any(p.match(g) for g in TEXT)]
    for top in ("bronchocli", "tests", "benchmarks", "docs", ".ci"):
        out += [p for p in sorted((ROOT / top).rglob("*")) if p.is_file() and any(p.match(g) for g in TEXT)
                and "__pycache__" not in p.parts and not any(p.relative_to(ROOT).match(g) for g in LOGS)]
    return [p for p in out if p != Path(__file__).resolve()]


def test_nothing_in_the_repository_points_outside_it():
    """No document, module, test or script names a file, script or note that is not in the repository."""
    bad = [f"{p.relative_to(ROOT)}:{i}: {line.strip()[:100]}" for p in repository_text()
           for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if OUTSIDE.search(line)]
    assert not bad, "\n".join(bad)


# a file path in backticks: a token with a slash whose first part is a folder of this repository, or one ending
# in a file type of it; resolved against the repository, the document's folder, the package and the results
EXISTING = re.compile(r"`([\w.][\w.-]*(?:/[\w.-]+)+/?)`")
OURS = ("bronchocli", "tests", "benchmarks", "docs", ".ci")
SUFFIXES = (".py", ".md", ".sh", ".json", ".toml", ".yaml", ".yml", ".txt")
# paths in backticks that are not this repository's files, each for its reason
NOT_OURS = {
    "experiments/train_all.sh", "BronchoTrack/data/datasets.py", "BronchoTrack/data/dataorg.py",
    "models/modules.py", "models/bronchonet.py",  # the authors' repository (docs/reproduction.md)
    "data/bronchopose/spec.json",  # inside a logged MLflow Model (docs/api.md)
}
GENERATED = ("reports/", "runs/", "data/")  # what the main job writes into a project folder: named, never committed


def backticked_paths(text: str) -> list[tuple[int, str]]:
    text = re.sub(r"^```.*?^```", lambda m: "\n" * m.group(0).count("\n"), text, flags=re.S | re.M)
    return [(text.count("\n", 0, m.start()) + 1, m.group(1)) for m in EXISTING.finditer(text)
            if m.group(1).split("/")[0] in OURS or Path(m.group(1)).suffix in SUFFIXES]


def missing_paths(doc: Path, root: Path = ROOT) -> list[str]:
    out = []
    for line, path in backticked_paths(doc.read_text(encoding="utf-8")):
        where = (root / path, doc.parent / path, root / "bronchocli" / path, root / "benchmarks" / path,
                 root / "benchmarks" / "results" / path)
        if path not in NOT_OURS and not path.startswith(GENERATED) and not any(p.exists() for p in where):
            out.append(f"{doc.relative_to(root) if doc.is_relative_to(root) else doc}:{line}: `{path}`")
    return out


def test_every_file_path_in_backticks_in_the_docs_exists(docblocks):
    bad = [m for p in docblocks.documents() if p.suffix == ".md" for m in missing_paths(p)]
    assert not bad, "a path the docs name is not in the repository:\n" + "\n".join(bad)


def test_a_backticked_path_that_does_not_exist_is_named(tmp_path):
    doc = tmp_path / "doc.md"
    doc.write_text("See `benchmarks/docblocks.py`, `training/loop.py` and `results/render.json`,\n"
                   "not `tests/data/test_generate.py` nor `benchmarks/nope.sh`; `runs/mlflow.db` is an output.\n"
                   "```\n`tests/in_a_fence.py`\n```\n", encoding="utf-8")
    assert missing_paths(doc, ROOT) == [f"{doc}:2: `tests/data/test_generate.py`", f"{doc}:2: `benchmarks/nope.sh`"]


def test_relative_links_of_the_documents_resolve(docblocks):
    bad = []
    for p in docblocks.documents():
        if p.suffix != ".md":
            continue
        for target in re.findall(r"\]\(([^)\s]+)\)", p.read_text(encoding="utf-8")):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            if not (p.parent / target.split("#")[0]).exists():
                bad.append(f"{p.relative_to(ROOT)}: {target}")
    assert not bad, "\n".join(bad)


def test_readme_gives_a_newcomer_what_they_need_first():
    lines = README.read_text(encoding="utf-8").splitlines()
    marker = lines.index("<!-- main-command -->")
    assert marker <= 20, f"{marker} lines before the main command (at most 20)"
    text = "\n".join(lines)
    for heading in ("Results at a glance", "Glossary", "Profiles"):
        assert re.search(rf"^#+ {heading}", text, re.M), heading
    for term in ("training mean", "†", "ratio"):
        assert f"**{term}**" in text, term
    assert "(CONTRIBUTING.md)" in text and (ROOT / "CONTRIBUTING.md").exists()


def test_readme_markers_hold_the_commands_ci_reads():
    """.ci/run takes the line after the test-command marker and its fence; the fast tier has its own slot; the main
    command is a fenced block of steps (benchmarks/main_job_phases.sh runs them) whose steps sweep, then report."""
    lines = README.read_text(encoding="utf-8").splitlines()
    for marker in ("<!-- test-command -->", "<!-- fast-test-command -->"):
        i = lines.index(marker)
        assert lines[i + 1].startswith("```") and lines[i + 3] == "```", marker
    test = lines[lines.index("<!-- test-command -->") + 2]
    assert "pytest" in test
    i = lines.index("<!-- main-command -->")
    assert lines[i + 1].startswith("```")
    steps = lines[i + 2:lines.index("```", i + 2)]
    commands = [s.split("#", 1)[0].strip() for s in steps]
    assert commands[0].startswith("git clone ") and any(c.startswith("pip install torch==2.13.0") for c in commands)
    sweep = next(k for k, c in enumerate(commands) if c.startswith("bronchopose sweep"))
    assert commands[sweep + 1].startswith("bronchopose report")


def test_readme_quotes_no_timing_or_ratio_outside_a_generated_span():
    """A time, a rate or a three-decimal ratio typed into the README's prose (not a span) has no results file."""
    text = re.sub(r"<!-- n: .*?<!-- /n -->", "", README.read_text(encoding="utf-8"), flags=re.S)
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    typed = re.compile(r"(?<![\d.])\d+(\.\d+)?\s?(min|s|ms|pairs/s|fps|frames/s)\b|(?<![\d.])0\.\d{3}(?![\d.])")
    bad = [f"README.md:{i}: {m.group(0)!r} in {line.strip()[:80]!r}" for i, line in enumerate(text.splitlines(), 1)
           for m in typed.finditer(line)]
    assert not bad, "quote it through a span of its results file (CONTRIBUTING.md):\n" + "\n".join(bad)


# -- the config's numbers (benchmarks/docconfig.py) ---------------------------------------------------------------------

@pytest.fixture(scope="module")
def plans(docblocks):
    return docblocks.load_results()["config"]


def test_every_plan_of_experiments_yaml_has_its_facts_from_the_loader(docblocks, plans):
    """The facts are the loader's: an independent read of the YAML agrees on what it states directly."""
    import yaml

    raw = yaml.safe_load((ROOT / "experiments.yaml").read_text(encoding="utf-8"))
    assert list(plans) == ["default", *raw["profiles"]]
    for name, f in plans.items():
        merged = raw if name == "default" else {**raw, **{k: v if not isinstance(v, dict) else {**raw.get(k, {}), **v}
                                                          for k, v in raw["profiles"][name].items()}}
        assert f["steps"] == merged["train"]["steps"], name
        assert f["seeds"] == merged["grid"]["seed"], name
        assert f["pairs"] == f["steps"] * f["pairs_per_step"] and f["cells"] == sum(f["stage_cells"])


def test_a_changed_config_is_a_changed_span_and_write_follows_it(docblocks, tmp_path):
    text = (ROOT / "experiments.yaml").read_text(encoding="utf-8")
    config = tmp_path / "experiments.yaml"
    config.write_text(text.replace("      steps: 5000\n", "      steps: 4000\n", 1), encoding="utf-8")
    doc = tmp_path / "doc.md"
    doc.write_text("| `learning-curve` | <!-- n: config/learning-curve/size -->x<!-- /n --> |\n\n"
                   "<!-- numbers: profiles -->\n<!-- /numbers -->\n", encoding="utf-8")
    results = docblocks.load_results(ROOT / "benchmarks" / "results", tmp_path / "none.json", config)
    assert len(docblocks.check([doc], results, tmp_path)) == 2
    docblocks.write([doc], results, tmp_path)
    written = doc.read_text(encoding="utf-8")
    assert "4,000 steps × 20 pairs" in written and "| `learning-curve` | `bronchopose-learning-curve` |" in written
    assert docblocks.check([doc], results, tmp_path) == []
    assert docblocks.check([doc], docblocks.load_results(), tmp_path)  # against the real config: 5,000 steps


def test_a_number_typed_beside_a_profile_that_the_config_contradicts_is_named(docblocks, plans, tmp_path):
    lc, default, cost = plans["learning-curve"], plans["default"], plans["learning-cost"]
    right = (f"`learning-curve` trains {lc['steps']:,} steps × {lc['batch_size']} pairs at {lc['image_size']}², "
             f"validation every {lc['val_every']} steps.\n\n"
             f"| plan | our CPU default |\n|---|---|\n| Steps | {default['steps']} steps, {default['n_seeds']} seeds |\n\n"
             f"`learning-cost` has objective `{cost['objective']}`.\n\n"
             f"`learning-curve` with `--set train.steps=7` trains 7 steps. Before 2026-11-28 `learning-curve` ran "
             f"3 steps. The main job (Table 6) at {default['image_size'] + 1}²: no plan named.\n")
    doc = tmp_path / "doc.md"
    doc.write_text(right, encoding="utf-8")
    assert docblocks.check([doc], docblocks.load_results(tmp_path / "none", tmp_path / "none.json"), tmp_path) == []
    wrong = (right.replace(f"{lc['steps']:,} steps", f"{lc['steps'] + 1000:,} steps")
             .replace(f"| {default['steps']} steps", f"| {default['steps'] - 1} steps")
             .replace(f"objective `{cost['objective']}`", "objective `val_best.ratio.pos_l2`")
             .replace(f"at {lc['image_size']}²", f"at {lc['image_size'] * 2}²"))
    doc.write_text(wrong, encoding="utf-8")
    diffs = docblocks.check([doc], docblocks.load_results(tmp_path / "none", tmp_path / "none.json"), tmp_path)
    assert len(diffs) == 4, diffs
    assert any("doc.md:1: next to learning-curve: typed steps" in d for d in diffs)
    assert any("doc.md:5: next to the default plan: typed steps" in d for d in diffs)
    assert any("objective 'val_best.ratio.pos_l2'" in d and "'cost'" in d for d in diffs)
    assert any(f"'{lc['image_size'] * 2}²'" in d for d in diffs)


def test_a_figure_means_one_thing_in_every_results_file(docblocks, tmp_path):
    """install_s is torch + project wherever its parts are recorded beside it (not the clone or the venv)."""
    results_dir, _ = _project(tmp_path, "", {"install_s": 22.6, "torch_s": 20.7, "project_s": 1.9,
                                             "runs": {"C": {"install_s": 28.6, "torch_s": 22.9, "project_s": 5.7}}})
    assert docblocks.load_results(results_dir, tmp_path / "none.json")["job"]["figures"]["install_s"] == 22.6
    (results_dir / "job.json").write_text((results_dir / "job.json").read_text().replace("28.6", "32.7"))
    with pytest.raises(docblocks.NumbersError, match=r"figures/runs/C/install_s is 32.7, not torch_s \+ project_s"):
        docblocks.load_results(results_dir, tmp_path / "none.json")


def test_the_summary_shows_the_latest_rows_of_each_figure_and_its_goal_once(docblocks, tmp_path):
    results_dir = tmp_path / "results"
    results_dir.mkdir()
    for name, date, cpu in (("old", "2026-01-01", "A"), ("new-a", "2026-02-01", "A"), ("new-b", "2026-02-01", "B")):
        (results_dir / f"{name}.json").write_text(json.dumps(
            {"title": "t", "machine": cpu, "cpu": cpu, "date": date, "command": "c", "figures": {"x": 1},
             "summary": {"of": "job", "figure": f"the job ({name})", "result": name, "goal": f"goal {name}"}}))
    lines = docblocks.summary_table(docblocks.load_results(results_dir, tmp_path / "none.json"))
    body = [line for line in lines[2:]]
    assert len(body) == 2 and not any("(old)" in line for line in body)
    assert sum("goal new-a" in line or "goal new-b" in line for line in body) == 1
