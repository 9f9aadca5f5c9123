"""The cost of learning (issue 45), read back from the MLflow runs that measured it.

Every training run logs ``train.core_s`` (CPU seconds of its training steps, every thread) and
``train.pairs_seen`` at each validation, and ``cost.pairs_to_0.90`` / ``cost.core_s_to_0.90`` once a validation's
``val.ratio.pos_l2`` reached 0.90 (bronchocli/training/cost.py). This script collects those runs from one or more
benchmark projects (folders with their own experiments.yaml and MLflow store) — the reference run
(``train --set train.stop_at_ratio=0.90``), the trials of ``tune --profile learning-cost`` and single lever runs —
and writes benchmarks/results/learning-cost.json: per run its settings that differ from the reference recipe, its
validation curve by pairs seen, the cost to 0.90 and the ratio to the reference's cost, with the CPU it ran on.

    python benchmarks/bench_learning_cost.py PROJECT [PROJECT ...] [--reference cost-reference] [--out FILE] [--markdown]

Runs already in the results file that these projects do not hold (an earlier session's, whose folders are gone)
are kept, each with the machine and date it was collected on; ``--fresh`` drops them.

The CPU line is this machine's: run it on the machine that trained the runs (the JSON says which runs' hosts
were recorded in their tags too). Nothing here trains anything.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

from bench_common import cpu_line

from bronchocli.config import Config, load_config
from bronchocli.runs.client import client_for
from bronchocli.training.cost import COST_TARGET

HERE = Path(__file__).resolve().parent
PAIRS = f"cost.pairs_to_{COST_TARGET:.2f}"
CORE = f"cost.core_s_to_{COST_TARGET:.2f}"
# the settings a lever changes, with the reference recipe's values (a run's params hold only those that differ
# from the config schema's defaults: each is read with that default, ``schema_default``)
LEVERS = {"train.lr": 1e-3, "train.warmup": 0.05, "train.schedule": "cosine", "train.batch_size": 20,
          "model.dropout": 0.2, "train.steps": 5000, "image_size": 96, "train.threads": 1, "data.window": 10,
          "train.precision": "auto", "train.grad_clip": None}
# levers shown in the table's "other" column when a run changed them
OTHER = {"data.window": "window", "train.precision": "precision", "train.threads": "threads",
         "train.grad_clip": "grad clip"}


# experiments whose change is no logged setting (a diagnostic patch in cost_levers.sh): the table's "other" column
PATCHED = {"cost-conv3d-pad0": "fusion unpadded (patched, diagnostic)"}


def _value(text: str | None, default: Any) -> Any:
    if text is None:
        return default
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def schema_default(key: str) -> Any:
    """A setting's value in the config schema's defaults: a run logs only the params that differ from them."""
    section, name = key.split(".")
    value = getattr(getattr(Config(name="defaults"), section), name)
    return value.value if hasattr(value, "value") else value


def image_size(client, run, default: int) -> int:
    """The frame size of the run's dataset: its MLflow dataset input names the folder (``dataset.json``)."""
    for inp in client.get_run(run.info.run_id).inputs.dataset_inputs:
        try:
            uri = json.loads(inp.dataset.source)["uri"]
        except (ValueError, KeyError, TypeError):
            continue
        meta = Path(uri.removeprefix("file://")) / "dataset.json"
        if meta.is_file():
            size = json.loads(meta.read_text()).get("image_size")
            return int(size[0] if isinstance(size, list) else size)
    return default


