"""The documents' config numbers, from experiments.yaml (one source), and the check of the numbers typed beside a
profile's name.

benchmarks/docblocks.py quotes measured figures from results files; a profile's size, budget, objective and
seeds are not measured: experiments.yaml states them. ``facts()`` reads every plan of experiments.yaml (the
default, as ``default``, and each profile by its name) through the platform's own loader and planner, and
docblocks offers it as the results entry ``config``: ``<!-- n: config/learning-curve/steps as , -->5,000<!-- /n -->``
quotes a profile's budget, ``<!-- n: config/default/size -->…<!-- /n -->`` its whole size, and the block
``<!-- numbers: profiles -->`` renders every plan's table. A changed config is then a changed span that
``python benchmarks/docblocks.py --write`` regenerates.

A number typed into prose (not a span) next to a profile's name can still drift, so ``typed(paths, facts)``
reads every table row, table cell under a profile's column and sentence of the documents that names exactly
one plan (```learning-curve```, ``--profile paper``, ``profiles.gpu-bench``; the default as "default plan",
"CPU default", "default config" or a table's "(default)" row) and checks its typed quantities against that
plan: ``N steps``, ``every N steps``, ``N pairs``, ``N²`` / ``N×N``, ``N seeds``, ``N patients``, ``N cells``,
``N trials``, ``N trajectories per lobe`` and ``objective `X```. Inline code and ``--set`` overrides are not
prose about the plan and are skipped; so is a sentence that says what a plan *was* (a date, "before",
"earlier"), which is history, or quotes another source ("the paper says"), not the config.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "experiments.yaml"
DEFAULT = "default"


# -- the facts ---------------------------------------------------------------------------------------------------------

def plan_names(config: Path = CONFIG) -> list[str]:
    """``default`` and every profile of ``config``, in the file's order."""
    raw = yaml.safe_load(config.read_text(encoding="utf-8")) or {}
    return [DEFAULT, *(raw.get("profiles") or {})]


def facts(config: Path = CONFIG) -> dict[str, dict]:
    """Per plan (``default`` and each profile): its sizes, budget, objective and seeds, and ``size``, the one
    line the documents show; ``resolved``: the whole resolved config."""
    from bronchocli.config.loading import load_config

    raw = yaml.safe_load(config.read_text(encoding="utf-8")) or {}
    out = {}
    for name in plan_names(config):
        cfg = load_config(config, None if name == DEFAULT else name)
        tuning = name != DEFAULT and "tune" in (raw.get("profiles", {}).get(name) or {})
        out[name] = plan_facts(cfg, tuning)
    return out


def plan_facts(cfg, tuning: bool = False) -> dict:
    """The facts of one resolved config (``tuning``: the plan is a tuning study, sized by its trials)."""
    from bronchocli.config.grid import source_of, stage_cells, stages_of
    from bronchocli.generation.sources import patient_sources

    gen, train, tune = cfg.dataset.generate, cfg.train, cfg.tune
    patients = [s.patient for s in patient_sources(gen, cfg.paths.anatomy, cfg.paths.centreline)]  # as planned
    cells: dict[str, list] = {}
    for stage in stages_of(cfg):
        combos = []
        if stage.select is not None:  # the first `top` combinations of its source: the size it will have
            for c in cells[source_of(cfg, stage).name]:
                combo = {f: getattr(c, f) for f in stage.select.over}
                if combo not in combos:
                    combos.append(combo)
            combos = combos[: stage.select.top]
        cells[stage.name] = stage_cells(cfg, stage, patients, combos)
    every = [c for stage in cells.values() for c in stage]
    pps = train.pairs_per_step
    f = {
        "name": cfg.name,
        "image_size": gen.image_size,
        "patients": gen.patients,
        "lobes": len(gen.lobes),
        "trajectories": gen.trajectories,
        "splits": f"{cfg.splits.train}/{cfg.splits.val}/{cfg.splits.test}",
        "window": cfg.data.window,
        "steps": train.steps,
        "batch_size": train.batch_size,
        "pairs_per_step": pps,
        "pairs": train.steps * pps,
        "val_every": train.val_every,
        "val_every_pairs": train.val_every * pps,
        "lr": train.lr,
        "schedule": train.schedule,
        "threads": train.threads,
        "precision": train.precision,
        "seeds": list(cfg.grid.seed),
        "n_seeds": len({c.seed for c in every}),
        "stages": [s for s in cells],
        "stage_cells": [len(v) for v in cells.values()],
        "cells": len(every),
        "models": len({(c.arch, c.rot_loss) for c in every}),
        "archs": sorted({c.arch for c in every}),
        "losses": len({c.rot_loss for c in every}),
        "objective": tune.objective,
        "trials": tune.trials,
        "budget_pairs": tune.budget_pairs,
        "tuning": tuning,
        "resolved": cfg.model_dump(mode="json"),
    }
    f["size"] = size(f)
    return f


