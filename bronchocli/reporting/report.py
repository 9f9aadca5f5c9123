"""`bronchopose report` in library form: collect runs once, build tables, write Markdown/LaTeX and figures.

``collect_index`` finds the runs (the config's cells, or a stored sweep),
``make_report`` is what ``entry.report`` (the command) calls; ``build_tables`` and
``write_tables`` are usable on their own (tests, notebooks).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from ..config import Config
from ..errors import BronchoError, DataError
from ..io import TEMP_SUFFIX, save_figure, write_json, write_text
from ..runs.client import client_for, find_experiment, redacted_uri, require_store
from ..runs.parents import KIND_SWEEP, REPORT_FOLDER, deleted_parent_line, find_parent, log_report
from ..runs.relocation import writes_here
from . import dataset_figures as dataset_figs
from .collect import RunIndex, collect_runs
from .context import NoData, Profiler
from .figure_cache import RECORD, FigureCache, digest, files_key
from .figures import FORMATS, Loader, make_figures
from .latex import to_latex
from .markdown import to_markdown
from .methods import write_methods
from .scope import config_plan
from .curves import training_curves
from .skill_figures import learning_curve, skill_figures
from .table_model import Table
from .tables import ONCE, TABLES, ReportContext

OUTPUT_FORMATS = {"md": ("md",), "latex": ("tex",), "both": ("md", "tex")}
RENDERERS = {"md": to_markdown, "tex": to_latex}


@dataclass
class ReportResult:
    tables: list[Table]
    files: list[Path] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)  # besides each table's own warnings (figures, ...)

    def table(self, key: str) -> Table:
        """The table whose file stem is ``key`` (e.g. ``table6-sota-pair``) or whose stem starts with it."""
        found = [t for t in self.tables if t.key == key] or [t for t in self.tables if t.key.startswith(key)]
        if len(found) != 1:
            keys = ", ".join(t.key for t in self.tables) or "none"
            raise KeyError(f"{key!r}: {'several' if found else 'no'} table(s) match; the tables: {keys}")
        return found[0]


def output_suffixes(fmt: str) -> tuple[str, ...]:
    if fmt not in OUTPUT_FORMATS:
        raise BronchoError(f"--format {fmt!r}: must be one of {', '.join(OUTPUT_FORMATS)}")
    return OUTPUT_FORMATS[fmt]


def collect_index(client, cfg: Config, sweep: str | None = None, pose_frame: str | None = None,
                  include_other_configs: bool = False) -> RunIndex:
    """The runs of the config's cells (``sweep`` None) or of the stored sweep ``sweep`` (no config cells)."""
    exp = find_experiment(client, cfg.experiment_name, redacted_uri(cfg))  # deleted by hand: the line status gives
    if sweep is not None:
        return collect_runs(client, cfg.experiment_name, sweep, pose_frame)
    plan = config_plan(client, [exp.experiment_id], cfg) if exp is not None else None
    return collect_runs(client, cfg.experiment_name, cfg.name, pose_frame, plan=plan,
                        include_other_configs=include_other_configs)


def build_tables(ctx: ReportContext, names: Sequence[str], evaluations: Sequence[str],
                 warnings: list[str] | None = None) -> list[Table]:
    """Every requested table, for every requested evaluation, in that order; a table that does not apply to
    these runs (``NoData``) is skipped with one line in ``warnings``."""
    out = []
    for name in names:
        for ev in (evaluations[:1] if name in ONCE else evaluations):
            try:
                out.append(TABLES[name](ctx, ev))
            except NoData as exc:
                if warnings is not None:
                    warnings.append(str(exc))
                break
    return without_repeats(out, warnings)


def _rows_of(table: Table) -> frozenset:
    """A table's model rows as what they hold: each row's runs (its labels aside)."""
    return frozenset(frozenset(r.runs) for r in table.rows if r.kind == "model" and r.runs)


