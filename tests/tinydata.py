"""A tiny valid bronchopose dataset for tests, written in well under a second (no VTK).

``write_tiny_dataset(root)`` writes the layout of docs/dataset-format.md:
``dataset.json`` (with a content fingerprint), one ``<patient>.csv`` per
patient and PNG frames. Camera paths are smooth random walks whose roll and
yaw cross ±180° in some trajectories (the first trajectory of every lobe
always does). Each frame is a view of a fixed 3-D texture: pixel directions
of the camera (x forward, y left, z up; R from the pose) hit the texture at a
fixed depth, so images change consistently with the pose and a network can
learn relative motion from them.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
from PIL import Image
from scipy.spatial.transform import Rotation

from bronchocli import __version__, geometry

SPACING_MM = (0.5, 0.5, 0.5)
_LOBE_BASE = {"ur": (60.0, 40.0, 80.0), "br": (60.0, 45.0, 50.0), "ul": (30.0, 40.0, 80.0), "bl": (30.0, 45.0, 50.0)}
_WAVES = np.random.default_rng(1234).normal(0.0, 0.5, (3, 4, 3))  # channel x wave x xyz
_PHASES = np.random.default_rng(4321).uniform(0, 2 * math.pi, (3, 4))


def tiny_path(rng: np.random.Generator, n: int, base: np.ndarray, cross: bool) -> np.ndarray:
    """Smooth random poses ``(n, 6)``; with ``cross`` the roll starts near 180° and crosses it."""
    speed = rng.uniform(0.5, 1.5)
    heading = rng.normal(size=3)
    vel = speed * heading / np.linalg.norm(heading) + np.cumsum(rng.normal(0, 0.1, (n, 3)), 0)
    pos = base + rng.normal(0, 2, 3) + np.concatenate([np.zeros((1, 3)), np.cumsum(vel[1:], 0)])
    start = np.array([rng.uniform(-180, 180), rng.uniform(-40, 40), rng.uniform(-180, 180)])
    rate = np.array([rng.uniform(-8, 8), rng.uniform(-2, 2), rng.uniform(-8, 8)])
    if cross:
        start[0], rate[0] = 176.0, 3.0
    ang = start + np.arange(n)[:, None] * rate + np.cumsum(rng.normal(0, 0.5, (n, 3)), 0)
    ang[:, 1] = np.clip(ang[:, 1], -70, 70)
    return np.column_stack([pos, geometry.wrap_deg(ang)])


def render_views(poses: np.ndarray, size: int, depth: float = 8.0) -> np.ndarray:
    """``(N, 6)`` poses -> ``(N, size, size, 3)`` uint8 views of the fixed 3-D texture."""
    f = (size / 2) / math.tan(math.radians(35.0))
    c = (size - 1) / 2
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    dirs = np.stack([np.ones_like(u), -(u - c) / f, -(v - c) / f], -1).reshape(-1, 3)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    R = geometry.euler_to_matrix(poses[:, 3:])  # (N, 3, 3)
    points = poses[:, None, :3] + depth * np.einsum("nij,pj->npi", R, dirs)  # (N, P, 3)
    phase = points @ _WAVES.reshape(12, 3).T + _PHASES.reshape(12)  # (N, P, channel*wave)
    value = 0.5 + 0.5 * np.sin(phase).reshape(len(poses), size * size, 3, 4).mean(-1)  # in [0, 1]
    return (value * 255).round().astype(np.uint8).reshape(len(poses), size, size, 3)


def _patient_rows(rng, patient, lobes, trajectories, frames, size, root) -> list[dict]:
    rows = []
    for lobe in lobes:
        for t in range(trajectories):
            poses = tiny_path(rng, frames, np.asarray(_LOBE_BASE.get(lobe, (45.0, 45.0, 65.0))), cross=t == 0)
            images = render_views(poses, size)
            (root / patient / lobe).mkdir(parents=True, exist_ok=True)
            for k in range(frames):
                name = f"{patient}/{lobe}/t{t:03d}_f{k:04d}.png"
                Image.fromarray(images[k]).save(root / name, compress_level=1)
                x, y, z, a, b, g = poses[k]
                rows.append(dict(patient=patient, lobe=lobe, trajectory=t, frame=k, pos_x=x, pos_y=y, pos_z=z,
                                 Rx=a, Ry=b, Rz=g, filename=name, base_filename=f"{lobe}/b{k}"))
    return rows


def fingerprint(root: Path, patients: list[str]) -> str:
    """As docs/dataset-format.md defines it: per patient, the CSV bytes then each listed frame's SHA-256 digest."""
    h = hashlib.sha256()
    for p in patients:
        h.update((root / f"{p}.csv").read_bytes())
        for name in pd.read_csv(root / f"{p}.csv", usecols=["filename"])["filename"]:
            h.update(hashlib.sha256((root / name).read_bytes()).digest())
    return h.hexdigest()


def write_tiny_dataset(root, *, patients: int = 3, lobes=("ur", "br", "ul", "bl"), trajectories: int = 6,
                       frames: int = 12, image_size: int = 32, seed: int = 0) -> Path:
    """Write a valid bronchopose dataset under ``root`` and return its path."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    ids = [f"p{i:02d}" for i in range(patients)]
    counts = {}
    for p in ids:
        rows = _patient_rows(rng, p, lobes, trajectories, frames, image_size, root)
        pd.DataFrame(rows).to_csv(root / f"{p}.csv", index=False)
        counts[p] = {"frames": len(rows), "trajectories": len(lobes) * trajectories}
    f = (image_size / 2) / math.tan(math.radians(35.0))
    c = (image_size - 1) / 2
    meta = {
        "format": "bronchopose-dataset", "version": 1, "patients": ids, "lobes": list(lobes),
        "image_size": [image_size, image_size],
        "camera": {"fov_deg": 70.0, "fx": f, "fy": f, "cx": c, "cy": c, "near_mm": 0.2, "far_mm": 400.0},
        "voxel_grid": {p: {"origin_mm": [0.0, 0.0, 0.0], "spacing_mm": list(SPACING_MM)} for p in ids},
        "generator": {"tinydata": {"seed": seed, "trajectories": trajectories, "frames": frames}},
        "counts": {"frames": sum(v["frames"] for v in counts.values()),
                   "trajectories": sum(v["trajectories"] for v in counts.values()), "per_patient": counts},
        "fingerprint": fingerprint(root, ids),
        "bronchocli_version": __version__,
    }
    (root / "dataset.json").write_text(json.dumps(meta, indent=2))
    return root


def turning_angles(beta: float, n: int = 40) -> np.ndarray:
    """Intrinsic XYZ Euler angles (degrees, canonical) of a camera turning by ~2.5° a frame from
    (20°, beta, -30°): near beta = ±90° (gimbal lock) alpha and gamma swing far more than the camera turns."""
    start = Rotation.from_euler("XYZ", [20.0, beta, -30.0], degrees=True)
    return (start * Rotation.from_rotvec(np.outer(np.arange(n), np.radians([1.5, 0.3, 2.0])))).as_euler(
        "XYZ", degrees=True)