def run_row(client, run) -> dict[str, Any]:
    """One run: its lever settings, validation curve (pairs seen -> val.ratio.pos_l2 and val.mode_gap), cost and
    status."""
    p, m, tags = run.data.params, run.data.metrics, run.data.tags
    rid = run.info.run_id
    ratio = {int(x.step): x.value for x in client.get_metric_history(rid, "val.ratio.pos_l2")}
    pairs = {int(x.step): x.value for x in client.get_metric_history(rid, "train.pairs_seen")}
    core = {int(x.step): x.value for x in client.get_metric_history(rid, "train.core_s")}
    gap = {int(x.step): x.value for x in client.get_metric_history(rid, "val.mode_gap")}  # eval ÷ batch-stat loss
    curve = [{"step": s, "pairs": pairs.get(s), "core_s": core.get(s), "val_ratio": ratio[s], "mode_gap": gap.get(s)}
             for s in sorted(ratio)]
    settings = {k: _value(p.get(k), schema_default(k)) for k in LEVERS if k != "image_size"}
    settings["image_size"] = _value(p.get("data.image_size"), image_size(client, run, LEVERS["image_size"]))
    first = next((c for c in curve if math.isfinite(c["val_ratio"]) and c["val_ratio"] <= COST_TARGET), None)
    return {
        "run_id": rid, "name": tags.get("mlflow.runName", ""), "arch": p.get("arch"), "seed": _value(p.get("seed"), 0),
        "status": run.info.status, "kind": tags.get("run_kind", "cell"), "pruned": tags.get("pruned") == "true",
        "study": tags.get("study"), "trial": _value(tags.get("trial"), None), "settings": settings,
        "curve": curve, "best_val_ratio": min((c["val_ratio"] for c in curve), default=None),
        "val_best_ratio": m.get("val_best.ratio.pos_l2"),
        "pairs_to_target": m.get(PAIRS, first["pairs"] if first else None),
        "core_s_to_target": m.get(CORE, first["core_s"] if first else None),
        "pairs_per_core_s": (curve[-1]["pairs"] / curve[-1]["core_s"]) if curve and curve[-1]["core_s"] else None,
        "host": tags.get("host") or tags.get("mlflow.source.name"),
    }


def collect(projects: list[Path]) -> list[dict[str, Any]]:
    rows = []
    for folder in projects:
        cfg = load_config(folder / "experiments.yaml")
        client = client_for(cfg)
        for exp in client.search_experiments():
            for run in client.search_runs([exp.experiment_id], max_results=5000):
                if run.data.tags.get("run_kind") in ("sweep", "study"):
                    continue  # parents hold no training
                row = run_row(client, run)
                row["experiment"] = exp.name
                rows.append(row)
    return rows


EARLY_PAIRS = 5000  # the first pairs, where the 3-D-conv head's validation swings
REPLICATE = re.compile(r"-s(\d+)(?=-|$)")  # cost_levers.sh COST_SEED: cost-onecycle-s1-xeon is seed 1 of cost-onecycle-xeon