def _evaluation(table: Table) -> str:
    return table.key.rsplit("-", 1)[-1]


def repeats(table: Table, other: Table) -> bool:
    """Whether ``table``'s rows are ``other``'s (the same runs per row, the same evaluation) and ``other`` shows
    every column it shows: e.g. a two-model plan's Table 2, its rows Table 6's (accumulated) under other labels."""
    mine = _rows_of(table)
    return (bool(mine) and table is not other and mine == _rows_of(other) and _evaluation(table) == _evaluation(other)
            and {c.heading for c in table.columns} <= {c.heading for c in other.columns})


def without_repeats(tables: Sequence[Table], warnings: list[str] | None = None) -> list[Table]:
    """The tables less each that repeats another (``repeats``; of two that repeat each other, the later goes):
    it is not written, and its skill figure with it; one line in ``warnings`` says which table holds its rows."""
    kept: list[Table] = []
    for i, t in enumerate(tables):
        other = next((o for j, o in enumerate(tables) if repeats(t, o) and not (repeats(o, t) and j > i)), None)
        if other is None:
            kept.append(t)
        elif warnings is not None:
            warnings.append(f"{t.key} not written: its rows are those of {other.title.split('.')[0]} "
                            f"({other.key}) under other labels")
    return kept


def write_tables(tables: Sequence[Table], out: Path, suffixes: Sequence[str]) -> list[Path]:
    """The tables in each format and, when there is one, the Methods page their captions point to."""
    files = [write_text(Path(out) / f"{t.key}.{s}", RENDERERS[s](t)) for t in tables for s in suffixes]
    return files + (write_methods(out, list(suffixes)) if tables else [])


def dataset_figures(root: Path, out: Path, warnings: list[str]) -> list[Path]:
    """The dataset's sample-frame montage and positions plot (data preview); a missing dataset is a warning."""
    try:
        montage = dataset_figs.montage_figure(root)
        positions = dataset_figs.positions_figure(root, warnings=warnings)
    except (DataError, OSError, ImportError) as exc:
        warnings.append(f"figures: no dataset figures ({type(exc).__name__}: {exc})")
        return []
    return save_figure(montage, out / "fig-dataset-frames", FORMATS) + \
        save_figure(positions, out / "fig-dataset-positions", FORMATS)


def make_report(
    ctx: ReportContext,
    names: Sequence[str],
    evaluations: Sequence[str],
    suffixes: Sequence[str],
    out: Path,
    *,
    loader: Loader | None = None,
    n_trajectories: int = 4,
    dataset_root: Path | None = None,
    warnings: list[str] | None = None,
    progress: Callable[[str], None] | None = None,
) -> ReportResult:
    """Tables (and, with a ``loader``, the run figures, skill figures and learning curve; with
    ``dataset_root``, the dataset figures) under ``out``.

    ``warnings`` (the list a loader reports into, if any) becomes ``result.warnings``, after the index's
    notes and the skipped tables. A figure group whose inputs did not change since the last report into
    ``out`` is not redrawn (``figure_cache``); ``progress`` hears each phase.
    """
    warnings = warnings if warnings is not None else []
    say = progress or (lambda text: None)
    notes: list[str] = list(ctx.index.notes)
    say("building the tables")
    tables = build_tables(ctx, names, evaluations, notes)
    with staged_outputs(Path(out)) as stage:  # all files, or none: a failure half-way leaves ``out`` as it was
        result = ReportResult(tables, write_tables(tables, stage, suffixes), warnings)
        result.warnings[:0] = notes
        figures = FigureCache(Path(out), stage)  # each group drawn only when its inputs changed
        runs_key = digest(sorted(r.run_id for r in ctx.index.runs.values()), ctx.index.pose_frame, n_trajectories)
        if loader is not None:
            say("figures: trajectories and errors per frame (reads the runs' predictions)")
            result.files += figures.once("runs", runs_key, result.warnings, lambda: make_figures(
                ctx.index, loader, stage, n_trajectories, result.warnings))
            say("figures: skill per table, learning curve")
            tables_key = files_key(p for p in result.files if p.suffix == ".md") + repr(
                [t.key for t in tables])
            result.files += figures.once("skill", tables_key, result.warnings,
                                         lambda: skill_figures(tables, stage, result.warnings))
            result.files += figures.once("learning-curve", runs_key, result.warnings,
                                         lambda: learning_curve(ctx, stage, result.warnings))
            if ctx.history is not None:
                result.files += figures.once("training-curves", runs_key, result.warnings, lambda: training_curves(
                    list(ctx.index.runs.values()), ctx.history, stage, result.warnings))
        if dataset_root is not None:
            say("figures: dataset frames and positions")
            meta = Path(dataset_root) / "metadata.json"
            data_key = digest(str(dataset_root), meta.read_bytes() if meta.is_file() else b"")
            result.files += figures.once("dataset", data_key, result.warnings,
                                         lambda: dataset_figures(Path(dataset_root), stage, result.warnings))
        if figures.reused:
            say(f"figures unchanged since the last report, not redrawn: {', '.join(figures.reused)}")
        if loader is not None or dataset_root is not None:
            figures.save()
        result.files = publish(stage, Path(out), result.files)
    return result


