"""Seeded procedural human airway trees: each seed is a different "patient".

Coordinates are mm in a patient frame like DICOM LPS: +x towards the patient's
left, +y posterior, +z superior; the carina sits at the origin and the trachea
above it (largest z). Three stages:

1. Trachea and main bronchi from textbook morphometry (ranges in ``Morphometry``):
   the right main bronchus is shorter, wider and steeper than the left, and the two
   share the carina angle unequally.
2. Lobar bronchi from anatomical direction templates (right upper lobe, bronchus
   intermedius -> middle and lower lobes; left upper and lower lobes), jittered.
3. Below that, Kitaoka et al. (1999)'s bifurcation rules: a flow ratio r splits the
   parent diameter into d·r^(1/n) and d·(1-r)^(1/n) (n = 2.8), the branching angles
   follow from r, lengths are ~3 diameters, and the branching plane turns ~90° from
   the parent's. Among candidate plane rotations the one whose children keep the most
   clearance from the tree grown so far (and from the mid-sagittal plane) wins, so
   branches rarely grow through each other. Branches thinner than a per-patient
   minimum diameter, or at ``max_generation``, end the tree.

docs/anatomy.md lists the morphometry and its sources.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .. import hostfree as hf
from .airway import AirwayTree, Branch
from .graph import grid_around

RIGHT, LEFT = -1.0, 1.0  # sign of x towards each lung (LPS: +x is the patient's left)
MEDIASTINUM_MM = 8.0  # peripheral branches keep this far from the mid-sagittal plane (x = 0)


@dataclass(frozen=True)
class Morphometry:
    """Per-patient ranges (uniform draws) of the generator; lengths and diameters in mm, angles in degrees."""

    trachea_length: tuple[float, float] = (100.0, 120.0)
    trachea_diameter: tuple[float, float] = (16.0, 18.0)
    trachea_tilt: tuple[float, float] = (2.0, 10.0)  # the trachea leans posteriorly going down
    carina_angle: tuple[float, float] = (62.0, 74.0)  # between the two main bronchi
    right_share: tuple[float, float] = (0.36, 0.44)  # fraction of the carina angle on the right
    rmb_length: tuple[float, float] = (19.0, 26.0)
    lmb_length: tuple[float, float] = (42.0, 52.0)
    rmb_ratio: tuple[float, float] = (0.76, 0.84)  # main bronchus / trachea diameter
    lmb_ratio: tuple[float, float] = (0.70, 0.76)
    flow_ratio: tuple[float, float] = (0.38, 0.50)  # Kitaoka's r (minor child's share of the flow)
    diameter_exponent: float = 2.8  # Kitaoka's n
    length_per_diameter: tuple[float, float] = (2.4, 3.4)
    angle_jitter: float = 3.0  # std of the noise added to Kitaoka's branching angles
    template_jitter: float = 6.0  # std of the rotation applied to the lobar direction templates
    min_diameter: tuple[float, float] = (3.0, 3.6)  # thinner children end the tree (CT-like depth)
    max_generation: int = 10
    bend: float = 0.03  # mid-point offset of each branch as a fraction of its length
    step_mm: float = 1.0  # centreline point spacing


# Lobar bronchi: (name, parent, diameter ratio, length mm, direction as (lateral, anterior, superior)).
LOBAR = (
    ("RUL", "RMB", (0.70, 0.76), (10.0, 16.0), (0.90, 0.05, 0.25)),
    ("BI", "RMB", (0.80, 0.85), (20.0, 28.0), None),  # continues the RMB, bent towards vertical
    ("RML", "BI", (0.70, 0.75), (10.0, 15.0), (0.45, 0.75, -0.50)),
    ("RLL", "BI", (0.80, 0.85), (8.0, 14.0), (0.30, -0.25, -0.92)),
    ("LUL", "LMB", (0.78, 0.84), (10.0, 15.0), (0.85, 0.35, 0.30)),
    ("LLL", "LMB", (0.78, 0.85), (10.0, 16.0), (0.35, -0.30, -0.88)),
)
SIDE = {"RMB": RIGHT, "BI": RIGHT, "RUL": RIGHT, "RML": RIGHT, "RLL": RIGHT,
        "LMB": LEFT, "LUL": LEFT, "LLL": LEFT}


def procedural_tree(seed: int = 0, voxel_mm: float = 0.5, morph: Morphometry = Morphometry()) -> AirwayTree:
    """A seeded airway tree (no lobe paths yet; ``load_anatomy`` adds them)."""
    rng = np.random.default_rng(seed)
    grower = _Grower(rng, morph)
    grower.grow_central()
    grower.grow_peripheral()
    pts = np.concatenate([b.points for b in grower.branches])
    rad = np.concatenate([b.radii for b in grower.branches])
    spacing, origin = grid_around(pts, rad, voxel_mm)
    return AirwayTree(branches=grower.branches, origin_mm=origin, spacing_mm=spacing, name=f"procedural-{seed}")


def _unit(v: np.ndarray) -> np.ndarray:
    return hf.unit(v)


def rotate(v: np.ndarray, axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues' rotation of ``v`` about the unit ``axis``."""
    c, s = hf.cos(angle_rad), hf.sin(angle_rad)
    return v * c + np.cross(axis, v) * s + axis * hf.dot(axis, v) * (1 - c)


