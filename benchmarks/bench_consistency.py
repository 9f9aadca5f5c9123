"""Evaluation consistent with training (issue 35): one cell trained through the platform's own path
(prepare -> network -> Trainer -> test evaluation, no MLflow), with config overrides, and what it measured:
the test ratio to the training-mean reference (pair position L2) and the mode gap (eval-mode loss ÷
batch-statistics loss on the same training batches) at every validation and for the tested weights.

    python benchmarks/bench_consistency.py --arch baseline --set train.bn_freeze=0.25 --out results.jsonl

One JSON line per run is appended to ``--out`` (and printed): the numbers of benchmarks/README.md,
"Evaluation consistent with training".
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from bronchocli import cells
from bronchocli.config import load_config
from bronchocli.speed import cpu_info, cpu_key
from bronchocli.training.engine import fit_and_evaluate
from bronchocli.training.prepare import prepare


def cpu_model() -> str:
    return next((line.split(":", 1)[1].strip() for line in cpu_info().splitlines() if line.startswith("model name")),
                "unknown CPU")


def run(arch: str, rot_loss: str, seed: int, overrides: list[str], config: str, profile: str | None) -> dict:
    cfg = load_config(config, profile, overrides)
    cell = cells.make(arch=arch, rot_loss=rot_loss, population="personalized", seed=seed,
                      pose_frame="camera")
    data = prepare(cfg, cell, progress=False)
    t0 = time.perf_counter()
    out = fit_and_evaluate(cfg, cell, data)
    m = out.metrics
    return {
        "arch": arch, "rot_loss": rot_loss, "seed": seed, "set": overrides, "profile": profile,
        "steps": m["train.steps"], "pairs_seen": m["train.pairs_seen"],
        "ratio_train_mean_pair_pos_l2": m["pair.pos_l2.mean"] / m["train_mean.pair.pos_l2.mean"],
        "ratio_train_mean_pair_rot_l2": m["pair.rot_l2.mean"] / m["train_mean.pair.rot_l2.mean"],
        "eval_mode_gap": m.get("eval.mode_gap"), "best_step": m["train.best_step"],
        "history": [{k: h[k] for k in ("step", "train_loss", "val_loss", "val.mode_gap", "val.mode_gap.eval_loss",
                                       "val.mode_gap.batch_loss") if k in h} for h in out.fit.history],
        "pred_std_ratio_pos": m.get("pred.std_ratio.pos"), "train_pairs_per_s": m["train.pairs_per_s"],
        "wall_s": time.perf_counter() - t0, "threads": torch.get_num_threads(),
        "cpu": f"{cpu_model()} ({cpu_key()})",
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", default="baseline")
    ap.add_argument("--rot-loss", default="ce")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], dest="overrides", metavar="KEY=VALUE")
    ap.add_argument("--config", default="experiments.yaml")
    ap.add_argument("--profile", default=None)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    row = run(a.arch, a.rot_loss, a.seed, a.overrides, a.config, a.profile)
    line = json.dumps(row)
    print(line, flush=True)
    if a.out is not None:
        with a.out.open("a") as f:
            f.write(line + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
