"""Sharing the cores (issue 40): two ``bronchopose train`` at once before / after, and a ``train`` beside a
2-worker ``sweep``; training pairs/s of every run.

    python benchmarks/bench_share.py [--arch offsetnet] [--steps 150] [--image-size 64] [--only alone,two-after]

Every scenario starts real commands as subprocesses, each in its own project folder (its own MLflow store) on
one rendered dataset (2 patients, 64², generated once), and reads back each run's ``train.pairs_per_s``
(pairs over training time: start-up, validation and evaluation excluded) and its ``threads`` /
``threads.source`` params.

* ``alone``: one ``train`` with the default threads (its share: every core);
* ``two-before``: two ``train`` started at once, each with ``train.threads`` = every core (what every command
  took before issue 40);
* ``two-after``: two ``train`` started at once with the default threads (each its share);
* ``sweep-before``: a ``train`` beside ``sweep --workers 2`` (two cells), the workers pinned to cores / 2 and
  the ``train`` on every core (the old defaults);
* ``sweep-after``: the same with the default threads.

The claims folder is private to the benchmark (``XDG_RUNTIME_DIR`` = a temporary folder), so processes of
the project outside the benchmark do not change its shares; a load that is not the project's (another
program, a training run of an older version) is never counted by the shares, and slows every scenario alike.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import tempfile
import textwrap
from pathlib import Path

from bench_common import cell_runs, cpu_line, finish, private_env, start

from bronchocli.config import load_config
from bronchocli.generation import ensure_dataset
from bronchocli.runs.cores import machine_cores

CONFIG = """\
    name: share-{name}
    dataset:
      root: {data}
      generate: {{patients: 2, lobes: [ur, br, ul, bl], trajectories: 6, image_size: {size}, step_mm: [2.0, 4.0],
                 max_frames: 24, workers: 2}}
    splits: {{train: 4, val: 1, test: 1}}
    grid: {{arch: [{arch}], rot_loss: [mse], population: [personalized], folds: [p00], seed: [1, 2],
           pose_frame: [camera]}}
    data: {{window: 10}}
    train: {{steps: {steps}, batch_size: 20, val_every: {val_every}, max_val_pairs: 40, bn_recalibrate: 4}}
    runs: {{model_artifact: none}}
"""
SCENARIOS = ("alone", "two-before", "two-after", "sweep-before", "sweep-after")


def project(root: Path, name: str, args: argparse.Namespace, data: Path) -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    (folder / "experiments.yaml").write_text(textwrap.dedent(CONFIG.format(
        name=name, data=data, size=args.image_size, arch=args.arch, steps=args.steps,
        val_every=max(1, args.steps // 3))))
    return folder


def train(folder: Path, env: dict[str, str], arch: str, threads: int | None) -> subprocess.Popen:
    extra = ["--set", f"train.threads={threads}"] if threads else []
    return start(folder, env, "train", "--arch", arch, "--rot-loss", "mse", "--population", "personalized",
                 "--seed", "0", "--quiet", *extra)


def sweep(folder: Path, env: dict[str, str], threads: int | None) -> subprocess.Popen:
    extra = ["--set", f"train.threads={threads}"] if threads else []
    return start(folder, env, "sweep", "--workers", "2", *extra)


def runs_of(folder: Path) -> list[dict[str, str | float]]:
    out = []
    for run in cell_runs(folder):
        p, m = run.data.params, run.data.metrics
        out.append({"seed": p.get("seed", "?"), "threads": p.get("threads", "?"),
                    "source": p.get("threads.source", "?"), "pairs_per_s": m["train.pairs_per_s"]})
    return out


def scenario(name: str, root: Path, args: argparse.Namespace, data: Path, env: dict[str, str]) -> list[tuple]:
    cores = machine_cores()
    before = name.endswith("before")
    procs: dict[str, tuple[Path, subprocess.Popen]] = {}
    if name == "alone":
        folder = project(root, name, args, data)
        procs["train"] = (folder, train(folder, env, args.arch, None))
    elif name.startswith("two"):
        for label in ("train A", "train B"):
            folder = project(root, f"{name}-{label[-1]}", args, data)
            procs[label] = (folder, train(folder, env, args.arch, cores if before else None))
    else:
        folder = project(root, f"{name}-sweep", args, data)
        procs["sweep"] = (folder, sweep(folder, env, max(1, cores // 2) if before else None))
        folder = project(root, f"{name}-train", args, data)
        procs["train"] = (folder, train(folder, env, args.arch, cores if before else None))
    wall = finish(procs)
    rows = []
    for label, (folder, _) in procs.items():
        for run in runs_of(folder):
            who = f"{label} (seed {run['seed']})" if label == "sweep" else label
            rows.append((name, who, run["threads"], run["source"], run["pairs_per_s"], wall))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arch", default="offsetnet")
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--only", default=",".join(SCENARIOS), help="comma-separated scenarios to run")
    args = parser.parse_args()
    wanted = [s for s in args.only.split(",") if s]
    unknown = sorted(set(wanted) - set(SCENARIOS))
    if unknown:
        raise SystemExit(f"--only {','.join(unknown)}: unknown (valid: {', '.join(SCENARIOS)})")
    print(f"# {cpu_line()} at the start; {args.arch}, {args.steps} steps x 20 pairs, {args.image_size}²",
          flush=True)
    with tempfile.TemporaryDirectory(prefix="bench-share-") as tmp:
        root = Path(tmp)
        data = root / "data"
        gen = project(root, "generate", args, data)
        ensure_dataset(load_config(gen / "experiments.yaml"), progress=False)
        env = private_env(root)
        print("| scenario | process | threads | threads.source | pairs/s | wall s |")
        print("|---|---|---|---|---|---|")
        for name in wanted:
            rows = scenario(name, root, args, data, env)
            for row in rows:
                print(f"| {row[0]} | {row[1]} | {row[2]} | {row[3]} | {row[4]:.1f} | {row[5]:.0f} |", flush=True)
            if len(rows) > 1:
                print(f"| {name} | **sum** | | | **{sum(r[4] for r in rows):.1f}** | |", flush=True)
        print(f"# load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
