"""Anatomy loading and lumen-surface extraction times, stage by stage.

    python benchmarks/bench_surface.py [--voxel 0.5] [--seeds 0 1 2] [--repeat 3]

For the real CT-derived tree (tests/fixtures/airways: the Chaste project's, BSD-3) and a few procedural
patients: time to load the anatomy (tree + lobe paths), then each stage of
``lumen_surface`` - the round-cone signed distance, Flying Edges, largest piece,
windowed-sinc smoothing, decimation to the triangle budget, cleaning/normals -
and the resulting mesh (grid, voxels, triangles, closed?, pieces). Also times
100k ``centreline_distance`` queries. Best of ``--repeat`` runs per figure.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bronchocli.anatomy import centreline_distance, load_anatomy
from bronchocli.anatomy import surface as S
from bronchocli.anatomy.sdf import lumen_sdf_grid

REAL = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "airways" / "TestSubject002MajorAirways.vtu"


def best_of(repeat: int, fn):
    """(best seconds, last result) of ``repeat`` calls."""
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def stages(tree, voxel: float, repeat: int) -> dict:
    h = S.surface_grid_mm(tree, voxel)
    row = {"grid_mm": h}
    row["sdf_s"], (sdf, origin) = best_of(repeat, lambda: lumen_sdf_grid(tree, h))
    row["voxels_M"] = sdf.size / 1e6
    row["flying_edges_s"], poly = best_of(repeat, lambda: S.iso_surface(sdf, origin, np.full(3, h), 0.0))
    row["fe_triangles"] = poly.GetNumberOfPolys()
    row["largest_s"], poly = best_of(repeat, lambda: S.largest_piece(poly))
    row["smooth_s"], poly = best_of(repeat, lambda: S._smooth(poly))
    n = poly.GetNumberOfPolys()
    reduction = min(S.MAX_REDUCTION, max(0.0, 1 - S.MAX_TRIANGLES / n))
    row["decimate_s"], poly = best_of(repeat, lambda: S._decimated_closed(poly, reduction))
    row["clean_normals_s"], poly = best_of(repeat, lambda: S.clean_surface(poly))
    row["total_s"], final = best_of(repeat, lambda: S.lumen_surface(tree, voxel))
    report = S.mesh_report(final)
    row["triangles"] = report["triangles"]
    row["closed"] = report["boundary_edges"] == 0 and report["non_manifold_edges"] == 0
    row["pieces"] = report["pieces"]
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxel", type=float, default=0.5)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    sources = ([("real tree", str(REAL), 0)] if REAL.is_file() else []) + [
        (f"procedural seed {s}", "procedural", s) for s in args.seeds]
    rows = []
    for name, src, seed in sources:
        load_s, tree = best_of(args.repeat, lambda src=src, seed=seed: load_anatomy(src, seed=seed, voxel_mm=args.voxel))
        row = {"anatomy": name, "branches": len(tree.branches), "load_s": load_s, **stages(tree, args.voxel, args.repeat)}
        pts = np.random.default_rng(0).normal(size=(100_000, 3)) * 30 + tree.branches[0].points[-1]
        centreline_distance(tree, pts[:10])  # build the index outside the timing
        row["distance_100k_s"], _ = best_of(args.repeat, lambda tree=tree, pts=pts: centreline_distance(tree, pts))
        rows.append(row)
    keys = list(rows[0])
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join(f"{v:.2f}" if isinstance(v, float) else str(v) for v in r.values()) + " |")


if __name__ == "__main__":
    main()
