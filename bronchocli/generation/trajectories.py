"""Camera trajectories along the lobe paths, as in the paper (pure NumPy, no VTK).

A lobe path is sampled on a grid of *base points* every ``base_step_mm`` of arc
length (base point ``b`` sits at arc ``b * base_step_mm``; frames of any
trajectory at the same base point share its ``base_filename``). A trajectory
walks down the path, advancing a whole number of base steps per frame: its
speed starts uniform in ``step_mm = [min, max]`` and drifts by up to a quarter
of that range per frame (reflected at the limits), so increments vary within
and between trajectories.

At every frame the camera is offset from the base point by an integer number
of voxels ``(dx, dy, dz)`` in ``[-k, k]`` (``offset_voxels``) and rolled by a
multiple of ``roll_step_deg`` in ``[-roll_deg, roll_deg]`` about its optical
axis. These four variation indices form a random walk: the first frame draws
them uniformly, then at each frame every index moves by -1, 0 or +1 (uniform
among the moves that stay in range). The camera looks at the centreline point
``look_ahead_mm`` further along the path (past the path end: extrapolated along
the end tangent, the chord over the last 2 mm). Its unrolled up vector is the
path's up vector parallel-transported from the trachea (discrete parallel
transport: at each joint of the polyline it turns by the minimal rotation that
takes one segment direction onto the next); the first segment's up is the
world -y axis (anterior in the LPS-like frame of CT data), or +z when the
trachea runs along y.

Inside-lumen rule: a camera position is accepted when its distance ``d`` to
the airway centreline satisfies ``d < r - wall_margin_mm`` (``r`` the local
radius). A rejected proposal is redrawn (counted in ``rejected``) up to
``MAX_TRIES`` times; if all fail, the last proposal's offset is moved towards
the centreline one voxel at a time on its largest component until it is
accepted or zero (the frame is counted in ``clamped``). Base points keep an
arc-length margin from both path ends so no offset pokes through the end caps;
the last one also stays half a look-ahead before the path end, where the
segmented airway (not the real one) is closed.

With ``max_frames`` a trajectory covers a contiguous segment of at most that
many frames starting at a seeded uniform base point, chosen so that the
expected segment fits before the path end; without it, it runs from the
trachea entrance to the path end. Every random number comes from
``numpy.random.default_rng`` seeded with (generate.seed, patient index, lobe
index, trajectory index), so plans never depend on worker count or order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .. import geometry
from .. import hostfree as hf
from ..cells import LOBES
from ..config import Generate
from ..errors import DataError

MAX_TRIES = 20  # redraws of a variation step before clamping towards the centreline
END_TANGENT_MM = 2.0  # chord length that defines the end tangent for look-at extrapolation
SPEED_DRIFT = 0.25  # max per-frame speed change, as a fraction of step_mm's range
END_STOP_FRACTION = 0.5  # last base point this fraction of look_ahead_mm before the path end

DistanceFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]  # points mm -> (distance, local radius)


# -- path parameterisation --------------------------------------------------------


def _unit(v: np.ndarray) -> np.ndarray:
    return hf.unit(v)


def minimal_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation of smallest angle taking unit vector ``a`` onto unit vector ``b`` (Rodrigues)."""
    v = np.cross(a, b)
    c = float(hf.dot(a, b))
    if c < -1.0 + 1e-12:
        raise DataError("lobe path reverses direction (180° turn between two centreline segments)")
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + hf.matmul(vx, vx) / (1.0 + c)


