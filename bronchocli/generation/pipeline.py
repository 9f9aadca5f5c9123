"""Synthetic dataset generation: anatomy -> trajectories -> rendered frames and poses on disk.

``generate_dataset(cfg)`` builds the dataset of ``cfg.dataset.generate`` in
``cfg.dataset.root`` (layout: docs/dataset-format.md; pipeline and trajectory
rules: docs/generator.md):

1. per patient (in parallel): load the anatomy, write its centreline graph
   (``<patient>/airway.vtp``) and its render-ready lumen surface (cached in
   ``<root>/.work/``), and plan its trajectories (:mod:`.trajectories`);
2. render every trajectory's missing frames (one task per trajectory, in
   ``--workers`` processes, each with its own VTK context);
3. write each patient's CSV once all its frames exist, then ``dataset.json``
   last, and remove the work folder.

It is resumable: ``<root>/.work/manifest.json`` records the generator config,
frames already on disk are kept, and plans are deterministic, so a re-run
continues where an interrupted one stopped and produces the same bytes. A
root holding output of a different config is an error, never mixed.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from .. import __version__, interrupts, io, pathcheck
from ..anatomy import centreline_distance, load_anatomy, lumen_surface, save_centreline
from ..config import Config, Generate
from ..data.naming import DATASET_JSON
from ..errors import DataError, WriteFailed
from ..io import file_lock, remove_stale_temps, write_bytes, write_json, write_polydata
from ..render.appearance import prepare_surface
from ..render.camera import intrinsics
from ..render.tasks import Callback, RenderProgress, RenderTask, close_renderer, init_worker, run_task
from . import writer
from .sources import PatientSource, patient_sources
from .trajectories import PathSampler, PlannedTrajectory, plan_lobe

# bump when the same config would render different frames or poses. 2: host-independent arithmetic (hostfree):
# version 1's poses depended on the CPU's BLAS/SIMD/libm kernels (docs/reproduction.md, "One seed, one dataset")
GENERATOR_VERSION = 2
WORK_DIR = ".work"
MANIFEST = "manifest.json"
LOCK = ".generate.lock"  # held while generating: concurrent generators of one root take turns
OURS = (WORK_DIR, LOCK)
IGNORED_KEYS = ("workers",)  # generator settings that do not change the dataset


@dataclass
class PatientPlan:
    source: PatientSource
    origin_mm: list[float]
    spacing_mm: list[float]
    trajectories: list[PlannedTrajectory]  # lobe order of generate.lobes, then trajectory index
    lobe_paths: dict[str, dict]  # lobe -> {"length_mm", "generation"}
    csv_text: str


# -- config and sources -----------------------------------------------------------------


def _signature(record: dict | None) -> dict:
    """What must match for two generator configs to make the same dataset.

    Anatomy files compare by name, so moving a project (absolute paths change)
    does not orphan its datasets; the worker count never matters.
    """
    sig = {k: v for k, v in (record or {}).items() if k not in IGNORED_KEYS}
    for key in ("anatomy", "centreline"):
        if sig.get(key) not in (None, "procedural"):
            sig[key] = Path(sig[key]).name
    return sig


def _differences(a: dict, b: dict) -> list[str]:
    keys = sorted(set(a) | set(b))
    return [k for k in keys if a.get(k) != b.get(k)]


# -- root state -----------------------------------------------------------------------------


def _mismatch(stored: dict, want: dict) -> list[str] | None:
    """None when ``stored`` (dataset.json or the work manifest) was made with this config and generator,
    else the generate keys that differ."""
    have = _signature(stored.get("generator"))
    if have == want and stored.get("generator_version") == GENERATOR_VERSION:
        return None
    return _differences(have, want) or ["generator_version"]


def _check_root(root: Path, record: dict) -> str:
    """'complete', 'resume' or 'fresh'; DataError if ``root`` holds something generated otherwise."""
    meta_path = root / DATASET_JSON
    want = _signature(record)
    if meta_path.is_file():
        diff = _mismatch(json.loads(meta_path.read_text()), want)
        if diff is None:
            return "complete"
        raise DataError(f"{root}: holds a complete dataset generated with a different config "
                        f"(differs in generate.{', generate.'.join(diff)}); choose another --out/dataset.root or delete it")
    if not root.exists():
        return "fresh"
    manifest = root / WORK_DIR / MANIFEST
    what = "files that are not a bronchopose dataset"
    if manifest.is_file():
        diff = _mismatch(json.loads(manifest.read_text()), want)
        if diff is None:
            return "resume"
        what = f"a partial dataset of a different config (differs in generate.{', generate.'.join(diff)})"
    if any(p.name not in OURS for p in root.iterdir()):
        raise DataError(f"{root}: holds {what}; choose another --out/dataset.root or delete it")
    return "fresh"  # empty, or only an unstarted work folder of another config: take it over


# -- per-patient preparation (runs in workers) --------------------------------------------------


def plan_patient(source: PatientSource, gen: Generate):
    """(airway tree, planned trajectories) of one patient: the poses, from the config alone (no rendering)."""
    tree = load_anatomy(source.anatomy, seed=source.seed, voxel_mm=gen.voxel_mm, centreline=source.centreline,
                        lobe_generation=gen.lobe_generation)
    missing = [lb for lb in gen.lobes if lb not in tree.lobe_paths]
    if missing:
        raise DataError(f"{source.anatomy}: no lobe path for {', '.join(missing)} "
                        f"(found: {', '.join(tree.lobe_paths) or 'none'})")
    distance = lambda pts: centreline_distance(tree, pts)  # noqa: E731
    plans: list[PlannedTrajectory] = []
    for lobe in gen.lobes:
        lp = tree.lobe_paths[lobe]
        path = PathSampler(np.asarray(lp.points, dtype=np.float64), np.asarray(lp.radii, dtype=np.float64))
        plans += plan_lobe(path, gen, tree.spacing_mm, distance, patient=source.patient,
                           patient_index=source.index, lobe=lobe)
    return tree, plans


def planned_pose_fingerprint(cfg: Config) -> str:
    """The ``pose_fingerprint`` that generating ``cfg``'s dataset records, computed without rendering a frame."""
    gen = cfg.dataset.generate
    csvs = []
    for source in patient_sources(gen, cfg.paths.anatomy, cfg.paths.centreline):
        tree, plans = plan_patient(source, gen)
        csvs.append(writer.patient_csv(plans, tree.to_voxels).encode("utf-8"))
    return writer.pose_fingerprint(csvs)