def plural(n: int, word: str) -> str:
    return f"{n:,} {word}{'' if n == 1 else 'es' if word.endswith('s') else 's'}"


def size(f: dict) -> str:
    """A plan's size in one line: '4 cells (2 models × 2 seeds), 96², 3 patients, 500 steps × 20 pairs'."""
    if f["tuning"]:
        parts = [plural(f["trials"], "trial"), f"{f['image_size']}²", plural(f["patients"], "patient"),
                 f"≤ {f['budget_pairs'] or f['pairs']:,} pairs each"]
    else:
        if len(f["stages"]) > 1:
            what = (f"{len(f['stages'])} stages of {' + '.join(map(str, f['stage_cells']))} cells, "
                    f"{plural(f['n_seeds'], 'seed')}")
        elif f["cells"] == 1:
            what = "1 cell"
        else:
            models = (f"{plural(len(f['archs']), 'architecture')} × {plural(f['losses'], 'loss')}"
                      if len(f["archs"]) > 1 and f["losses"] > 1 and f["models"] == len(f["archs"]) * f["losses"]
                      else plural(f["models"], "model"))
            what = f"{plural(f['cells'], 'cell')} ({models} × {plural(f['n_seeds'], 'seed')}"
            what += ")" if f["cells"] == f["models"] * f["n_seeds"] else " × folds)"
        parts = [what, f"{f['image_size']}²", plural(f["patients"], "patient"),
                 f"{f['steps']:,} steps × {f['pairs_per_step']:,} pairs"]
    if f["threads"]:
        each = "" if f["cells"] == 1 else " each"
        parts.append(f"one thread{each}" if f["threads"] == 1 else f"{f['threads']} threads{each}")
    if f["precision"] not in ("auto", "32"):
        parts.append(f["precision"])
    return ", ".join(parts)