def publish(stage: Path, out: Path, files: Sequence[Path]) -> list[Path]:
    """Move the staged files into ``out`` (renames within one file system: no file is ever half-written); files
    already in ``out`` (figures not redrawn) stay where they are, and so does the staged figure record."""
    moved = []
    record = stage / RECORD
    if record.is_file():
        os.replace(record, out / RECORD)
    for f in files:
        if not Path(f).is_relative_to(stage):
            moved.append(Path(f))
            continue
        final = out / Path(f).relative_to(stage)
        final.parent.mkdir(parents=True, exist_ok=True)
        os.replace(f, final)
        moved.append(final)
    return moved


STAGE = re.compile(rf"^\.report-(\d+)-[0-9a-f]{{8}}@(.+){re.escape(TEMP_SUFFIX)}$")  # .report-<pid>-<hex>@<host>.tmp


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def stale_stages(out: Path) -> list[Path]:
    """Staging folders in ``out`` left by a report of this host whose process is gone (SIGKILL, power loss)."""
    host = socket.gethostname()
    found = []
    for p in out.iterdir() if out.is_dir() else ():
        m = STAGE.match(p.name)
        if m and m.group(2) == host and not p.is_symlink() and p.is_dir() and not _pid_alive(int(m.group(1))):
            found.append(p)
    return found


@contextmanager
def staged_outputs(out: Path) -> Iterator[Path]:
    """A hidden staging folder inside ``out``, removed afterwards (with whatever a failed report left in it).

    Staging folders that an earlier report of this host left when it was killed (its process gone) are removed
    first; only folders named like this function's own (``STAGE``) are ever removed.
    """
    out.mkdir(parents=True, exist_ok=True)
    for old in stale_stages(out):
        shutil.rmtree(old, ignore_errors=True)
    stage = out / f".report-{os.getpid()}-{uuid.uuid4().hex[:8]}@{socket.gethostname()}{TEMP_SUFFIX}"
    stage.mkdir()
    try:
        yield stage
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def summary_index(index: RunIndex) -> str:
    """One line: how many runs the report sees and how many were set aside."""
    dup = sum(len(v) for v in index.duplicates.values())
    unfinished = sum(len(v) for v in index.unfinished.values())
    scope = (f"{len(index.runs)} of the config's {len(index.plan.keys)} cells have a FINISHED run"
             if index.plan is not None else f"{len(index.runs)} cells with a FINISHED run")
    text = (f"sweep {index.sweep!r} (experiment {index.experiment!r}, pose frame {index.pose_frame!r}): "
            f"{scope}, {dup} superseded duplicate(s), "
            f"{len(index.unfinished)} cell(s) with only unfinished runs ({unfinished} run(s))")
    if index.other_configs:
        text += f", {index.other_configs} run(s) of other configs left out"
    return text