def replicates(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The levers run on more than one seed (cost_levers.sh COST_SEED), by the seed-0 experiment's name: per seed
    (sorted) the pairs and core-seconds to the target (None: not reached) and × cheaper than its seed's reference."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        if r["kind"] == "cell":
            groups.setdefault(REPLICATE.sub("", r["experiment"]), []).append(r)
    out = {}
    for name, runs in sorted(groups.items()):
        runs = sorted(runs, key=lambda r: r.get("seed", 0))
        if len({r.get("seed", 0) for r in runs}) < 2:
            continue
        out[name] = {"seeds": [r.get("seed", 0) for r in runs], "pairs": [r["pairs_to_target"] for r in runs],
                     "core_s": [r["core_s_to_target"] for r in runs],
                     "best_val_ratio": [r["best_val_ratio"] for r in runs],
                     "cheaper": [r.get("cheaper_than_reference") for r in runs],
                     "cheaper_pairs": [r.get("cheaper_pairs_than_reference") for r in runs]}
    return out


def _gaps(r: dict[str, Any]) -> dict[str, Any]:
    """The run's largest mode gap over its first ``EARLY_PAIRS`` pairs and its last one (None: not logged)."""
    gaps = [(c["pairs"], c["mode_gap"]) for c in r.get("curve", []) if c.get("mode_gap") is not None and c["pairs"]]
    early = [g for p, g in gaps if p <= EARLY_PAIRS]
    return {"mode_gap_max_early": max(early, default=None), "mode_gap_last": gaps[-1][1] if gaps else None}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("projects", nargs="+", type=Path, help="benchmark project folders (experiments.yaml + runs/)")
    ap.add_argument("--reference", nargs="+", default=["cost-reference"],
                    help="name prefixes of the reference runs' experiments (cost-reference, cost-reference-today, "
                         "cost-reference-xeon...): each run is compared with the one of its own date and machine")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "learning-cost.json")
    ap.add_argument("--markdown", action="store_true", help="also print the runs as a Markdown table")
    ap.add_argument("--fresh", action="store_true", help="drop the runs of the results file these projects lack")
    args = ap.parse_args(argv)
    machine, today = cpu_line(), dt.date.today().isoformat()
    rows = collect(args.projects)
    for r in rows:
        r["machine"], r["date"] = machine, today
    commands = ["python benchmarks/bench_learning_cost.py " + " ".join(p.name for p in args.projects)]
    if not args.fresh and args.out.is_file():
        old = json.loads(args.out.read_text())
        have = {r["run_id"] for r in rows}
        kept = [dict(r, machine=r.get("machine", old["machine"]), date=r.get("date", old["date"]))
                for r in old["figures"]["runs"] if r["run_id"] not in have]
        rows += kept
        if kept:
            commands = [c for c in old.get("commands", [old["command"]]) if c not in commands] + commands
    def is_reference(experiment: str) -> bool:
        return experiment.startswith(tuple(args.reference))

    refs = [r for r in rows if is_reference(r["experiment"]) and r["core_s_to_target"]]

    def reference_of(r: dict[str, Any]) -> dict[str, Any] | None:
        """The reference run of ``r``'s seed measured on the same day and machine (the same host state), else any
        seed's of that day and machine, else the first one (two sessions of one day may run on different hosts)."""
        same = [x for x in refs if x.get("date") == r.get("date") and x.get("machine") == r.get("machine")]
        seed = [x for x in same if x.get("seed", 0) == r.get("seed", 0)]  # a replicate against its own seed's
        return (seed or same or refs or [None])[0]

    for r in rows:
        ref = reference_of(r)
        if ref is not None and r["core_s_to_target"] and r["arch"] == ref["arch"]:  # the same model's cost only
            r["cheaper_than_reference"] = ref["core_s_to_target"] / r["core_s_to_target"]
            r["cheaper_pairs_than_reference"] = ref["pairs_to_target"] / r["pairs_to_target"]
            r["reference"] = ref["experiment"]
    # the cheapest BronchoTrack recipe (the cost is BronchoTrack's; other architectures are listed for comparison)
    learned = [r for r in rows if r["pairs_to_target"] and not is_reference(r["experiment"])
               and r["arch"] == "convlstm"]
    best = max(learned, key=lambda r: r.get("cheaper_than_reference") or 0, default=None)
    figures: dict[str, Any] = {"target": COST_TARGET, "runs": rows}
    figures["references"] = {r["experiment"]: {"run": r["run_id"], "date": r.get("date"),
                                               "pairs": r["pairs_to_target"],
                                               "core_s": r["core_s_to_target"],
                                               "pairs_per_core_s": r["pairs_per_core_s"]} for r in refs}
    if best is not None:
        figures["best"] = {"run": best["run_id"], "name": best["name"], "settings": best["settings"],
                           "pairs": best["pairs_to_target"], "core_s": best["core_s_to_target"],
                           "cheaper_pairs": best.get("cheaper_pairs_than_reference"),
                           "cheaper_core_s": best.get("cheaper_than_reference"), "experiment": best["experiment"]}
    # one entry per single-run experiment (a lever run), for the prose's spans
    figures["by_experiment"] = {r["experiment"]: {k: r.get(k) for k in (
        "pairs_to_target", "core_s_to_target", "best_val_ratio", "pairs_per_core_s", "cheaper_than_reference",
        "cheaper_pairs_than_reference", "date", "machine")} | _gaps(r) for r in rows if r["kind"] == "cell"}
    figures["replicates"] = replicates(rows)
    out = {"title": f"Cost of learning: pairs seen and core-seconds of training until val.ratio.pos_l2 <= "
                    f"{COST_TARGET} (bronchocli/training/cost.py)",
           "machine": machine, "date": today, "command": commands[-1], "commands": commands,
           "figures": figures}
    figures["docs_table"] = markdown(out).splitlines()  # benchmarks/README.md's block "learning-cost" (docblocks.py)
    figures["docs_replicates"] = replicates_markdown(figures["replicates"])  # its block of the levers over seeds
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(out, indent=1) + "\n")
    tmp.replace(args.out)
    if args.markdown:
        print(markdown(out))
    print(f"wrote {args.out} ({len(rows)} runs)", file=sys.stderr)
    return 0


