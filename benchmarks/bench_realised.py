"""Speed in the sweep against speed alone (issue 39, item 1): per architecture of the main job, the training
pairs/s its cells realise in a real 2-worker sweep ÷ the best pairs/s of the architecture alone at the same
threads (goal: >= 0.85), and whether the shipped speed setting is the best in the sweep too.

    python benchmarks/bench_realised.py [--set KEY=VALUE ...] [--alone-steps 100] [--settings LIST]
                                        [--sweep-settings all|none|LIST] [--compare-steps 160] [--phases]

1. **The sweep**: ``bronchopose sweep run --workers 2`` of the default plan (the repository's experiments.yaml
   and the ``--set`` overrides, e.g. fewer steps) in a temporary project on a dataset rendered first
   (``data generate``); per cell its ``train.pairs_per_s`` (pairs over training time: start-up, validation,
   checkpoints and test evaluation excluded) and the speed setting it logged (``speed.precision``,
   ``speed.channels_last``, ``speed.source``: the shipped bronchocli/speed_settings.json entry of this CPU's
   vector instructions) and ``threads``.
2. **Alone**: each architecture of the plan as one ``bronchopose train`` process, nothing else of the
   benchmark running, at the threads the sweep's cells logged, in every candidate setting (fp32 / bf16 autocast
   × channels-last / contiguous: ``--set train.precision`` and ``--set model.channels_last``; bf16 only where
   the CPU has native bf16, as ``profile --speed``, unless ``--settings`` names it), ``--alone-steps`` steps.
3. **The sweep in each setting** (``--sweep-settings``, default every candidate): the same sweep with one
   setting forced on every cell, ``--compare-steps`` steps each, so "best in the sweep" is measured, not
   assumed from the single-process ranking.

``--phases`` also times the report and prints bench_phases.py's phase table of the main sweep.
The claims folder is private (bench_common.private_env): only the benchmark's processes share the cores.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from collections import defaultdict
from pathlib import Path

from bench_common import cell_runs, cpu_line, private_env, timed
from bench_phases import new_project, print_phases, run_main_job, set_args

from bronchocli.speed import cpu_key

# label (as speed_settings.json names the candidates) -> (train.precision, model.channels_last)
SETTINGS = {"fp32 CL": ("32", True), "fp32 contiguous": ("32", False), "bf16 CL": ("bf16-mixed", True),
            "bf16 contiguous": ("bf16-mixed", False)}
SLUG = {label: label.replace(" ", "-").lower() for label in SETTINGS}  # on the command line: fp32-cl, ...


def setting_of(params: dict[str, str]) -> str:
    """The candidate label of a run's logged speed setting."""
    want = (params.get("speed.precision", "?"), params.get("speed.channels_last", "?") == "true")
    return next((label for label, s in SETTINGS.items() if s == want), f"{want[0]} CL={want[1]}")


def forced(label: str) -> list[str]:
    precision, cl = SETTINGS[label]
    return [f"train.precision={precision}", f"model.channels_last={str(cl).lower()}"]


def parse_settings(text: str, default: list[str]) -> list[str]:
    if text == "all":
        return default
    if text == "none":
        return []
    by_slug = {v: k for k, v in SLUG.items()}
    out = [by_slug.get(s.strip().lower(), s.strip()) for s in text.split(",") if s.strip()]
    bad = [s for s in out if s not in SETTINGS]
    if bad:
        raise SystemExit(f"unknown setting(s) {', '.join(bad)} (valid: {', '.join(SLUG.values())})")
    return out


def by_arch(folder: Path, overrides: list[str]) -> dict[str, list[dict]]:
    """Per architecture, its cells: pairs/s, setting, speed source, threads."""
    out: dict[str, list[dict]] = defaultdict(list)
    for run in cell_runs(folder, overrides):
        p = run.data.params
        out[p.get("arch", "?")].append({"rate": run.data.metrics["train.pairs_per_s"], "setting": setting_of(p),
                                        "source": p.get("speed.source", "?"), "threads": p.get("threads", "?"),
                                        "rot_loss": p.get("rot_loss", "mse"), "seed": p.get("seed", "?")})
    return out


def alone(root: Path, env: dict, sets: list[str], cells: dict[str, list[dict]], labels: list[str],
          steps: int, threads: str) -> dict[tuple[str, str], float]:
    """Each architecture alone in each setting: pairs/s."""
    rates = {}
    extra = [f"train.steps={steps}", f"train.val_every={steps}", f"train.threads={threads}",
             "runs.model_artifact=none"]
    for label in labels:
        folder = new_project(root, f"alone-{SLUG[label]}")
        overrides = [*sets, *extra, *forced(label)]
        for arch, runs in cells.items():
            timed(folder, env, "train", "--arch", arch, "--rot-loss", runs[0]["rot_loss"], "--population",
                  "personalized", "--seed", "0", "--quiet", *set_args(overrides), log=f"train-{arch}.log")
        for arch, runs in by_arch(folder, overrides).items():
            rates[(arch, label)] = runs[0]["rate"]
            print(f"# alone: {arch} {label}: {runs[0]['rate']:.1f} pairs/s", flush=True)
    return rates


