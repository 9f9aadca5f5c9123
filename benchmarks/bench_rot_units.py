"""What DE and CE weigh in the loss without ``train.rot_scale``: their value at an error of one training-label std.

    python benchmarks/bench_rot_units.py PROJECT [--profile NAME]   # -> benchmarks/results/rot-loss-units.json

PROJECT is a folder with experiments.yaml and its dataset (generated). The position term and the MSE rotation
term of the standardised loss are 1 at an error of one label std in every component; this prints DE's and CE's
value there (``metrics.rot_loss_unit`` at the training split's label std of BronchoTrack's personalized cell), the
factor ``train.rot_scale: label_std`` divides them by. Nothing is trained.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from bench_common import cpu_line
from docblocks import record

from bronchocli import metrics
from bronchocli.cells import Cell
from bronchocli.config import load_config
from bronchocli.training.prepare import prepare


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("project", type=Path)
    ap.add_argument("--profile", default=None)
    args = ap.parse_args()
    cfg = load_config(args.project / "experiments.yaml", args.profile)
    cell = Cell(arch="convlstm", rot_loss="ce", population="personalized", seed=0,
                pose_frame=cfg.grid.pose_frame[0])
    std = torch.tensor(prepare(cfg, cell, progress=False).label_std, dtype=torch.float64)
    figures = {"label_std": [round(float(x), 4) for x in std],
               "ce_at_one_std": float(metrics.rot_loss_unit(metrics.cosine_error, std)),
               "de_at_one_std": float(metrics.rot_loss_unit(metrics.direction_error, std))}
    figures["ce_weight_vs_mse"] = 1.0 / figures["ce_at_one_std"]
    figures["de_weight_vs_mse"] = 1.0 / figures["de_at_one_std"]
    path = record("rot-loss-units", title="DE and CE at an error of one training-label std (the default dataset)",
                  machine=cpu_line(), command=f"python benchmarks/bench_rot_units.py {args.project}"
                  + (f" --profile {args.profile}" if args.profile else ""), figures=figures)
    print(f"CE {figures['ce_at_one_std']:.4f}, DE {figures['de_at_one_std']:.4f} at one std; wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
