"""What pretraining buys (issue 56), read back from the MLflow runs of benchmarks/pretraining.sh.

Every run trains BronchoTrack (ConvLSTM + MSE+CE) on the main job's data and recipe for its whole budget, validates
every 1,000 pairs and logs ``val.ratio.pos_l2`` (validation position error ÷ the training mean's) with
``train.pairs_seen`` and ``train.core_s`` (CPU seconds of the training steps, every thread) at each validation.
This script reads those curves and the runs' test metrics and writes benchmarks/results/pretraining.json:

* per run: its arm or lever, seed, the settings it changed, its validation curve, the pairs and core-seconds until
  the ratio first reached 0.90 and 0.85 (resolution: one validation, 1,000 pairs), and its test ratios (÷ the
  training mean's error on the same test units: per pair and accumulated over whole trajectories, position and
  rotation);
* per arm/lever: those over its seeds, and its cost to 0.90 against B0-random's (``speedup``: B0-random's mean
  core-seconds to 0.90 over this arm's; seeds that never reached 0.90 are counted at their whole budget, so a
  speed-up is a lower bound when a reference seed did not and an upper bound when one of the arm's did not:
  ``speedup_bound``); frozen stages shared between runs cost once, ``features_core_s``, outside the runs' own;
* ``table``: the Markdown table benchmarks/README.md shows (a ``numbers: lines`` block).

    python benchmarks/bench_pretraining.py PROJECT [--out FILE] [--command TEXT]

Run it on the machine that trained the runs (its CPU line is this machine's). Nothing here trains anything.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import re
import statistics
import sys
from pathlib import Path
from typing import Any

from bench_common import cpu_line

from bronchocli import runkeys
from bronchocli.config import load_config
from bronchocli.runs.client import client_for

HERE = Path(__file__).resolve().parent
TARGETS = (0.90, 0.85)
NAME = re.compile(r"^pt-(?P<arm>.+)-s(?P<seed>\d+)$")
ARMS = {  # arm or lever -> how the table names it (in the table's order)
    "b0-random": "EfficientNet-B0, random (the recipe before)",
    "lite0-random": "EfficientNet-Lite0, random",
    "lite0-imagenet": "EfficientNet-Lite0, ImageNet",
    "lite0-imagenet-frozen9": "Lite0 ImageNet, whole backbone frozen",
    "lite0-imagenet-frozen9-lr3e-3": "Lite0 ImageNet, whole backbone frozen, lr 3e-3",
    "lite0-imagenet-frozen7": "Lite0 ImageNet, stem + 6 stages frozen",
    "lite0-imagenet-frozen6": "Lite0 ImageNet, stem + 5 stages frozen",
    "lite0-imagenet-frozen4": "Lite0 ImageNet, stem + 3 stages frozen",
    "lite0-imagenet-blr0.1": "Lite0 ImageNet, backbone at lr/10",
    "lite0-imagenet-64": "Lite0 ImageNet, 64² frames",
    "lite0-imagenet-128": "Lite0 ImageNet, 128² frames",
}
TEST = {"pair_pos": "ratio.train_mean.pair.pos_l2", "acc_pos": "ratio.train_mean.acc.pos_l2",
        "pair_rot": "ratio.train_mean.pair.rot_l2", "acc_rot": "ratio.train_mean.acc.rot_l2"}


def _history(client, run_id: str, key: str) -> dict[int, float]:
    return {m.step: m.value for m in client.get_metric_history(run_id, key) if m.step > 0}


def _first(curve: list[list[float]], target: float) -> tuple[float, float] | None:
    """(pairs, core-seconds) at the first validation whose ratio is <= target."""
    return next(((pairs, core) for pairs, core, ratio in curve if ratio <= target), None)


def read_run(client, run) -> dict[str, Any]:
    ratio = _history(client, run.info.run_id, runkeys.VAL_RATIO)
    pairs = _history(client, run.info.run_id, runkeys.train("pairs_seen"))
    core = _history(client, run.info.run_id, runkeys.train("core_s"))
    curve = [[pairs[s], round(core[s], 1), round(ratio[s], 4)] for s in sorted(ratio) if s in pairs and s in core]
    out: dict[str, Any] = {"run_id": run.info.run_id, "curve": curve, "budget_pairs": curve[-1][0] if curve else None,
                           "core_s": curve[-1][1] if curve else None,
                           "settings": {k: v for k, v in run.data.params.items()
                                        if k in ("model.backbone", "model.pretrained", "model.frozen_stages",
                                                 "train.backbone_lr", "image_size")},
                           "init": run.data.tags.get("init")}
    for target in TARGETS:
        hit = _first(curve, target)
        out[f"pairs_to_{target:.2f}"], out[f"core_s_to_{target:.2f}"] = hit if hit else (None, None)
    out["test"] = {k: round(run.data.metrics[m], 4) for k, m in TEST.items() if m in run.data.metrics}
    # the one-off computation of shared frozen stages (training/frozen_features.py): in the run that computed it
    out["features_core_s"] = run.data.metrics.get(runkeys.train("frozen_features_core_s"))
    return out


def _mean(values: list[float]) -> float | None:
    return round(statistics.fmean(values), 1) if values else None


def summarise(runs: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    arms: dict[str, dict[str, Any]] = {}
    for name, run in sorted(runs.items()):
        arms.setdefault(run["arm"], {"runs": []})["runs"].append(name)
    for arm, a in arms.items():
        rs = [runs[n] for n in a["runs"]]
        a["seeds"] = [r["seed"] for r in rs]
        for target in TARGETS:
            t = f"{target:.2f}"
            reached = [r for r in rs if r[f"pairs_to_{t}"] is not None]
            a[f"reached_{t}"] = f"{len(reached)}/{len(rs)}"
            a[f"pairs_to_{t}"] = [r[f"pairs_to_{t}"] for r in rs]
            a[f"core_s_to_{t}"] = [r[f"core_s_to_{t}"] for r in rs]
            # a seed that never reached the target counts at its whole budget (a lower bound on the cost)
            a[f"core_s_to_{t}_mean"] = _mean([r[f"core_s_to_{t}"] if r[f"core_s_to_{t}"] is not None
                                              else r["core_s"] for r in rs if r["core_s"] is not None])
        for k in TEST:
            vals = [r["test"][k] for r in rs if k in r["test"]]
            a[k] = [min(vals), max(vals)] if vals else None
        per = [r["core_s"] / r["budget_pairs"] * 1000 for r in rs if r["core_s"] and r["budget_pairs"]]
        a["core_s_mean_per_kpair"] = round(statistics.fmean(per), 2) if per else None
        once = [r["features_core_s"] for r in rs if r.get("features_core_s")]
        a["features_core_s"] = round(max(once), 1) if once else None
    ref = arms.get("b0-random", {})
    base = ref.get("core_s_to_0.90_mean")
    for a in arms.values():
        own = a.get("core_s_to_0.90_mean")
        a["speedup_0.90"] = round(base / own, 2) if base and own else None
        # a seed that never reached 0.90 is counted at its whole budget: its arm's cost is then a lower bound, so
        # the speed-up is a lower bound when the reference has one, an upper bound when the arm has one
        a["speedup_bound"] = ("≥ " if not _all(ref) and _all(a) else "≤ " if _all(ref) and not _all(a) else
                              "~ " if not _all(ref) and not _all(a) else "")
    return arms


def _all(arm: dict[str, Any]) -> bool:
    done, total = arm.get("reached_0.90", "0/1").split("/")
    return done == total


def _range(v: list[float] | None, fmt: str = ".3f") -> str:
    if not v:
        return "—"
    lo, hi = (format(x, fmt) for x in v)
    return lo if lo == hi else f"{lo}–{hi}"


def _costs(pairs: list[float | None], core: list[float | None]) -> str:
    return " / ".join("never" if p is None else f"{p / 1000:g}k ({c:.0f} s)" for p, c in zip(pairs, core))


def table(arms: dict[str, dict[str, Any]]) -> list[str]:
    head = ["| arm (BronchoTrack: ConvLSTM + MSE+CE, 96², 10,000 pairs) | seeds | pairs (core-s) to 0.90, per seed | "
            "to 0.85, per seed | core-s to 0.90, mean | vs B0 random | shared features, once (core-s) | test per "
            "pair, position | accumulated, position | per pair, rotation | accumulated, rotation |",
            "|" + "---|" * 11]
    rows = []
    for arm, label in ARMS.items():
        if arm not in arms:
            continue
        a = arms[arm]
        speed = "reference" if arm == "b0-random" else \
            f"{a['speedup_bound']}{a['speedup_0.90']:.1f}×" if a.get("speedup_0.90") else "—"
        once = f"{a['features_core_s']:.0f}" if a.get("features_core_s") else "—"
        rows.append(f"| {label} | {', '.join(map(str, a['seeds']))} | {_costs(a['pairs_to_0.90'], a['core_s_to_0.90'])}"
                    f" | {_costs(a['pairs_to_0.85'], a['core_s_to_0.85'])} | {a['core_s_to_0.90_mean']:.0f} | "
                    f"{speed} | {once} | {_range(a['pair_pos'])} | {_range(a['acc_pos'])} | {_range(a['pair_rot'])} | "
                    f"{_range(a['acc_rot'])} |")
    return head + rows


def collect(project: Path) -> dict[str, dict[str, Any]]:
    cfg = load_config(project / "experiments.yaml")
    client = client_for(cfg)
    runs: dict[str, dict[str, Any]] = {}
    for exp in client.search_experiments():
        m = NAME.match(exp.name)
        if not m:
            continue
        finished = [r for r in client.search_runs([exp.experiment_id]) if r.info.status == "FINISHED"]
        if not finished:
            continue
        run = read_run(client, finished[0])
        run.update(arm=m["arm"], seed=int(m["seed"]))
        runs[exp.name] = run
    return runs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("project", type=Path)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "pretraining.json")
    ap.add_argument("--command", help="how the runs were made, when not the plain script (recorded as the command)")
    args = ap.parse_args(argv)
    runs = collect(args.project.resolve())
    if not runs:
        print(f"no FINISHED pt-* runs in {args.project}", file=sys.stderr)
        return 1
    arms = summarise(runs)
    result = {
        "title": "What pretraining buys: BronchoTrack's cost to val.ratio.pos_l2 <= 0.90 / 0.85 and its test ratios, "
                 "per backbone, initialisation and lever (benchmarks/pretraining.sh)",
        "machine": cpu_line(), "date": dt.date.today().isoformat(),
        "command": args.command or (f"benchmarks/pretraining.sh {args.project} && "
                                    f"python benchmarks/bench_pretraining.py {args.project}"),
        "figures": {"arms": arms, "runs": runs, "table": table(arms)},
    }
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1, default=lambda x: None if isinstance(x, float) and math.isnan(x)
                              else x) + "\n")
    tmp.replace(args.out)
    print("\n".join(result["figures"]["table"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