def sweeps(root: Path, env: dict, sets: list[str], labels: list[str], steps: int) -> dict[tuple[str, str], float]:
    """The sweep with one setting forced on every cell: mean pairs/s per architecture."""
    rates = {}
    for label in labels:
        folder = new_project(root, f"sweep-{SLUG[label]}")
        overrides = [*sets, f"train.steps={steps}", *forced(label)]
        wall = timed(folder, env, "sweep", "run", "--workers", "2", *set_args(overrides), log="sweep.log")
        for arch, runs in by_arch(folder, overrides).items():
            rates[(arch, label)] = statistics.mean(r["rate"] for r in runs)
            print(f"# sweep in {label}: {arch} {rates[(arch, label)]:.1f} pairs/s (wall {wall:.0f} s)", flush=True)
    return rates


def report(cells: dict[str, list[dict]], solo: dict, swept: dict, labels: list[str], sweep_labels: list[str]) -> None:
    print("\n| arch | cells | setting in the sweep (source) | threads | realised pairs/s in the sweep (min–max) | "
          "best alone pairs/s (setting) | realised ÷ best alone (goal ≥ 0.85) | alone in the sweep's setting | "
          "best in the sweep (setting) | shipped best in the sweep too? |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for arch, runs in sorted(cells.items()):
        rates = [r["rate"] for r in runs]
        real = statistics.mean(rates)
        shipped = runs[0]["setting"]
        mine = {label: solo[(arch, label)] for label in labels if (arch, label) in solo}
        best = max(mine, key=mine.get) if mine else None
        theirs = {label: swept[(arch, label)] for label in sweep_labels if (arch, label) in swept}
        top = max(theirs, key=theirs.get) if theirs else None
        if top is None or shipped not in theirs:
            verdict = "not measured" + ("" if top is None else f" ({shipped} not among --sweep-settings)")
        else:
            verdict = "yes" if top == shipped else f"no: {theirs[top] / theirs[shipped]:.2f}× with {top}"
        print(f"| {arch} | {len(runs)} | {shipped} ({runs[0]['source']}) | {runs[0]['threads']} | "
              f"{real:.1f} ({min(rates):.1f}–{max(rates):.1f}) | "
              + (f"{mine[best]:.1f} ({best}) | {real / mine[best]:.2f} | " if best else "— | — | ")
              + (f"{mine[shipped]:.1f}" if shipped in mine else "—") + " | "
              + (f"{theirs[top]:.1f} ({top})" if top else "not measured (--sweep-settings)") + f" | {verdict} |")
    if solo:
        print("\nalone, pairs/s per setting:")
        print("| arch | " + " | ".join(labels) + " |")
        print("|---|" + "---|" * len(labels))
        for arch in sorted(cells):
            print(f"| {arch} | " + " | ".join(f"{solo[(arch, s)]:.1f}" if (arch, s) in solo else "—" for s in labels)
                  + " |")
    if swept:
        print("\nin the sweep (every cell in one setting, mean over its cells), pairs/s per setting:")
        print("| arch | " + " | ".join(sweep_labels) + " |")
        print("|---|" + "---|" * len(sweep_labels))
        for arch in sorted(cells):
            print(f"| {arch} | " + " | ".join(f"{swept[(arch, s)]:.1f}" if (arch, s) in swept else "—"
                                              for s in sweep_labels) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="a config override for every command (as `bronchopose --set`)")
    parser.add_argument("--settings", default="all", help="alone: all (bf16 only with native bf16), or a list "
                        f"of {', '.join(SLUG.values())}")
    parser.add_argument("--sweep-settings", default="all", help="sweeps with one setting forced: all (the "
                        "--settings list), none, or a list")
    parser.add_argument("--alone-steps", type=int, default=100, help="optimiser steps of each alone run")
    parser.add_argument("--compare-steps", type=int, default=160, help="optimiser steps of the forced sweeps")
    parser.add_argument("--phases", action="store_true", help="also time the report and print the phase table")
    parser.add_argument("--install-s", type=float, help="--phases: the install's seconds, measured apart")
    parser.add_argument("--keep", type=Path, help="run in this (new) folder and keep it")
    args = parser.parse_args()
    native = cpu_key().endswith("+bf16")
    candidates = [s for s in SETTINGS if native or s.startswith("fp32")]
    labels = parse_settings(args.settings, candidates)
    sweep_labels = parse_settings(args.sweep_settings, labels)
    print(f"# {cpu_line()}", flush=True)
    with tempfile.TemporaryDirectory(prefix="bench-realised-") as tmp:
        root = args.keep.resolve() if args.keep else Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        user_sets = list(args.overrides)
        if not any(s.startswith("dataset.root=") for s in user_sets):
            user_sets.append(f"dataset.root={root / 'data'}")  # one dataset for every project of the benchmark
        env = private_env(root)
        job = run_main_job(root, user_sets, report=args.phases)
        cells = by_arch(job.folder, user_sets)
        threads = statistics.mode(r["threads"] for runs in cells.values() for r in runs)
        solo = alone(root, env, user_sets, cells, labels, args.alone_steps, threads)
        swept = sweeps(root, env, user_sets, sweep_labels, args.compare_steps)
        print(f"\n# {cpu_line()} (at the end); alone: {args.alone_steps} steps, {threads} thread(s); forced "
              f"sweeps: {args.compare_steps} steps; the main sweep: the plan with {' '.join(args.overrides) or '—'}")
        report(cells, solo, swept, labels, sweep_labels)
        if args.phases:
            print_phases(job, args.install_s)


if __name__ == "__main__":
    main()