def replicates_markdown(reps: dict[str, dict[str, Any]]) -> list[str]:
    """The levers run over seeds, a row per seed: pairs and core-seconds to the target, × cheaper than the
    reference of the same seed, host and day (– where it was not reached)."""
    lines = ["| experiment (seed 0's) | seed | pairs to 0.90 | core-s to 0.90 | × cheaper (core-s) | × cheaper (pairs) "
             "| best val ratio |", "|---|---|---|---|---|---|---|"]
    for name, r in reps.items():
        for i, seed in enumerate(r["seeds"]):
            lines.append(f"| {name} | {seed} | {_fmt(r['pairs'][i], ',.0f')} | {_fmt(r['core_s'][i], '.0f')} "
                         f"| {_fmt(r['cheaper'][i], '.2f')} | {_fmt(r['cheaper_pairs'][i], '.2f')} "
                         f"| {_fmt(r['best_val_ratio'][i], '.3f')} |")
    return lines


def _fmt(v: Any, spec: str = ".3g") -> str:
    return "–" if v is None else format(v, spec) if isinstance(v, float) else str(v)


def markdown(out: dict[str, Any]) -> str:
    lines = ["| run | arch | image | lr | warm-up | schedule | batch | dropout | budget (pairs) | best val ratio "
             "| other | pairs to 0.90 | core-s to 0.90 | × cheaper (core-s) | status | date |", "|" + "---|" * 16]
    for r in sorted(out["figures"]["runs"], key=lambda r: (r["core_s_to_target"] is None, r["core_s_to_target"] or 0)):
        s = r["settings"]
        budget = s["train.steps"] * s["train.batch_size"]
        status = "pruned" if r["pruned"] else r["status"].lower()
        lines.append(f"| {r['experiment']} {r['name'].split('·')[0]} | {r['arch']} "
                     f"| {s['image_size']}² | {_fmt(s['train.lr'])} | {_fmt(s['train.warmup'])} "
                     f"| {s['train.schedule']} | {s['train.batch_size']} | {_fmt(s['model.dropout'])} | {budget:,} "
                     f"| {_fmt(r['best_val_ratio'])} | {_other(s, r['experiment'])} | {_fmt(r['pairs_to_target'], ',.0f')} "
                     f"| {_fmt(r['core_s_to_target'], '.0f')} | {_fmt(r.get('cheaper_than_reference'), '.2f')} "
                     f"| {status} | {r.get('date', out['date'])} |")
    return "\n".join(lines)


def _other(settings: dict[str, Any], experiment: str = "") -> str:
    """The levers a run changed beyond the table's own columns (``window 5``, ``precision bf16-mixed``)."""
    changed = [f"{name} {settings[k]}" for k, name in OTHER.items() if k in settings and settings[k] != LEVERS[k]]
    return ", ".join(changed + ([PATCHED[experiment]] if experiment in PATCHED else [])) or "–"


if __name__ == "__main__":
    sys.exit(main())