def prepare_patient(source: PatientSource, gen: Generate, root: str) -> PatientPlan:
    """Load one anatomy, write its centreline graph and render-ready surface, plan its trajectories."""
    tree, plans = plan_patient(source, gen)
    patient_dir = Path(root) / source.patient
    patient_dir.mkdir(parents=True, exist_ok=True)
    if not (patient_dir / "airway.vtp").exists():
        save_centreline(tree, patient_dir / "airway.vtp")
    surface_path = _surface_path(root, source.patient)
    if not surface_path.exists():
        _write_surface(tree, gen, source, surface_path)
    info = {lb: {"length_mm": round(float(tree.lobe_paths[lb].arc_length[-1]), 3),
                 "generation": int(tree.lobe_paths[lb].generation)} for lb in gen.lobes}
    return PatientPlan(source, [float(v) for v in tree.origin_mm], [float(v) for v in tree.spacing_mm], plans, info,
                       writer.patient_csv(plans, tree.to_voxels))


def _surface_path(root: str | Path, patient: str) -> Path:
    return Path(root) / WORK_DIR / f"{patient}-lumen.vtp"


def _write_surface(tree, gen: Generate, source: PatientSource, path: Path) -> None:
    surface = prepare_surface(lumen_surface(tree, voxel_mm=gen.voxel_mm), texture=gen.realism.texture,
                              seed=abs(gen.seed) * 1000 + source.index)
    write_polydata(surface, path)


# -- execution: in-process or a pool of spawned workers -------------------------------------


class _Runner:
    """Runs tasks in this process (workers=1) or in spawned processes, each with its own VTK context."""

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self.pool = None
        if workers > 1:
            threads = max(1, (os.cpu_count() or 1) // workers)
            self.pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn"),
                                            initializer=init_worker, initargs=(threads, os.getpid()))

    def map(self, fn, *iterables) -> list:
        if self.pool is None:
            return [fn(*args) for args in zip(*iterables)]
        with interrupts.ignored_in_children():
            results = self.pool.map(fn, *iterables)  # submits (and spawns workers) now, results come later
        return list(results)

    def submit(self, fn, *args):
        with interrupts.ignored_in_children():
            return self.pool.submit(fn, *args)

    def close(self, abort: bool = False) -> None:
        """Stop the pool; with ``abort`` (Ctrl-C, an error) without waiting for the trajectories being rendered:
        their finished frames are on disk (written atomically) and a re-run renders the rest."""
        if self.pool is not None:
            if abort:
                for proc in list((self.pool._processes or {}).values()):  # noqa: SLF001 - no public way to stop them
                    proc.terminate()
            self.pool.shutdown(wait=True, cancel_futures=True)
        close_renderer()