def initial_up(tangent: np.ndarray) -> np.ndarray:
    """Up vector of the first path segment: world -y (anterior) projected off the tangent, else +z."""
    hint = np.array([0.0, -1.0, 0.0]) if abs(tangent[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    return _unit(hint - hf.dot(hint, tangent) * tangent)


def transported_ups(points: np.ndarray) -> np.ndarray:
    """Up vector of each polyline segment ``(K-1, 3)``, parallel-transported from the first."""
    t = _unit(np.diff(points, axis=0))
    ups = np.empty_like(t)
    ups[0] = initial_up(t[0])
    for i in range(1, len(t)):
        u = hf.matvec(minimal_rotation(t[i - 1], t[i]), ups[i - 1])
        ups[i] = _unit(u - hf.dot(u, t[i]) * t[i])  # re-orthogonalise against round-off drift
    return ups


@dataclass
class PathSampler:
    """Arc-length parameterisation of one lobe path: points, radii and transported up vectors."""

    points: np.ndarray  # (K, 3) mm
    radii: np.ndarray  # (K,)
    arc: np.ndarray = field(init=False)  # (K,) cumulative arc length
    ups: np.ndarray = field(init=False)  # (K-1, 3) per segment

    def __post_init__(self) -> None:
        seg = hf.norm(np.diff(self.points, axis=0))
        keep = np.concatenate([[True], seg > 1e-9])  # drop repeated points
        self.points, self.radii = self.points[keep], self.radii[keep]
        if len(self.points) < 2:
            raise DataError("lobe path has fewer than two distinct points")
        self.arc = np.concatenate([[0.0], np.cumsum(hf.norm(np.diff(self.points, axis=0)))])
        self.ups = transported_ups(self.points)

    @property
    def length(self) -> float:
        return float(self.arc[-1])

    def _segment(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        i = np.clip(np.searchsorted(self.arc, a, side="right") - 1, 0, len(self.arc) - 2)
        w = (a - self.arc[i]) / (self.arc[i + 1] - self.arc[i])
        return i, w

    def position(self, a: np.ndarray) -> np.ndarray:
        """Centreline points at arc lengths ``a`` (clamped to the path)."""
        a = np.clip(np.asarray(a, dtype=np.float64), 0.0, self.length)
        i, w = self._segment(a)
        return self.points[i] + w[..., None] * (self.points[i + 1] - self.points[i])

    def up(self, a: np.ndarray) -> np.ndarray:
        """Transported up vector of the segment holding arc length ``a``."""
        i, _ = self._segment(np.clip(np.asarray(a, dtype=np.float64), 0.0, self.length))
        return self.ups[i]

    def look_at(self, a: np.ndarray) -> np.ndarray:
        """Centreline point at arc ``a``; beyond the end, extrapolated along the end tangent."""
        a = np.asarray(a, dtype=np.float64)
        end = self.points[-1]
        tangent = _unit(end - self.position(np.array(max(self.length - END_TANGENT_MM, 0.0))))
        beyond = np.maximum(a - self.length, 0.0)
        return self.position(a) + beyond[..., None] * tangent


# -- planning ----------------------------------------------------------------------


@dataclass
class PlannedTrajectory:
    """Camera poses of one trajectory (mm frame of the anatomy) and how its variations were drawn."""

    patient: str
    lobe: str
    index: int
    base_index: np.ndarray  # (N,) int: base point b at arc b * base_step_mm
    arc_mm: np.ndarray  # (N,)
    offset_voxels: np.ndarray  # (N, 3) int
    roll_deg: np.ndarray  # (N,)
    position_mm: np.ndarray  # (N, 3)
    rotation: np.ndarray  # (N, 3, 3) columns (forward, left, up)
    radius_mm: np.ndarray  # (N,) local airway radius at the camera
    clearance_mm: np.ndarray  # (N,) radius minus distance to the centreline
    clamped: np.ndarray  # (N,) bool: offset pulled towards the centreline
    rejected: int = 0  # variation proposals redrawn because they left the lumen

    def __len__(self) -> int:
        return len(self.base_index)


def roll_levels(gen: Generate) -> int:
    """Number of roll steps on each side of zero: [-n, n] * roll_step_deg."""
    return int(math.floor(gen.roll_deg / gen.roll_step_deg + 1e-9))


def trajectory_rng(gen: Generate, patient_index: int, lobe: str, trajectory: int) -> np.random.Generator:
    lobe_index = LOBES.index(lobe) if lobe in LOBES else 100 + sum(map(ord, lobe))
    return np.random.default_rng([abs(gen.seed), int(gen.seed < 0), patient_index, lobe_index, trajectory])


def _base_range(path: PathSampler, gen: Generate, spacing: np.ndarray) -> tuple[int, int]:
    """First and last base index, keeping the largest offset away from the path's end caps."""
    margin = math.sqrt(3.0) * gen.offset_voxels * float(np.max(spacing)) + gen.wall_margin_mm
    first = int(math.ceil(margin / gen.base_step_mm - 1e-9))
    # Stop half a look-ahead before the leaf's end cap: the segmented airway ends there, the real one does not.
    end_margin = max(margin, END_STOP_FRACTION * gen.look_ahead_mm)
    last = int(math.floor((path.length - end_margin) / gen.base_step_mm + 1e-9))
    if last - first < 1 or (last - first) * gen.base_step_mm < gen.step_mm[1]:
        raise DataError(f"lobe path of {path.length:.1f} mm is too short for step_mm={list(gen.step_mm)} "
                        f"and offset_voxels={gen.offset_voxels}")
    return first, last


def _base_points(rng: np.random.Generator, gen: Generate, first: int, last: int) -> np.ndarray:
    """Base indices visited by one trajectory (varying speed; contiguous segment with max_frames)."""
    lo, hi = gen.step_mm
    speed = rng.uniform(lo, hi)
    start = first
    if gen.max_frames is not None:
        # Room for the expected segment, and always for one full-speed step (>= 2 frames).
        span = max(int(round((gen.max_frames - 1) * 0.5 * (lo + hi) / gen.base_step_mm)),
                   int(math.ceil(hi / gen.base_step_mm - 1e-9)))
        start = int(rng.integers(first, max(first, last - span) + 1))
    out = [start]
    while gen.max_frames is None or len(out) < gen.max_frames:
        speed += rng.uniform(-1.0, 1.0) * SPEED_DRIFT * (hi - lo)
        if speed < lo or speed > hi:  # reflect at the limits
            speed = 2 * lo - speed if speed < lo else 2 * hi - speed
            speed = min(max(speed, lo), hi)
        nxt = out[-1] + max(1, int(round(speed / gen.base_step_mm)))
        if nxt > last:
            break
        out.append(nxt)
    return np.asarray(out, dtype=np.int64)


def _step(rng: np.random.Generator, state: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """One random-walk move: each index -1/0/+1, uniform among moves that stay within [-bound, bound]."""
    lo = np.where(state > -bounds, -1, 0)
    hi = np.where(state < bounds, 1, 0)
    return state + rng.integers(lo, hi + 1)


def _inside(offsets: np.ndarray, base: np.ndarray, spacing: np.ndarray, margin: float,
            distance: DistanceFn) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pos = base + offsets * spacing
    d, r = distance(pos)
    return d < r - margin, r, r - d


def _choose(rng, state, bounds, first, base, spacing, margin, distance) -> tuple[np.ndarray, int, bool]:
    """Next variation state at one base point: (state, rejected proposals, clamped?)."""
    rejected = 0
    for _ in range(MAX_TRIES):
        prop = rng.integers(-bounds, bounds + 1) if first else _step(rng, state, bounds)
        ok, _, _ = _inside(prop[None, :3], base, spacing, margin, distance)
        if ok[0]:
            return prop, rejected, False
        rejected += 1
    prop = prop.copy()
    while prop[:3].any():
        j = int(np.argmax(np.abs(prop[:3])))
        prop[j] -= np.sign(prop[j])
        if _inside(prop[None, :3], base, spacing, margin, distance)[0][0]:
            break
    return prop, rejected, True


def plan_trajectory(path: PathSampler, gen: Generate, spacing: np.ndarray, distance: DistanceFn,
                    rng: np.random.Generator, *, patient: str = "", lobe: str = "", index: int = 0) -> PlannedTrajectory:
    """One random-walk trajectory along ``path`` (see the module docstring for the rules)."""
    spacing = np.asarray(spacing, dtype=np.float64)
    first, last = _base_range(path, gen, spacing)
    bases = _base_points(rng, gen, first, last)
    arcs = bases * gen.base_step_mm
    base_mm = path.position(arcs)
    bounds = np.array([gen.offset_voxels] * 3 + [roll_levels(gen)])
    states, clamped, rejected = [], [], 0
    state = np.zeros(4, dtype=np.int64)
    for t, base in enumerate(base_mm):
        state, rej, clamp = _choose(rng, state, bounds, t == 0, base, spacing, gen.wall_margin_mm, distance)
        states.append(state)
        clamped.append(clamp)
        rejected += rej
    states = np.asarray(states, dtype=np.int64)
    offsets = states[:, :3]
    position = base_mm + offsets * spacing
    d, radius = distance(position)
    roll = states[:, 3] * gen.roll_step_deg
    forward = path.look_at(arcs + gen.look_ahead_mm) - position
    R = geometry.roll_about_forward(geometry.look_at_rotation(forward, path.up(arcs)), roll)
    return PlannedTrajectory(patient, lobe, index, bases, arcs, offsets, roll.astype(np.float64), position,
                             np.asarray(R), np.asarray(radius, dtype=np.float64), np.asarray(radius - d, dtype=np.float64),
                             np.asarray(clamped, dtype=bool), rejected)


def plan_lobe(path: PathSampler, gen: Generate, spacing: np.ndarray, distance: DistanceFn, *,
              patient: str, patient_index: int, lobe: str) -> list[PlannedTrajectory]:
    """The ``gen.trajectories`` trajectories of one (patient, lobe), each from its own seeded stream."""
    return [plan_trajectory(path, gen, spacing, distance, trajectory_rng(gen, patient_index, lobe, t),
                            patient=patient, lobe=lobe, index=t) for t in range(gen.trajectories)]