def open_store(cfg: Config):
    """The config's MLflow client; a missing SQLite store is an error here (a report must not create one)."""
    require_store(cfg)
    return client_for(cfg, reading=True)


def log_to_parent(client, cfg: Config, sweep: str, out: Path, files: Sequence[Path]) -> str:
    """The report's files as artifacts of the sweep's parent run (under ``report/``, the layout of ``out``), so
    the MLflow UI shows the sweep's tables and figures; returns the line to print (what was logged, or why not).

    Nothing is created: no parent (runs made by ``train``, not a sweep), or a parent whose artifacts live
    outside this project's ``runs.artifacts`` (a store read where another project keeps them), is one line.
    """
    exp = client.get_experiment_by_name(cfg.experiment_name)
    parent = find_parent(client, exp.experiment_id, KIND_SWEEP, sweep) if exp is not None else None
    if parent is None and exp is not None and (line := deleted_parent_line(client, exp.experiment_id, KIND_SWEEP,
                                                                           sweep)):
        return f"not logged to MLflow: {line}"
    if parent is None:
        return f"not logged to MLflow: sweep {sweep!r} has no parent run (its runs were not made by `sweep`)"
    if not writes_here(cfg, client.get_run(parent).info.artifact_uri):
        return (f"not logged to MLflow: the parent run {parent} of sweep {sweep!r} keeps its artifacts outside "
                f"runs.artifacts ({cfg.paths.artifacts})")
    n = log_report(client, parent, out, files)
    return f"logged {n} file(s) to the parent run {parent} of sweep {sweep!r} (artifacts {REPORT_FOLDER}/)"


def profiles_from_json(path: Path) -> Profiler:
    """A profiler answering from `bronchopose profile --format json` output (no measuring)."""
    try:
        rows = json.loads(Path(path).read_text())
        by_arch = {r["arch"]: r for r in rows}
    except (OSError, ValueError, TypeError, KeyError) as exc:
        raise BronchoError(f"--latency-from {path}: expected the JSON list of `bronchopose profile --format json` "
                           f"({type(exc).__name__}: {exc})") from None
    return lambda arch: by_arch.get(arch)


def measuring_profiler(image_size: int, device: str, record: Path | None = None, repeats: int = 3) -> Profiler:
    """Batch-1 latency and GMAC per architecture from ``record`` (a JSON of rows this function measured before,
    for this device and size), else measured (``models.profile.profile_arch``, batch 1 only, median of
    ``repeats`` after one warm-up) and added to ``record``: a report times each architecture once per machine.
    Delete the record (or pass ``--latency-from``) to measure again."""
    recorded: dict[str, Any] = {}
    if record is not None and record.is_file():
        try:
            recorded = json.loads(record.read_text())
        except ValueError:
            recorded = {}

    def profile(arch: str):
        if arch in recorded:
            return {**recorded[arch], "recorded": str(record)}
        from ..models.profile import profile_arch  # lazy: torch only when the ablation table is measured

        row = profile_arch(arch, image_size=image_size, device=device, batch=1, repeats=repeats, warmup=1,
                           batch_n=False)
        if record is not None:
            recorded[arch] = row
            record.parent.mkdir(parents=True, exist_ok=True)
            write_json(record, recorded)
        return row
    return profile


def latency_record(cfg: Config, image_size: int, device: str) -> Path:
    """Where the report keeps the latencies it measured for this device and input size (the frame cache's
    folder: per machine, never committed)."""
    return cfg.paths.cache / f"ablation-latency-{device}-{image_size}.json"


def default_image_size(cfg: Config) -> int:
    return cfg.data.image_size or cfg.dataset.generate.image_size