def _tasks(plans: list[PatientPlan], root: Path, gen: Generate) -> list[RenderTask]:
    tasks = []
    sink = writer.DatasetFrames(str(root))
    for pp in plans:
        surface = str(_surface_path(root, pp.source.patient))
        for t in pp.trajectories:
            names = [writer.frame_filename(t.patient, t.lobe, t.index, f) for f in range(len(t))]
            tasks.append(RenderTask(t.patient, t.lobe, t.index, sink, surface, names, t.position_mm,
                                    t.rotation, t.radius_mm, gen.image_size, gen.fov_deg, gen.realism))
    return tasks


def _render_all(runner: _Runner, tasks: list[RenderTask], work: Path, progress: bool,
                callback: Callback | None) -> list[list[bytes]]:
    """Frame digests per task (same order), rendering what is missing.

    A finished task's digests are kept in ``.work/digests/`` so a resumed run
    does not re-read the frames of trajectories that were complete.
    """
    results: list[list[bytes] | None] = [writer.load_digests(_digest_path(work, t), len(t.filenames)) for t in tasks]
    pending = [i for i, (r, t) in enumerate(zip(results, tasks)) if r is None or t.missing()]

    def finish(i: int, digests: list[bytes]) -> None:
        results[i] = digests
        writer.save_digests(_digest_path(work, tasks[i]), digests)

    with RenderProgress([tasks[i] for i in pending], sum(len(t.filenames) for t in tasks), progress, callback) as bar:
        if runner.pool is None:
            for i in pending:
                finish(i, run_task(tasks[i], on_frame=lambda rendered: bar.advance(int(rendered)))[0])
        else:
            futures = {runner.submit(run_task, tasks[i]): i for i in pending}
            for fut in as_completed(futures):
                digests, rendered = fut.result()
                finish(futures[fut], digests)
                bar.advance(rendered)
    return results  # type: ignore[return-value]


def _digest_path(work: Path, task: RenderTask) -> Path:
    return work / "digests" / f"{task.patient}-{task.lobe}-{task.trajectory}.sha256"


# -- public API ----------------------------------------------------------------------------


def generate_dataset(cfg: Config, *, root: Path | None = None, workers: int | None = None,
                     progress: bool = True, callback: Callback | None = None) -> Path:
    """Generate (or finish, or just confirm) the synthetic dataset of ``cfg.dataset.generate``.

    Returns the dataset root. Idempotent: a complete dataset of the same config
    is left as is; a partial one is resumed. ``callback(done, total)`` is called
    as frames complete (raising from it interrupts the generation cleanly).
    With ``workers > 1`` the renderers run in spawned processes, so a script
    calling this needs the usual ``if __name__ == "__main__":`` guard.
    """
    root = Path(root) if root is not None else cfg.paths.dataset
    gen = cfg.dataset.generate
    sources = patient_sources(gen, cfg.paths.anatomy, cfg.paths.centreline)
    record = {**gen.model_dump(mode="json"), "anatomy": sources[0].anatomy, "centreline": sources[0].centreline}
    if _check_root(root, record) == "complete":
        return root
    created = not root.exists()
    with _exclusive(root):
        state = _check_root(root, record)  # again: another process may have worked here while we waited
        if state != "complete":
            try:
                _generate(root, gen, sources, record, workers or gen.workers, progress, callback,
                          fresh=state == "fresh")
            except BaseException:
                if created:
                    _remove_stub(root, [src.patient for src in sources])
                raise
    return root


def _remove_stub(root: Path, patients: list[str]) -> None:
    """A generation that failed before rendering any frame leaves no folder behind (nothing to resume).

    Only what generation writes is removed (its work folder and lock, each patient's folder and CSV); the
    root goes only once nothing else is left in it.
    """
    if any(root.rglob("*.png")):
        return
    ours = {*OURS, *patients, *(f"{p}.csv" for p in patients)}
    for p in root.iterdir():
        if p.name not in ours:
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
    try:
        root.rmdir()
    except OSError:  # something else is in it: left as it is
        pass


def _generate(root: Path, gen: Generate, sources: list[PatientSource], record: dict, workers: int, progress: bool,
              callback: Callback | None, *, fresh: bool) -> None:
    work = root / WORK_DIR
    if fresh:  # cached surfaces of another config must not be reused
        shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    write_json(work / MANIFEST, {"generator_version": GENERATOR_VERSION, "generator": record})
    remove_stale_temps(root)
    runner = _Runner(workers)
    done, tasks = False, None
    try:
        try:
            plans = runner.map(prepare_patient, sources, [gen] * len(sources), [str(root)] * len(sources))
            tasks = _tasks(plans, root, gen)
            digests = _render_all(runner, tasks, work, progress, callback)
            done = True
        finally:
            runner.close(abort=not done)
        writer.ensure_room(root, sum(len(pp.csv_text) for pp in plans) + writer.FRAME_MARGIN)  # CSVs, dataset.json
        _finish(root, gen, record, plans, tasks, digests)
    except (WriteFailed, OSError) as exc:
        if isinstance(exc, OSError) and exc.errno not in writer.FULL_ERRNOS:
            raise
        raise _disk_full(root, gen, tasks) from None


