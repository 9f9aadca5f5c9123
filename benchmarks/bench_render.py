"""Rendering throughput of the dataset generator, and the time to generate the default dataset.

    python benchmarks/bench_render.py [--sizes 64 128 256] [--workers 1 2] [--anatomy procedural] [--no-default]

Builds procedural patient 0 (or ``--anatomy FILE``) at 0.5 mm, plans one
trajectory along every lobe path (0.5-1 mm per frame, the paper's fine
sampling; about 1,300 frames), then measures at each frame size:

* ``render``: camera move + render + pixel read-back, one process;
* ``end to end``: the generator's own worker code (``run_task``: render, PNG
  encode at level 1, atomic write, SHA-256) in 1 and 2 spawned processes,
  frames per second of wall time after every worker has built its renderer.

Finally it times ``generate_dataset`` on the default ``experiments.yaml``
(anatomy, surfaces, planning, rendering, CSVs; with its configured workers)
into a temporary folder. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bronchocli.config import Generate, Realism, load_config  # noqa: E402
from bronchocli.generation.writer import DatasetFrames  # noqa: E402
from bronchocli.render.tasks import RenderTask, init_worker, run_task  # noqa: E402


def build(anatomy: str, work: Path) -> tuple[Path, list]:
    """The prepared lumen surface (.vtp) and one planned trajectory per lobe."""
    from bronchocli.anatomy import centreline_distance, load_anatomy, lumen_surface
    from bronchocli.generation.trajectories import PathSampler, plan_lobe
    from bronchocli.io import write_polydata
    from bronchocli.render.appearance import prepare_surface

    tree = load_anatomy(anatomy, seed=0, voxel_mm=0.5)
    surface = prepare_surface(lumen_surface(tree, voxel_mm=0.5), texture=True, seed=0)
    path = work / "lumen.vtp"
    write_polydata(surface, path)
    gen = Generate(trajectories=1, step_mm=(0.5, 1.0), max_frames=None)
    plans = []
    for lobe in gen.lobes:
        lp = tree.lobe_paths[lobe]
        plans += plan_lobe(PathSampler(lp.points, lp.radii), gen, tree.spacing_mm,
                           lambda q: centreline_distance(tree, q), patient="bench", patient_index=0, lobe=lobe)
    print(f"surface: {surface.GetNumberOfPolys():,} triangles; frames per pass: {sum(len(p) for p in plans):,}")
    return path, plans


def render_only(surface: Path, plans: list, size: int) -> float:
    from bronchocli.io import read_polydata
    from bronchocli.render.scene import FrameRenderer

    with FrameRenderer(read_polydata(surface), width=size, realism=Realism()) as r:
        r.render(plans[0].position_mm[0], plans[0].rotation[0], plans[0].radius_mm[0])  # warm-up (shaders)
        n, start = 0, time.perf_counter()
        for p in plans:
            for i in range(len(p)):
                r.render(p.position_mm[i], p.rotation[i], p.radius_mm[i])
                n += 1
    return n / (time.perf_counter() - start)


def _tasks(surface: Path, plans: list, size: int, out: Path) -> list[RenderTask]:
    return [RenderTask("bench", p.lobe, p.index, DatasetFrames(str(out)), str(surface),
                       [f"s{size}/{p.lobe}/f{f:05d}.png" for f in range(len(p))],
                       p.position_mm, p.rotation, p.radius_mm, size, 70.0, Realism()) for p in plans]


def _worker_pass(tasks: list[RenderTask], start_at: float) -> tuple[float, float, int]:
    """Build the renderer, wait for the common start time, then run the tasks; returns (start, end, frames)."""
    from bronchocli.render.tasks import _renderer  # noqa: PLC0415

    _renderer(tasks[0])
    while time.time() < start_at:
        time.sleep(0.01)
    t0 = time.time()
    frames = sum(run_task(t)[1] for t in tasks)
    return t0, time.time(), frames


def end_to_end(surface: Path, plans: list, size: int, workers: int, out: Path) -> float:
    tasks = _tasks(surface, plans, size, out / f"w{workers}")
    for t in tasks:
        (Path(t.sink.root) / t.filenames[0]).parent.mkdir(parents=True, exist_ok=True)
    frames = [f for t in tasks for f in range(len(t.filenames))]
    shares = [[] for _ in range(workers)]
    for t in tasks:  # split every trajectory into contiguous halves so the workers get equal frame counts
        for w, idx in enumerate(np.array_split(np.arange(len(t.filenames)), workers)):
            shares[w].append(RenderTask(t.patient, t.lobe, t.trajectory, t.sink, t.surface,
                                        [t.filenames[i] for i in idx], t.position_mm[idx], t.rotation[idx],
                                        t.radius_mm[idx], t.width, t.fov_deg, t.realism))
    threads = max(1, (os.cpu_count() or 1) // workers)
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=init_worker,
                             initargs=(threads,)) as pool:
        start_at = time.time() + 8.0  # time for every worker to start and build its renderer
        results = list(pool.map(_worker_pass, shares, [start_at] * workers))
    span = max(r[1] for r in results) - min(r[0] for r in results)
    assert sum(r[2] for r in results) == len(frames)
    return len(frames) / span


def default_dataset(out: Path) -> tuple[float, dict]:
    import json

    from bronchocli.generation.pipeline import generate_dataset

    cfg = load_config(REPO / "experiments.yaml")
    start = time.perf_counter()
    root = generate_dataset(cfg, root=out / "default", progress=False)
    seconds = time.perf_counter() - start
    return seconds, json.loads((root / "dataset.json").read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--anatomy", default="procedural")
    ap.add_argument("--no-default", action="store_true", help="skip timing the default dataset")
    args = ap.parse_args()
    print(f"cpus: {os.cpu_count()}, load average: {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        surface, plans = build(args.anatomy, work)
        head = "| size | render fps (1 process) | " + " | ".join(f"end to end fps ({w} proc.)" for w in args.workers) + " |"
        rows = [head, "|" + "---|" * (2 + len(args.workers))]
        for size in args.sizes:
            cells = [f"{render_only(surface, plans, size):.0f}"]
            cells += [f"{end_to_end(surface, plans, size, w, work):.0f}" for w in args.workers]
            rows.append(f"| {size}x{size} | " + " | ".join(cells) + " |")
            print(rows[-1], flush=True)
        print("\n".join(rows))
        if not args.no_default:
            seconds, meta = default_dataset(work)
            c = meta["counts"]
            print(f"\ndefault dataset (experiments.yaml): {c['frames']:,} frames, {c['trajectories']} trajectories, "
                  f"{len(meta['patients'])} patients, {meta['image_size'][0]} px, "
                  f"workers {meta['generator']['workers']}: {seconds:.1f} s")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