def profiles_block(all_facts: dict[str, dict]) -> list[str]:
    """docs/config.md's table of every plan of experiments.yaml."""
    lines = ["| plan | experiment | dataset | trajectories per lobe (train/val/test) | budget per cell | validation "
             "| seeds | cells | objective |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, f in all_facts.items():
        plan = "(default)" if name == DEFAULT else f"`{name}`"
        budget = (f"≤ {f['budget_pairs']:,} pairs per trial, {f['trials']} trials" if f["tuning"] and f["budget_pairs"]
                  else f"{f['steps']:,} steps × {f['pairs_per_step']:,} pairs = {f['pairs']:,} pairs")
        cells = " + ".join(map(str, f["stage_cells"])) if len(f["stage_cells"]) > 1 else str(f["cells"])
        lines.append(f"| {plan} | `{f['name']}` | {f['image_size']}², {plural(f['patients'], 'patient')} "
                     f"| {f['trajectories']} ({f['splits']}) | {budget} | every {f['val_every']:,} steps "
                     f"| {', '.join(map(str, f['seeds']))} | {cells} | `{f['objective']}` |")
    return lines


# -- the typed numbers -------------------------------------------------------------------------------------------------

NUM = r"(\d{1,3}(?:,\d{3})+|\d+(?:\.\d+)?)(k?)"
QUANTITIES: list[tuple[str, re.Pattern, str]] = [
    # (what, pattern, the facts it may equal): "every N steps" before "N steps"
    ("validation interval", re.compile(rf"(?:validation|validated|validations?) every {NUM}(?: steps)?\b|"
                                       rf"\bevery {NUM} steps\b"), "val_every"),
    ("steps", re.compile(rf"(?<![\w.,]){NUM}\s(?:optimi[sz]er )?steps\b"), "steps"),
    ("pairs", re.compile(rf"(?<![\w.,]){NUM}\s(?:image )?pairs\b"), "pairs"),
    ("image size", re.compile(rf"(?<![\w.,]){NUM}(?:²|\s?[×x]\s?\d+\b)"), "image_size"),
    ("seeds", re.compile(rf"(?<![\w.,]){NUM}\sseeds\b"), "n_seeds"),
    ("patients", re.compile(rf"(?<![\w.,]){NUM}\s(?:procedural )?patients\b"), "patients"),
    ("cells", re.compile(rf"(?<![\w.,]){NUM}\scells\b"), "cells"),
    ("trials", re.compile(rf"(?<![\w.,]){NUM}\strials\b"), "trials"),
    ("trajectories", re.compile(rf"(?<![\w.,]){NUM}\strajectories per (?:patient and )?lobe\b"), "trajectories"),
]
OBJECTIVE = re.compile(r"objective:?\s+`([\w.]+)`")
SPAN = re.compile(r"<!-- n: .*?<!-- /n -->", re.S)
FENCE = re.compile(r"^```.*?^```", re.S | re.M)
CODE = re.compile(r"`[^`\n]*`")
# history (a date, "before", "was") or another source's words ("the paper says"): not what the config states
NOT_THE_CONFIG = re.compile(r"\b\d{4}-\d{2}-\d{2}\b|\bbefore\b|\bearlier\b|\bwas\b|\bwere\b|\bused to\b|"
                            r"\bthe (?:paper|text|paper's text) says\b")
SENTENCE = re.compile(r"(?<=[.;!?])\s+(?=[A-Z(`*\"])|\n(?=\s*(?:[-*] |\d+\. ))")
DEFAULT_WORDS = re.compile(r"\(default\)|\bdefault plan\b|\bCPU default\b|\bdefault config\b")


def allowed(f: dict, key: str) -> set:
    """The facts a typed quantity may equal."""
    if key == "pairs":
        return {f["batch_size"], f["pairs_per_step"], f["pairs"], f["val_every_pairs"], f["window"],
                *([f["budget_pairs"]] if f["budget_pairs"] else [])}
    if key == "cells":
        return {f["cells"], *f["stage_cells"]}
    if key == "n_seeds":
        return {f["n_seeds"], len(f["seeds"])}
    return {f[key]}


def named(text: str, names: Iterable[str]) -> set[str]:
    """The plans ``text`` names."""
    out = set()
    for name in names:
        if name == DEFAULT:
            if DEFAULT_WORDS.search(text):
                out.add(name)
        elif re.search(rf"(?:--profile[ =]|`|profiles\.){re.escape(name)}(?![\w-])", text):
            out.add(name)
    return out


def number(text: str, k: str) -> float:
    v = float(text.replace(",", ""))
    return v * 1000 if k else v


def disagreements(text: str, f: dict) -> list[str]:
    """What ``text`` (prose about one plan) types that the plan's facts do not say."""
    prose = CODE.sub("", text)
    out = []
    for what, pattern, key in QUANTITIES:
        ok = allowed(f, key)
        for m in pattern.finditer(prose):
            got = [g for g in m.groups() if g is not None]
            value = number(got[0], got[1] if len(got) > 1 else "")
            if key == "image_size" and value < 16:
                continue  # a feature map ("3×3 in the last stage"), not a frame
            if value not in ok:
                out.append(f"{what} {m.group(0).strip()!r} (experiments.yaml: {', '.join(map(str, sorted(ok)))})")
        prose = pattern.sub(" ", prose)  # a quantity is read once ("every 250 steps" is not also "250 steps")
    for m in OBJECTIVE.finditer(text):
        if m.group(1) != f["objective"]:
            out.append(f"objective {m.group(1)!r} (experiments.yaml: {f['objective']!r})")
    return out


def units(text: str, names: list[str]) -> Iterable[tuple[int, str, set[str]]]:
    """(line, text, the plans it is about) of every table row, profile column cell and sentence of ``text``."""
    text = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), SPAN.sub(lambda m: "…" + "\n" * m.group(0).count("\n"), text))
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        if lines[i].lstrip().startswith("|"):
            header = [c.strip() for c in lines[i].strip().strip("|").split("|")]
            columns = {j: named(h, names) for j, h in enumerate(header)}
            j = i + 1
            while j < len(lines) and lines[j].lstrip().startswith("|"):
                if not re.fullmatch(r"\s*\|[-:| ]+\|?\s*", lines[j]):
                    cells = [c.strip() for c in re.split(r"(?<!\\)\|", lines[j].strip().strip("|"))]
                    rest = []
                    for k, cell in enumerate(cells):
                        if len(columns.get(k, ())) == 1:
                            yield j + 1, cell, columns[k]
                        else:
                            rest.append(cell)
                    yield j + 1, " | ".join(rest), named(" | ".join(rest), names)
                j += 1
            i = j
            continue
        start = i
        para = []
        while i < len(lines) and lines[i].strip() and not lines[i].lstrip().startswith("|"):
            para.append(lines[i])
            i += 1
        if not para:
            i += 1
            continue
        joined = "\n".join(para)
        offset = 0
        for piece in SENTENCE.split(joined):
            at = joined.find(piece, offset)
            offset = at + len(piece)
            yield start + 1 + joined.count("\n", 0, at), piece, named(piece, names)


def typed(paths: Iterable[Path], all_facts: dict[str, dict], root: Path = ROOT) -> list[str]:
    """One line per quantity typed next to exactly one plan's name that experiments.yaml contradicts."""
    names = list(all_facts)
    out = []
    for path in paths:
        if path.suffix != ".md":
            continue
        rel = path.relative_to(root) if path.is_relative_to(root) else path
        for line, text, plans in units(path.read_text(encoding="utf-8"), names):
            if len(plans) != 1 or "--set" in text or NOT_THE_CONFIG.search(CODE.sub("", text)):
                continue
            plan = next(iter(plans))
            for problem in disagreements(text, all_facts[plan]):
                out.append(f"{rel}:{line}: next to {'the default plan' if plan == DEFAULT else plan}: typed {problem}; "
                           "quote it as a span of config/… or correct it")
    return out