def kitaoka_angles(r: float, n: float) -> tuple[float, float]:
    """Branching angles (degrees) of the minor (flow share r) and major child, Kitaoka et al. 1999 eq. 4-5."""
    pw = lambda base, e: float(hf.power(base, e))  # noqa: E731 - host-independent ** (hostfree)
    a = (1 + pw(r, 4 / n) - pw(1 - r, 4 / n)) / (2 * pw(r, 2 / n))
    b = (1 + pw(1 - r, 4 / n) - pw(r, 4 / n)) / (2 * pw(1 - r, 2 / n))
    return float(np.degrees(hf.acos(np.clip(a, -1, 1)))), float(np.degrees(hf.acos(np.clip(b, -1, 1))))


@dataclass
class _Tip:
    """A branch waiting for its children."""

    index: int
    side: float
    normal: np.ndarray  # normal of the plane the branch was born in


@dataclass
class _Grower:
    """Grows one tree: the branches so far, the tips still to bifurcate, and the occupied space."""

    rng: np.random.Generator
    m: Morphometry
    branches: list[Branch] = field(default_factory=list)
    tips: deque[_Tip] = field(default_factory=deque)  # breadth-first: one generation after another
    space_pts: list[np.ndarray] = field(default_factory=list)  # every other centreline point ...
    space_rad: list[np.ndarray] = field(default_factory=list)  # ... its radius ...
    space_ids: list[np.ndarray] = field(default_factory=list)  # ... and its branch
    _index: tuple | None = None  # (points count, KD-tree, radii, branch ids) of the space, rebuilt on growth

    def u(self, lo_hi: tuple[float, float]) -> float:
        return float(self.rng.uniform(*lo_hi))

    # ---- geometry of one branch -------------------------------------------------------
    def add(self, start: np.ndarray, direction: np.ndarray, length: float, diameter: float,
            parent: int | None, taper: float | None = None) -> int:
        """Append a gently bent branch from ``start`` along ``direction``; returns its index."""
        end = start + length * direction
        side = _unit(np.cross(direction, self.rng.normal(size=3)))
        ctrl = 0.5 * (start + end) + side * self.rng.uniform(0, self.m.bend) * length
        n = max(int(np.ceil(length / self.m.step_mm)), 3)
        t = np.linspace(0, 1, n + 1)[:, None]
        pts = ((1 - t) * (1 - t)) * start + 2 * (1 - t) * t * ctrl + (t * t) * end
        taper = self.rng.uniform(0.0, 0.06) if taper is None else taper
        radii = 0.5 * diameter * (1 - taper * t[:, 0])
        gen = 0 if parent is None else self.branches[parent].generation + 1
        index = len(self.branches)
        self.branches.append(Branch(points=pts, radii=radii, parent=parent, generation=gen))
        if parent is not None:
            self.branches[parent].children.append(index)
        self._occupy(pts, radii, index)
        return index

    def _occupy(self, pts, radii, index) -> None:
        self.space_pts.append(pts[::2])
        self.space_rad.append(radii[::2])
        self.space_ids.append(np.full(len(pts[::2]), index))

    def end(self, i: int) -> np.ndarray:
        return self.branches[i].points[-1]

    def chord(self, i: int) -> np.ndarray:
        p = self.branches[i].points
        return _unit(p[-1] - p[0])

    def diameter(self, i: int) -> float:
        return 2.0 * float(self.branches[i].radii[0])

    def jitter(self, v: np.ndarray, std_deg: float) -> np.ndarray:
        axis = _unit(np.cross(v, self.rng.normal(size=3)))
        return _unit(rotate(v, axis, np.radians(self.rng.normal(0, std_deg))))

    # ---- stage 1 and 2: trachea, main and lobar bronchi ------------------------------
    def grow_central(self) -> None:
        m = self.m
        tilt = np.radians(self.u(m.trachea_tilt))
        down = _unit(np.array([self.rng.normal(0, 0.03), hf.sin(tilt), -hf.cos(tilt)]))
        lt, dt = self.u(m.trachea_length), self.u(m.trachea_diameter)
        self.add(-lt * down, down, lt, dt, None, taper=self.rng.uniform(0.0, 0.04))
        carina = self.u(m.carina_angle)
        share = self.u(m.right_share)
        named = {}
        # Both main bronchi lie in one plane through the trachea axis (so the carina angle is
        # exactly the drawn one); the plane turns a little about the axis from patient to patient.
        lateral = rotate(np.array([1.0, 0.0, 0.0]), down, np.radians(self.rng.normal(0, 8)))
        for name, side, angle, length, ratio in (
                ("RMB", RIGHT, share * carina, m.rmb_length, m.rmb_ratio),
                ("LMB", LEFT, (1 - share) * carina, m.lmb_length, m.lmb_ratio)):
            d = _unit(rotate(down, _unit(np.cross(down, side * lateral)), np.radians(angle)))
            named[name] = self.add(self.end(0), d, self.u(length), dt * self.u(ratio), 0)
        for name, parent, ratio, length, template in LOBAR:
            p = named[parent]
            if template is None:  # bronchus intermedius: the RMB bent halfway to the trachea axis
                d = self.jitter(_unit(self.chord(p) + 0.6 * down), 3.0)
            else:
                lat, ant, sup = template
                d = self.jitter(_unit(np.array([SIDE[name] * lat, -ant, sup])), m.template_jitter)
            named[name] = self.add(self.end(p), d, self.u(length), self.diameter(p) * self.u(ratio), p)
        for name in ("RUL", "RML", "RLL", "LUL", "LLL"):
            i = named[name]
            parent_dir = self.chord(self.branches[i].parent)
            normal = np.cross(parent_dir, self.chord(i))
            normal = _unit(normal) if hf.norm(normal) > 1e-6 else _unit(np.cross(parent_dir, [1.0, 0, 0]))
            self.tips.append(_Tip(i, SIDE[name], normal))

    # ---- stage 3: Kitaoka bifurcations ---------------------------------------------------
    def grow_peripheral(self) -> None:
        d_min = self.u(self.m.min_diameter)
        while self.tips:
            tip = self.tips.popleft()
            if self.branches[tip.index].generation >= self.m.max_generation:
                continue
            self.bifurcate(tip, d_min)

    def bifurcate(self, tip: _Tip, d_min: float) -> None:
        m, i = self.m, tip.index
        d = self.diameter(i)
        r = self.u(m.flow_ratio)
        d_minor = d * float(hf.power(r, 1 / m.diameter_exponent))
        d_major = d * float(hf.power(1 - r, 1 / m.diameter_exponent))
        if d_major < d_min:
            return
        th_minor, th_major = kitaoka_angles(r, m.diameter_exponent)
        th_minor = np.radians(np.clip(th_minor + self.rng.normal(0, m.angle_jitter), 15, 60))
        th_major = np.radians(np.clip(th_major + self.rng.normal(0, m.angle_jitter), 10, 60))
        lengths = (d_minor * self.u(m.length_per_diameter), d_major * self.u(m.length_per_diameter))
        u, start = self.chord(i), self.end(i)
        best = None
        base = np.radians(90 + self.rng.normal(0, 10))
        for k in range(8):
            phi = base + k * np.pi / 4
            normal = _unit(rotate(tip.normal, u, phi))
            w = np.cross(normal, u)
            dirs = (_unit(hf.cos(th_minor) * u + hf.sin(th_minor) * w),
                    _unit(hf.cos(th_major) * u - hf.sin(th_major) * w))
            # Planes close to the parent's (phi near 0/180 deg) flatten the tree: penalise them.
            score = self.clearance(start, dirs, lengths, (d_minor, d_major), i, tip.side) - 0.3 * d * abs(hf.cos(phi))
            if best is None or score > best[0]:
                best = (score, normal, dirs)
        score, normal, dirs = best
        scale = 1.0
        while score < 0 and scale > 0.5:  # still crowded: shorter children
            scale *= 0.8
            score = self.clearance(start, dirs, tuple(scale * x for x in lengths), (d_minor, d_major), i, tip.side)
        if score < 0:  # no room for children even when shortened: this branch ends the tree here
            return
        for direction, length, diam in zip(dirs, lengths, (d_minor, d_major)):
            child = self.add(start, direction, scale * length, diam, i)
            if diam >= d_min:
                self.tips.append(_Tip(child, tip.side, normal))

    def clearance(self, start, dirs, lengths, diams, parent: int, side: float) -> float:
        """Smallest gap (mm) between the candidate children and the tree, or the mid-sagittal plane."""
        kd, rad, ids = self._space()
        gap = np.inf
        for direction, length, diam in zip(dirs, lengths, diams):
            q = start + np.outer(np.linspace(0.35, 1.0, 4) * length, direction)
            dist, idx = kd.query(q, k=16)
            own = ids[idx] == parent
            g = np.where(own, np.inf, dist - rad[idx] - 0.5 * diam)
            gap = min(gap, float(g.min()))
            gap = min(gap, float((side * q[:, 0]).min() - 0.5 * diam - MEDIASTINUM_MM))  # stay in this lung
        return gap

    def _space(self) -> tuple:
        n = sum(len(p) for p in self.space_pts)
        if self._index is None or self._index[0] != n:
            self._index = (n, cKDTree(np.concatenate(self.space_pts)), np.concatenate(self.space_rad),
                           np.concatenate(self.space_ids))
        return self._index[1:]