def frames_on_disk(root: Path) -> tuple[int, int]:
    """(frames, their bytes) under ``root``: what an interrupted generation keeps."""
    n = size = 0
    for p in Path(root).glob("*/*/*.png"):
        try:
            size += p.stat().st_size
            n += 1
        except OSError:
            pass
    return n, size


def _disk_full(root: Path, gen: Generate, tasks: list[RenderTask] | None) -> WriteFailed:
    """One line for a disk that filled while generating: the folder, the space free and needed, the frames kept."""
    kept, size = frames_on_disk(root)
    free = writer.free_bytes(root)
    total = sum(len(t.filenames) for t in tasks) if tasks is not None else None
    line = (f"data generate: {root}: disk full ({io.fmt_bytes(free) if free is not None else 'unknown'} free on the "
            f"file system mounted at {pathcheck.mount_point(root)}")
    if total is not None:
        per_frame = size / kept if kept else 3 * gen.image_size ** 2  # none yet: an uncompressed frame's size
        need = int((total - kept) * per_frame) + writer.FRAME_MARGIN + (total * 200)  # + the CSV rows
        line += f", about {io.fmt_bytes(need)} more needed for the {total - kept} frames left and the CSVs)"
    else:
        line += ", more needed to prepare the anatomy surfaces)"
    kept_line = f"the {kept} frames rendered so far are kept" if kept else "no frame was rendered yet"
    return WriteFailed(f"{line}; {kept_line}: free space there (or choose another --out) and run the same "
                       "command again to resume")


def _exclusive(root: Path):
    """Hold an exclusive lock on ``<root>/.generate.lock`` while generating."""
    return file_lock(root / LOCK)


def _finish(root: Path, gen: Generate, record: dict, plans: list[PatientPlan], tasks: list[RenderTask],
            digests: list[list[bytes]]) -> None:
    """Write the CSVs, then dataset.json (last), then drop the work folder."""
    by_patient: dict[str, list[bytes]] = {}
    for task, d in zip(tasks, digests):
        by_patient.setdefault(task.patient, []).extend(d)
    parts = []
    for pp in plans:
        path = root / f"{pp.source.patient}.csv"
        data = pp.csv_text.encode("utf-8")
        if not path.is_file() or path.read_bytes() != data:
            write_bytes(path, data)
        parts.append((data, by_patient.get(pp.source.patient, [])))
    meta = _metadata(gen, record, plans, writer.fingerprint(parts))
    meta["pose_fingerprint"] = writer.pose_fingerprint([data for data, _ in parts])  # the host-independent part
    # each CSV's own hash: a reader sees a CSV edited after generation (the fingerprint would no longer cover it)
    meta["csv_sha256"] = {pp.source.patient: hashlib.sha256(data).hexdigest() for pp, (data, _) in zip(plans, parts)}
    write_json(root / DATASET_JSON, meta)
    shutil.rmtree(root / WORK_DIR, ignore_errors=True)


def _metadata(gen: Generate, record: dict, plans: list[PatientPlan], fingerprint: str) -> dict:
    cam = intrinsics(gen.image_size, gen.image_size, gen.fov_deg)
    per_patient = {}
    for pp in plans:
        ts = pp.trajectories
        per_patient[pp.source.patient] = {
            "frames": int(sum(len(t) for t in ts)), "trajectories": len(ts),
            "rejected_positions": int(sum(t.rejected for t in ts)),
            "clamped_positions": int(sum(int(t.clamped.sum()) for t in ts)),
        }
    total = lambda key: int(sum(p[key] for p in per_patient.values()))  # noqa: E731
    return {
        "format": writer.FORMAT_NAME, "version": writer.FORMAT_VERSION,
        "patients": [pp.source.patient for pp in plans],
        "lobes": list(gen.lobes),
        "image_size": [gen.image_size, gen.image_size],
        "camera": cam.as_json(),
        "voxel_grid": {pp.source.patient: {"origin_mm": pp.origin_mm, "spacing_mm": pp.spacing_mm} for pp in plans},
        "anatomy": {pp.source.patient: {"source": pp.source.anatomy, "seed": pp.source.seed, "lobe_paths": pp.lobe_paths}
                    for pp in plans},
        "generator": record,
        "generator_version": GENERATOR_VERSION,
        "counts": {"frames": total("frames"), "trajectories": total("trajectories"),
                   "rejected_positions": total("rejected_positions"), "clamped_positions": total("clamped_positions"),
                   "per_patient": per_patient},
        "fingerprint": fingerprint,
        "bronchocli_version": __version__,
    }
