"""Seeded procedural street worlds: triangle meshes with semantics, actors with tracks, an ego path.

`generate_world(WorldConfig(style=..., seed=...))` builds, deterministically from the seed:
a ground heightfield (road, curbs, sidewalks, terrain, medians) shaped by a road layout
(straight, curved, T or X junction); buildings along the roads with varied footprint, height and
setback and some facade geometry; parked and moving vehicles (body, cabin, wheels; the moving ones
with a pose per 0.1 s and a 3D box); pedestrians; poles, street lights, signs, traffic lights;
trees, bushes, hedges; fences and walls; and the ego's trajectory along its lane at 10 Hz.
Styles set the mix: urban block, suburban, intersection, boulevard with trees.

Frames: world frame z up, metres; the ego starts at x = 0 heading +x, right-hand traffic.
Actor frames: x forward, y left, z up, origin at the centre of the box's footprint on the ground.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import Field, model_serializer

from ..boxes import Box
from ..config import SEED, StrictModel, load_yaml, validate_model
from ..labels import label_id
from ..mesh import TriangleMesh
from ..transforms import interpolate_poses, make_pose
from . import primitives as pr
from .layout import Layout, Road, make_layout

WORLD_VERSION = 1
STYLES = ("urban", "suburban", "intersection", "boulevard")
GROUND_STEP = 0.25  # heightfield spacing, metres
SIDEWALK_HEIGHT = 0.15
TERRAIN_HEIGHT = 0.10

L = {name: label_id(name) for name in (
    "road", "sidewalk", "curb", "terrain", "other_ground", "lane_marker", "building", "car", "truck",
    "pedestrian", "pole", "sign", "traffic_light", "vegetation", "tree_trunk", "fence")}


class WorldConfig(StrictModel):
    """What to generate. Every count and size not given is drawn from the style's ranges."""

    style: Literal["urban", "suburban", "intersection", "boulevard"] = "urban"
    seed: int = SEED.field(0)
    layout: Literal["auto", "straight", "curved", "t_junction", "x_junction"] = "auto"
    length_m: float = Field(default=102.4, gt=20, le=5000, description="road length ahead of the ego")
    ego_speed_mps: float | None = Field(default=None, ge=0, le=40)
    duration_s: float = Field(default=2.0, gt=0, le=600, description="ego trajectory and actor tracks")
    moving_vehicles: int | None = Field(default=None, ge=0, le=200)
    pedestrians: int | None = Field(default=None, ge=0, le=500)
    history_s: float = Field(default=0.0, ge=0, le=60, description="ego trajectory and actor tracks before t = 0")

    @model_serializer(mode="wrap")
    def _history_only_when_asked(self, handler):
        # history_s is written only where it is set: every config without one dumps as before
        # (the dataset samples' meta.json `world` stays byte for byte what it was)
        out = handler(self)
        if isinstance(out, dict) and not self.history_s:
            out.pop("history_s", None)
        return out

    @classmethod
    def from_yaml(cls, path) -> "WorldConfig":
        """Read a scenario file's `scene.world` section (or `scene.frames.world`, the world whose
        cameras a converted scene starts from; or a top-level `world:` section, or a file that is
        only that section)."""
        data = load_yaml(path)
        if isinstance(data, dict) and isinstance(data.get("scene"), dict) and "world" in data["scene"]:
            return validate_model(cls, data["scene"]["world"], f"{path} (scene.world)", "world settings")
        frames = data.get("scene", {}).get("frames") if isinstance(data, dict) and isinstance(data.get("scene"), dict) else None
        if isinstance(frames, dict) and "world" in frames:
            return validate_model(cls, frames["world"], f"{path} (scene.frames.world)", "world settings")
        if isinstance(data, dict) and "world" in data:
            return validate_model(cls, data["world"], f"{path} (world)", "world settings")
        return validate_model(cls, data, str(path), "world settings")


@dataclass
class Actor:
    """A rigid moving object: its mesh in the actor frame, its box size (l, w, h) and a track of
    actor-to-world poses at `times`."""

    instance: int
    label: int
    mesh: TriangleMesh
    size: np.ndarray
    times: np.ndarray
    poses: np.ndarray

    def pose_at(self, t: float) -> np.ndarray:
        """(4, 4) actor-to-world at time t (linear / SLERP between track samples, clamped)."""
        t = float(np.clip(t, self.times[0], self.times[-1]))
        i = int(np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2))
        if len(self.times) == 1:
            return self.poses[0]
        s = (t - self.times[i]) / (self.times[i + 1] - self.times[i])
        return interpolate_poses(self.poses[i], self.poses[i + 1], np.array([s]))[0]

    def box_at(self, t: float) -> Box:
        """The actor's 3D box at time t, world frame (its pose sits at the box's bottom centre)."""
        return Box.on_ground(self.pose_at(t), self.size, label=self.label, instance=self.instance)


@dataclass
class World:
    """A generated world: static mesh (world frame), actors, the ego path and the sun."""

    config: WorldConfig
    layout: Layout
    static: TriangleMesh
    actors: list[Actor]
    ego_times: np.ndarray
    ego_poses: np.ndarray
    sun_dir: np.ndarray  # unit vector towards the sun, world frame
    boxes_static: list[Box] = field(default_factory=list)  # parked vehicles etc.

    def ego_pose_at(self, t: float) -> np.ndarray:
        """(4, 4) ego-to-world at time t: between the 10 Hz path samples (linear / SLERP); before the
        first sample (t < 0 without `history_s`) or after the last, extrapolated from the nearest
        segment."""
        i = int(np.clip(np.searchsorted(self.ego_times, t, side="right") - 1, 0, len(self.ego_times) - 2))
        s = (t - self.ego_times[i]) / (self.ego_times[i + 1] - self.ego_times[i])
        return interpolate_poses(self.ego_poses[i], self.ego_poses[i + 1], np.array([s]))[0]

    def actor_meshes_at(self, t: float) -> list[TriangleMesh]:
        out = []
        for a in self.actors:
            p = a.pose_at(t)
            m = TriangleMesh(a.mesh.vertices @ p[:3, :3].T + p[:3, 3], a.mesh.faces, a.mesh.labels,
                             a.mesh.instances, a.mesh.colors, self.static.origin)
            out.append(m)
        return out

    def mesh_at(self, t: float) -> TriangleMesh:
        """The static scene plus every actor posed at time t."""
        return TriangleMesh.concatenate([self.static] + self.actor_meshes_at(t))

    def boxes_at(self, t: float) -> list[Box]:
        """Every box at time t, world frame: the static ones, then one per actor."""
        return self.boxes_static + [a.box_at(t) for a in self.actors]


# --- style parameters ------------------------------------------------------------------------

_STYLE = {
    "urban": dict(layouts=("straight", "x_junction", "t_junction", "curved"), lanes=(1, 2), sidewalk=(3.0, 5.0),
                  median=0.0, setback=(0.0, 1.0), height=(10.0, 40.0), frontage=(10.0, 24.0), depth=(12.0, 22.0),
                  gap=(0.0, 1.5), parked=0.6, moving=(2, 6), peds=(4, 12), trees=0.0, fences=0.1, speed=(6.0, 11.0)),
    "suburban": dict(layouts=("curved", "straight", "t_junction"), lanes=(1, 1), sidewalk=(1.8, 2.5), median=0.0,
                     setback=(5.0, 10.0), height=(5.0, 9.0), frontage=(9.0, 15.0), depth=(9.0, 14.0),
                     gap=(5.0, 12.0), parked=0.35, moving=(0, 3), peds=(0, 4), trees=0.6, fences=0.8, speed=(6.0, 10.0)),
    "intersection": dict(layouts=("x_junction", "t_junction"), lanes=(1, 2), sidewalk=(3.0, 4.5), median=0.0,
                         setback=(0.0, 3.0), height=(8.0, 30.0), frontage=(12.0, 26.0), depth=(12.0, 20.0),
                         gap=(0.5, 4.0), parked=0.4, moving=(3, 8), peds=(4, 14), trees=0.2, fences=0.2, speed=(5.0, 9.0)),
    "boulevard": dict(layouts=("straight", "curved"), lanes=(2, 3), sidewalk=(4.0, 6.0), median=(3.0, 6.0),
                      setback=(0.5, 4.0), height=(12.0, 30.0), frontage=(14.0, 28.0), depth=(12.0, 20.0),
                      gap=(0.0, 3.0), parked=0.5, moving=(3, 8), peds=(3, 10), trees=1.0, fences=0.1, speed=(9.0, 14.0)),
}


def _u(rng, lo_hi):
    return float(rng.uniform(*lo_hi)) if isinstance(lo_hi, tuple) else float(lo_hi)


class _Ids:
    def __init__(self):
        self.n = 0

    def __call__(self) -> int:
        self.n += 1
        return self.n


def _color_jitter(rng, base, amount=0.08):
    return tuple(np.clip(np.asarray(base) + rng.uniform(-amount, amount, 3), 0.02, 0.98))


# --- ground ----------------------------------------------------------------------------------


GROUND_BLOCK = 4  # cells per side of a block that may be merged into two triangles


def _ground(layout: Layout, x0, x1, y0, y1, footprints: list[np.ndarray]) -> TriangleMesh:
    """Heightfield over the rectangle: road at z=0, sidewalks and medians raised (curbs are the
    steep cells between), terrain slightly raised. Cells inside building footprints are left out
    (never visible, and they would put voxels inside buildings).

    The 0.25 m grid is only kept where something changes: blocks of 4 x 4 cells of one class,
    flat and clear of footprints become two triangles (their shared edges with fine blocks are
    collinear and flat, so the surface stays closed). This cuts the ground to about a tenth."""
    b = GROUND_BLOCK
    nbx = int(np.ceil((x1 - x0) / (GROUND_STEP * b)))
    nby = int(np.ceil((y1 - y0) / (GROUND_STEP * b)))
    xs = x0 + GROUND_STEP * np.arange(nbx * b + 1)
    ys = y0 + GROUND_STEP * np.arange(nby * b + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    pts = np.c_[gx.ravel(), gy.ravel()]
    cls, _ = layout.classify(pts)
    inside = np.zeros(len(pts), bool)
    for fp in footprints:
        inside |= _inside_polygon(pts, fp)
    z = np.select([cls == 1, cls == 2, cls == 3], [0.0, SIDEWALK_HEIGHT, SIDEWALK_HEIGHT], TERRAIN_HEIGHT)
    v = np.c_[pts, z]
    nx, ny = len(xs), len(ys)
    idx = np.arange(nx * ny).reshape(nx, ny)
    code = (cls.astype(np.int16) * 2 + inside).reshape(nx, ny)

    # Per block: uniform if all (b+1)^2 vertices share class and footprint state.
    blocks = np.lib.stride_tricks.sliding_window_view(code, (b + 1, b + 1))[::b, ::b]
    uniform = (blocks == blocks[..., :1, :1]).all(axis=(-1, -2))
    under = blocks[..., 0, 0] % 2 == 1  # uniform and inside a footprint: no ground at all
    bi, bj = np.nonzero(uniform & ~under)
    a0, a1 = idx[bi * b, bj * b], idx[bi * b + b, bj * b]
    a2, a3 = idx[bi * b + b, bj * b + b], idx[bi * b, bj * b + b]
    coarse = np.vstack([np.c_[a0, a1, a2], np.c_[a0, a2, a3]])
    fi, fj = np.nonzero(~uniform)
    ci = (fi[:, None, None] * b + np.arange(b)[None, :, None]).repeat(b, axis=2).ravel()
    cj = (fj[:, None, None] * b + np.arange(b)[None, None, :]).repeat(b, axis=1).ravel()
    c0, c1, c2, c3 = idx[ci, cj], idx[ci + 1, cj], idx[ci + 1, cj + 1], idx[ci, cj + 1]
    fine = np.vstack([np.c_[c0, c1, c2], np.c_[c0, c2, c3]])
    faces = np.vstack([coarse, fine])
    # Drop only cells entirely under a building: a cell straddling a wall stays (its covered part
    # is hidden), so the ground meets every wall without a gap.
    faces = faces[~np.all(inside[faces], axis=1)]
    fc = cls[faces]  # (F, 3) classes of the corners
    zspan = np.ptp(v[faces][:, :, 2], axis=1)
    majority = np.where((fc[:, 0] == fc[:, 1]) | (fc[:, 0] == fc[:, 2]), fc[:, 0], fc[:, 1])
    lab = np.select([majority == 1, majority == 2, majority == 3], [L["road"], L["sidewalk"], L["terrain"]], L["terrain"])
    lab = np.where(zspan > 0.04, L["curb"], lab)  # the steep cells between road and sidewalk
    palette = {L["road"]: (0.22, 0.22, 0.24), L["sidewalk"]: (0.62, 0.60, 0.57), L["curb"]: (0.70, 0.70, 0.68),
               L["terrain"]: (0.30, 0.42, 0.18)}
    colors = np.zeros((len(lab), 3))
    for k, c in palette.items():
        colors[lab == k] = c
    used, remap = np.unique(faces, return_inverse=True)
    return TriangleMesh(v[used], remap.reshape(-1, 3), lab, np.zeros(len(lab), np.int32), colors.astype(np.float32))


def _convex_overlap(p: np.ndarray, q: np.ndarray) -> bool:
    """Do two convex polygons (K, 2) overlap? (separating-axis test)"""
    for poly in (p, q):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.stack([-edges[:, 1], edges[:, 0]], 1)
        for nrm in normals:
            a, b = p @ nrm, q @ nrm
            if a.max() < b.min() or b.max() < a.min():
                return False
    return True


def _polygon_distance(xy: np.ndarray, poly: np.ndarray) -> float:
    """Distance from a point to a convex polygon (0 inside)."""
    if _inside_polygon(xy[None], poly)[0]:
        return 0.0
    a = poly
    b = np.roll(poly, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", xy - a, ab) / np.einsum("ij,ij->i", ab, ab), 0, 1)
    return float(np.min(np.linalg.norm(a + t[:, None] * ab - xy, axis=1)))


def _inside_polygon(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Points (N, 2) inside a convex polygon (K, 2) given counter-clockwise."""
    inside = np.ones(len(p), bool)
    for i in range(len(poly)):
        a, b = poly[i], poly[(i + 1) % len(poly)]
        inside &= (b[0] - a[0]) * (p[:, 1] - a[1]) - (b[1] - a[1]) * (p[:, 0] - a[0]) >= 0
    return inside


def _lane_markings(layout: Layout) -> list[TriangleMesh]:
    """Dashed centre lines and lane dividers as thin quads 5 mm above the road."""
    out = []
    for road in layout.roads:
        s_all = np.arange(0.0, road.length, 9.0)
        offsets = [0.0] if road.median == 0 else []
        for k in range(1, road.lanes):
            offsets += [k * road.lane_width + road.median / 2, -(k * road.lane_width + road.median / 2)]
        for off in offsets:
            for s in s_all:
                p0, t0 = road.at(s, off)
                p1, _ = road.at(min(s + 3.0, road.length), off)
                if layout.junction is not None and np.min(np.linalg.norm(np.r_[p0, p1] - layout.junction, axis=1)) < 12:
                    continue
                n = np.array([-t0[0, 1], t0[0, 0]]) * 0.075
                c = np.array([p0[0] - n, p1[0] - n, p1[0] + n, p0[0] + n])
                out.append(pr.quad(np.c_[c, np.full(4, 0.005)], label=L["lane_marker"], color=(0.92, 0.92, 0.88)))
    return out


# --- objects ---------------------------------------------------------------------------------


def _building(rng, ids, centre, yaw, frontage, depth, height, style) -> tuple[TriangleMesh, np.ndarray]:
    """A building block with optional facade geometry; returns the mesh and its footprint."""
    inst = ids()
    base = _color_jitter(rng, rng.choice([[0.62, 0.55, 0.48], [0.55, 0.35, 0.28], [0.75, 0.73, 0.68],
                                          [0.45, 0.47, 0.50], [0.70, 0.62, 0.50]]), 0.06)
    lab = L["building"]
    parts = [pr.box([0, 0, height / 2], [depth, frontage, height], label=lab, color=base, instance=inst)]
    if style in ("urban", "intersection", "boulevard"):
        # parapet on the roof, a ground-floor canopy and a few balcony slabs on the street side
        parts.append(pr.box([depth / 2 - 0.15, 0, height + 0.5], [0.3, frontage, 1.0], label=lab, color=base,
                            instance=inst))
        if rng.random() < 0.6:
            parts.append(pr.box([depth / 2 + 0.75, 0, 3.4], [1.5, frontage * 0.9, 0.15], label=lab,
                                color=_color_jitter(rng, (0.3, 0.3, 0.32)), instance=inst))
        if rng.random() < 0.5 and height > 9:
            for zb in np.arange(6.5, height - 2, 3.2):
                for yb in np.linspace(-frontage / 2 + 2.5, frontage / 2 - 2.5, max(1, int(frontage // 7))):
                    parts.append(pr.box([depth / 2 + 0.6, yb, zb], [1.2, 2.4, 0.12], label=lab, color=base, instance=inst))
    else:
        # a pitched roof: a triangular prism
        ridge = min(frontage, depth) * 0.35
        hd, hf = depth / 2, frontage / 2
        v = np.array([[-hd, -hf, height], [hd, -hf, height], [hd, hf, height], [-hd, hf, height],
                      [0, -hf, height + ridge], [0, hf, height + ridge]])
        f = np.array([[0, 1, 4], [3, 5, 2], [1, 2, 5], [1, 5, 4], [0, 4, 5], [0, 5, 3], [0, 3, 2], [0, 2, 1]])
        roof = _color_jitter(rng, rng.choice([[0.45, 0.18, 0.15], [0.25, 0.25, 0.28]]), 0.05)
        parts.append(TriangleMesh(v, f, np.full(8, lab, np.int16), np.full(8, inst, np.int32),
                                  np.tile(np.asarray(roof, np.float32), (8, 1))))
    m = TriangleMesh.concatenate(parts)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s], [s, c]])
    m.vertices[:, :2] = m.vertices[:, :2] @ rot.T + centre
    corners = np.array([[-depth / 2, -frontage / 2], [depth / 2, -frontage / 2], [depth / 2, frontage / 2],
                        [-depth / 2, frontage / 2]]) @ rot.T + centre
    return m, corners


def vehicle_mesh(rng, kind: str, instance: int, color) -> tuple[TriangleMesh, np.ndarray]:
    """A car, van or truck in its actor frame (x forward, footprint centre at the origin)."""
    if kind == "car":
        l, w, hb = rng.uniform(4.0, 4.9), rng.uniform(1.7, 1.95), rng.uniform(0.55, 0.75)
        cab_h = rng.uniform(0.45, 0.6)
        lab = L["car"]
    elif kind == "van":
        l, w, hb, cab_h = rng.uniform(4.8, 5.6), rng.uniform(1.9, 2.1), rng.uniform(1.2, 1.5), rng.uniform(0.4, 0.6)
        lab = L["car"]
    else:
        l, w, hb, cab_h = rng.uniform(7.0, 10.0), rng.uniform(2.3, 2.5), rng.uniform(2.2, 2.8), 0.0
        lab = L["truck"]
    r = 0.33 if kind != "truck" else 0.48
    z_body = 2 * r * 0.8
    parts = [pr.box([0, 0, z_body + hb / 2 - 0.1], [l, w, hb], label=lab, color=color, instance=instance)]
    if kind == "truck":
        parts.append(pr.box([l / 2 - 1.1, 0, z_body + 1.1], [2.0, w, 2.2], label=lab,
                            color=_color_jitter(rng, (0.8, 0.8, 0.8)), instance=instance))
        parts[0] = pr.box([-1.1, 0, z_body + hb / 2], [l - 2.3, w, hb], label=lab, color=color, instance=instance)
    if cab_h > 0:
        parts.append(pr.box([-0.15 * l, 0, z_body + hb - 0.1 + cab_h / 2], [0.5 * l, w * 0.88, cab_h], label=lab,
                            color=(0.12, 0.15, 0.2), instance=instance))
    for x in (-0.32 * l, 0.32 * l):
        for y in (-w / 2 + 0.12, w / 2 - 0.12):
            parts.append(pr.cylinder([x, y - 0.12, r], r, 0.24, segments=10, axis="y", label=lab,
                                     color=(0.05, 0.05, 0.05), instance=instance))
    m = TriangleMesh.concatenate(parts)
    height = float(m.vertices[:, 2].max())
    return m, np.array([l, w, height])


def _pedestrian_mesh(rng, instance: int) -> tuple[TriangleMesh, np.ndarray]:
    h = rng.uniform(1.55, 1.9)
    lab = L["pedestrian"]
    shirt = _color_jitter(rng, rng.choice([[0.7, 0.2, 0.2], [0.2, 0.3, 0.7], [0.85, 0.85, 0.8], [0.2, 0.5, 0.3]]))
    parts = [
        pr.cylinder([0, 0, 0], 0.16, h * 0.48, segments=8, label=lab, color=(0.2, 0.2, 0.3), instance=instance),
        pr.cylinder([0, 0, h * 0.48], 0.2, h * 0.38, segments=8, label=lab, color=shirt, instance=instance),
        pr.icosphere([0, 0, h * 0.92], h * 0.08, label=lab, color=(0.8, 0.65, 0.5), instance=instance),
    ]
    return TriangleMesh.concatenate(parts), np.array([0.5, 0.5, h])


def _tree(rng, ids, xy, z0, big=True) -> TriangleMesh:
    inst = ids()
    h = rng.uniform(5.0, 9.0) if big else rng.uniform(3.0, 5.0)
    crown = rng.uniform(1.5, 2.8) if big else rng.uniform(1.0, 1.6)
    trunk = pr.cylinder([xy[0], xy[1], z0], rng.uniform(0.12, 0.25), h - crown, segments=8, label=L["tree_trunk"],
                        color=_color_jitter(rng, (0.35, 0.26, 0.17), 0.04), instance=inst)
    green = _color_jitter(rng, (0.22, 0.42, 0.16), 0.06)
    parts = [trunk, pr.icosphere([xy[0], xy[1], z0 + h - crown * 0.7], crown, subdivisions=1, label=L["vegetation"],
                                 color=green, instance=inst, squash=(1.0, 1.0, rng.uniform(0.75, 1.1)))]
    if rng.random() < 0.5:
        off = rng.uniform(-0.6, 0.6, 2) * crown
        parts.append(pr.icosphere([xy[0] + off[0], xy[1] + off[1], z0 + h - crown * 1.1], crown * 0.7, subdivisions=1,
                                  label=L["vegetation"], color=green, instance=inst))
    return TriangleMesh.concatenate(parts)


def _pole(rng, ids, xy, z0, kind: str) -> TriangleMesh:
    inst = ids()
    grey = (0.45, 0.46, 0.47)
    if kind == "light":
        h = rng.uniform(6.0, 8.0)
        return TriangleMesh.concatenate([
            pr.cylinder([xy[0], xy[1], z0], 0.09, h, segments=8, label=L["pole"], color=grey, instance=inst),
            pr.box([xy[0], xy[1], z0 + h], [0.6, 0.25, 0.15], label=L["pole"], color=grey, instance=inst)])
    if kind == "sign":
        h = rng.uniform(2.2, 2.8)
        colour = rng.choice([[0.85, 0.1, 0.1], [0.1, 0.3, 0.8], [0.9, 0.85, 0.1], [0.95, 0.95, 0.95]])
        return TriangleMesh.concatenate([
            pr.cylinder([xy[0], xy[1], z0], 0.04, h, segments=6, label=L["pole"], color=grey, instance=inst),
            pr.box([xy[0], xy[1], z0 + h + 0.35], [0.05, 0.7, 0.7], yaw=rng.uniform(-0.3, 0.3), label=L["sign"],
                   color=colour, instance=inst)])
    # traffic light: pole with a head
    h = rng.uniform(3.0, 3.8)
    return TriangleMesh.concatenate([
        pr.cylinder([xy[0], xy[1], z0], 0.07, h, segments=8, label=L["pole"], color=grey, instance=inst),
        pr.box([xy[0], xy[1], z0 + h + 0.5], [0.3, 0.35, 1.0], label=L["traffic_light"], color=(0.1, 0.1, 0.1),
               instance=inst)])


# --- world -----------------------------------------------------------------------------------


def _yaw_pose(xy, yaw, z=0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return make_pose(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), [xy[0], xy[1], z])


def _place_along(road: Road, rng, spacing_lo_hi, lateral, margin=0.0):
    """Arc lengths from 0 to the road's length with random spacing."""
    s, out = rng.uniform(0, spacing_lo_hi[1]), []
    while s < road.length - margin:
        out.append(s)
        s += rng.uniform(*spacing_lo_hi)
    return np.array(out)


def generate_world(cfg: WorldConfig) -> World:
    """Build a world from its config; the same config gives the same world, bit for bit.

    Every stage draws from one random generator, in this order; a stage that draws more, less or
    earlier changes every world from that point on (and so every dataset sample)."""
    rng = np.random.default_rng([WORLD_VERSION, STYLES.index(cfg.style), cfg.seed])
    st = _STYLE[cfg.style]
    site = _Site(_make_layout(cfg, st, rng))
    _place_buildings(site, rng, st, cfg.style)
    _place_street_furniture(site, rng, st)
    _place_terrain_objects(site, rng, cfg)
    _lay_ground(site, cfg.length_m)
    boxes_static = _place_parked_vehicles(site, rng, st)
    static = TriangleMesh.concatenate(site.parts)
    ego = _ego_path(site.layout, rng, cfg, st)
    actors = _moving_vehicles(site, rng, cfg, st, ego)
    actors += _pedestrians(site, rng, cfg, st, ego.times)
    sun = _sun_direction(rng)
    return World(cfg, site.layout, static, actors, ego.times, ego.poses, sun, boxes_static)


# --- stages of generate_world -----------------------------------------------------------------


@dataclass
class _Site:
    """What the placement stages share: the layout, the instance-id counter, the static meshes
    placed so far (world frame), building footprints ((4, 2) corners, counter-clockwise) and point
    obstacles ((2,) xy, radius in metres) that later objects keep clear of."""

    layout: Layout
    ids: _Ids = field(default_factory=_Ids)
    parts: list[TriangleMesh] = field(default_factory=list)
    footprints: list[np.ndarray] = field(default_factory=list)
    obstacles: list[tuple[np.ndarray, float]] = field(default_factory=list)

    def free(self, xy, radius) -> bool:
        """Clear of every point obstacle and building footprint by `radius`."""
        if self.obstacles:
            c = np.array([o[0] for o in self.obstacles])
            r = np.array([o[1] for o in self.obstacles])
            if np.any(np.linalg.norm(c - xy, axis=1) <= r + radius):
                return False
        return not any(_polygon_distance(xy, fp) <= radius for fp in self.footprints)

    def clear_of_roads(self, poly, margin) -> bool:
        """Every corner of the polygon and its centroid more than `margin` from every road edge."""
        _, edge = self.layout.classify(np.vstack([poly, poly.mean(0, keepdims=True)]))
        return bool(np.all(edge > margin))


@dataclass
class _EgoPath:
    """The ego's drive: times (T,) s at 10 Hz (from 0, or from -history_s rounded up to the 10 Hz
    grid), arc lengths s (T,) m along the main road, the lateral offset of its lane (m, left
    positive) and poses (T, 4, 4) ego-to-world."""

    times: np.ndarray
    s: np.ndarray
    lane: float
    poses: np.ndarray


def _make_layout(cfg: WorldConfig, st: dict, rng) -> Layout:
    """The road layout: its kind, lanes, lane width, sidewalk and median widths."""
    kind = cfg.layout if cfg.layout != "auto" else str(rng.choice(st["layouts"]))
    lanes = int(rng.integers(st["lanes"][0], st["lanes"][1] + 1))
    return make_layout(kind, rng, length=cfg.length_m, lanes=lanes, lane_width=float(rng.uniform(3.2, 3.7)),
                       sidewalk=_u(rng, st["sidewalk"]), median=_u(rng, st["median"]),
                       parking=2.3 if st["parked"] > 0 else 0.0)


def _place_buildings(site: _Site, rng, st: dict, style: str) -> None:
    """Buildings on both sides of every road (and suburban yards in front of them)."""
    for road in site.layout.roads:
        for side in (-1.0, 1.0):
            s = rng.uniform(0.0, 6.0)
            while s < road.length:
                frontage = _u(rng, st["frontage"])
                depth = _u(rng, st["depth"])
                setback = _u(rng, st["setback"])
                lateral = side * (road.half_width + road.sidewalk + setback + depth / 2)
                p, t = road.at(s + frontage / 2, lateral)
                # The building's local +x (its street facade) faces the road.
                yaw = float(np.arctan2(t[0, 1], t[0, 0]) - side * np.pi / 2)
                height = _u(rng, st["height"])
                poly = _rect(p[0], yaw, depth + 0.4, frontage + 0.4)  # keep 0.2 m between buildings
                if (not any(_convex_overlap(poly, fp) for fp in site.footprints)
                        and site.clear_of_roads(poly, road.sidewalk - 0.05)):
                    m, fp = _building(rng, site.ids, p[0], yaw, frontage, depth, height, style)
                    m.vertices[:, 2] += TERRAIN_HEIGHT - 0.05  # sits slightly into the terrain
                    site.parts.append(m)
                    site.footprints.append(fp)
                    if style == "suburban" and rng.random() < st["fences"]:
                        site.parts += _yard(rng, site.ids, road, s, frontage, side, setback)
                s += frontage + _u(rng, st["gap"])


def _place_street_furniture(site: _Site, rng, st: dict) -> None:
    """Street lights and signs along the sidewalks, sidewalk and median trees, and traffic lights
    at the junction's corners."""
    layout = site.layout
    for road in layout.roads:
        for side in (-1.0, 1.0):
            edge = side * (road.half_width + road.sidewalk - 0.5)
            for s in _place_along(road, rng, (18.0, 30.0), edge):
                p, _ = road.at(s, edge)
                if site.free(p[0], 0.6) and _away_from_junction(layout, p[0], 9.0):
                    site.parts.append(_pole(rng, site.ids, p[0], SIDEWALK_HEIGHT,
                                            "light" if rng.random() < 0.7 else "sign"))
                    site.obstacles.append((p[0], 0.6))
            if st["trees"] > 0:
                tedge = side * (road.half_width + road.sidewalk * 0.6)
                for s in _place_along(road, rng, (7.0, 12.0), tedge):
                    p, _ = road.at(s, tedge)
                    if rng.random() < st["trees"] and site.free(p[0], 1.5) and _away_from_junction(layout, p[0], 10.0):
                        site.parts.append(_tree(rng, site.ids, p[0], SIDEWALK_HEIGHT))
                        site.obstacles.append((p[0], 1.5))
        if road.median > 0:
            for s in _place_along(road, rng, (8.0, 11.0), 0.0):
                p, _ = road.at(s, 0.0)
                if site.free(p[0], 1.0):
                    site.parts.append(_tree(rng, site.ids, p[0], SIDEWALK_HEIGHT, big=rng.random() < 0.7))
                    site.obstacles.append((p[0], 1.0))
    if layout.junction is not None:
        for dx in (-1, 1):
            for dy in (-1, 1):
                cross = layout.roads[1]
                xy = layout.junction + np.array([dx * (cross.half_width + 1.0), dy * (layout.main.half_width + 1.0)])
                site.parts.append(_pole(rng, site.ids, xy, SIDEWALK_HEIGHT, "traffic"))
                site.obstacles.append((xy, 0.5))


def _place_terrain_objects(site: _Site, rng, cfg: WorldConfig) -> None:
    """Trees and bushes on the terrain away from the roads (denser in suburbs)."""
    layout = site.layout
    area_lo, area_hi = _extent(layout, cfg.length_m, 10.0)
    n_free = int((40 if cfg.style == "suburban" else 12) * cfg.length_m / 102.4)
    for _ in range(n_free):
        xy = rng.uniform(area_lo, area_hi)
        _, edge = layout.classify(xy[None])
        if edge[0] > 2.0 and site.free(xy, 2.0) and not any(_inside_polygon(xy[None], fp)[0] for fp in site.footprints):
            if rng.random() < 0.5:
                site.parts.append(_tree(rng, site.ids, xy, TERRAIN_HEIGHT))
            else:
                inst = site.ids()
                site.parts.append(pr.icosphere([xy[0], xy[1], TERRAIN_HEIGHT + 0.4], rng.uniform(0.6, 1.2),
                                               label=L["vegetation"], color=_color_jitter(rng, (0.25, 0.4, 0.15)),
                                               instance=inst, squash=(1, 1, 0.6)))
            site.obstacles.append((xy, 2.0))


def _lay_ground(site: _Site, length: float) -> None:
    """The ground heightfield and lane markings, put first in the static parts. It comes after
    every building because it leaves out the cells under their footprints."""
    (gx0, gy0), (gx1, gy1) = _extent(site.layout, length, 25.0)
    ground = _ground(site.layout, gx0, gx1, gy0, gy1, site.footprints)
    site.parts = [ground] + _lane_markings(site.layout) + site.parts


def _place_parked_vehicles(site: _Site, rng, st: dict) -> list[Box]:
    """Parked vehicles along the curbs (static meshes in `site.parts`); returns their boxes."""
    layout = site.layout
    boxes = []
    for road in layout.roads:
        for side in (-1.0, 1.0):
            lateral = side * (road.half_width - road.parking / 2)
            for s in _place_along(road, rng, (6.0, 14.0), lateral, margin=5.0):
                if rng.random() > st["parked"]:
                    continue
                p, t = road.at(s, lateral)
                if not (site.free(p[0], 2.5) and _away_from_junction(layout, p[0], 14.0)):
                    continue
                inst = site.ids()
                kind_v = "car" if rng.random() < 0.8 else ("van" if rng.random() < 0.7 else "truck")
                m, size = vehicle_mesh(rng, kind_v, inst, _car_color(rng))
                yaw = float(np.arctan2(t[0, 1], t[0, 0])) + (np.pi if side > 0 else 0.0)
                pose = _yaw_pose(p[0], yaw)
                site.parts.append(TriangleMesh(m.vertices @ pose[:3, :3].T + pose[:3, 3], m.faces, m.labels,
                                               m.instances, m.colors))
                boxes.append(Box.on_ground(pose, size, label=int(m.labels[0]), instance=inst, yaw=yaw))
                site.obstacles.append((p[0], 2.5))
    return boxes


def _track_times(cfg: WorldConfig) -> np.ndarray:
    """The 10 Hz instants of the ego path and the actor tracks: from 0 to duration_s, preceded by
    the instants back to -history_s (rounded up to the grid) where a history is asked. The
    instants from 0 are the same numbers with or without a history."""
    times = np.round(np.arange(0.0, cfg.duration_s + 1e-9, 0.1), 6)
    n_back = int(np.ceil(cfg.history_s / 0.1 - 1e-9)) if cfg.history_s > 0 else 0
    if n_back:
        times = np.concatenate([-np.round(np.arange(n_back, 0, -1) * 0.1, 6), times])
    return times


def _ego_path(layout: Layout, rng, cfg: WorldConfig, st: dict) -> _EgoPath:
    """The ego drives the right lane of the main road at constant speed, at x = 0 at t = 0,
    sampled at 10 Hz (before t = 0 too where `history_s` asks: the same lane, the same speed)."""
    speed = cfg.ego_speed_mps if cfg.ego_speed_mps is not None else _u(rng, st["speed"])
    times = _track_times(cfg)
    main = layout.main
    s0 = 20.0  # the ego starts at x = 0, 20 m after the road's start
    lane = -(main.median / 2 + main.lane_width / 2) if main.lanes >= 1 else 0.0
    s = s0 + speed * times
    return _EgoPath(times, s, lane, _poses_along(main, s, lane, 0.0))


def _moving_vehicles(site: _Site, rng, cfg: WorldConfig, st: dict, ego: _EgoPath) -> list[Actor]:
    """Cars and vans driving a lane of a random road at constant speed; tracks at the ego's times.
    A vehicle whose track from t = 0 would leave its road or run through the ego is dropped (only
    from t = 0: a history must not change which vehicles a world has; before 0 a track may run
    past its road's end, continuing straight)."""
    layout = site.layout
    times = ego.times
    ahead = times >= 0
    actors = []
    n_mov = cfg.moving_vehicles if cfg.moving_vehicles is not None else int(rng.integers(st["moving"][0], st["moving"][1] + 1))
    for _ in range(n_mov):
        road = layout.roads[int(rng.integers(len(layout.roads)))]
        direction = rng.choice([-1.0, 1.0])
        k = int(rng.integers(road.lanes))
        lateral = -direction * (road.median / 2 + road.lane_width * (k + 0.5))
        v = rng.uniform(4.0, 13.0)
        s_start = rng.uniform(10.0, max(road.length - 10.0, 11.0))
        s_t = s_start + direction * v * times
        if np.any(s_t[ahead] < 0) or np.any(s_t[ahead] > road.length):
            continue
        if road is layout.main and np.any(np.abs(s_t - ego.s)[ahead] < 10.0) and lateral == ego.lane:
            continue  # not through the ego
        inst = site.ids()
        m, size = vehicle_mesh(rng, "car" if rng.random() < 0.85 else "van", inst, _car_color(rng))
        poses = _poses_along(road, s_t, lateral, 0.0, reverse=direction < 0)
        actors.append(Actor(inst, int(m.labels[0]), m, size, times.copy(), poses))
    return actors


def _pedestrians(site: _Site, rng, cfg: WorldConfig, st: dict, times: np.ndarray) -> list[Actor]:
    """Pedestrians walking along a sidewalk at constant speed (stopping at the road's ends)."""
    layout = site.layout
    actors = []
    n_ped = cfg.pedestrians if cfg.pedestrians is not None else int(rng.integers(st["peds"][0], st["peds"][1] + 1))
    for _ in range(n_ped):
        road = layout.roads[int(rng.integers(len(layout.roads)))]
        side = rng.choice([-1.0, 1.0])
        lateral = side * (road.half_width + road.sidewalk * rng.uniform(0.3, 0.7))
        v = rng.uniform(0.8, 1.6) * rng.choice([-1.0, 1.0])
        s_start = rng.uniform(5.0, max(road.length - 5.0, 6.0))
        s_t = np.clip(s_start + v * times, 0.0, road.length)
        inst = site.ids()
        m, size = _pedestrian_mesh(rng, inst)
        poses = _poses_along(road, s_t, lateral, SIDEWALK_HEIGHT, reverse=v < 0)
        actors.append(Actor(inst, L["pedestrian"], m, size, times.copy(), poses))
    return actors


def _sun_direction(rng) -> np.ndarray:
    """(3,) unit vector towards the sun: random azimuth, 25 to 65 degrees above the horizon."""
    az, el = rng.uniform(0, 2 * np.pi), rng.uniform(np.deg2rad(25), np.deg2rad(65))
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _extent(layout: Layout, length: float, margin: float):
    """The ground rectangle: the roads' bounding box widened to hold a chunk beside the route
    (at least a chunk's half width each side), plus `margin`."""
    pts = np.vstack([r.centerline for r in layout.roads])
    lo, hi = pts.min(0), pts.max(0)
    half = min(length, 102.4) / 2
    # Cover the ego's chunk even where the roads stop short of it (a T junction's main road).
    lo = np.minimum(lo, [-20.0, -half]) - margin
    hi = np.maximum(hi, [min(length, 102.4), half]) + margin
    return lo, hi


def _rect(centre, yaw, depth, frontage) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s], [s, c]])
    return np.array([[-depth / 2, -frontage / 2], [depth / 2, -frontage / 2], [depth / 2, frontage / 2],
                     [-depth / 2, frontage / 2]]) @ rot.T + centre


def _away_from_junction(layout: Layout, xy, dist) -> bool:
    if layout.junction is None:
        return True
    return bool(np.linalg.norm(xy - layout.junction) > dist + layout.main.half_width)


def _car_color(rng):
    return _color_jitter(rng, rng.choice([[0.85, 0.85, 0.85], [0.1, 0.1, 0.1], [0.6, 0.1, 0.1], [0.1, 0.2, 0.5],
                                          [0.5, 0.5, 0.52], [0.75, 0.7, 0.55], [0.2, 0.4, 0.25]]), 0.05)


def _poses_along(road: Road, s: np.ndarray, lateral: float, z: float, reverse: bool = False) -> np.ndarray:
    p, t = road.at(s, lateral)
    yaw = np.arctan2(t[:, 1], t[:, 0]) + (np.pi if reverse else 0.0)
    return np.stack([_yaw_pose(pi, yi, z) for pi, yi in zip(p, yaw)])


def _yard(rng, ids, road: Road, s, frontage, side, setback) -> list[TriangleMesh]:
    """A fence or hedge along the front of a suburban lot."""
    lateral = side * (road.half_width + road.sidewalk + 0.4)
    p0, t = road.at(s, lateral)
    p1, _ = road.at(s + frontage, lateral)
    mid = (p0[0] + p1[0]) / 2
    length = float(np.linalg.norm(p1[0] - p0[0]))
    yaw = float(np.arctan2(t[0, 1], t[0, 0]))
    inst = ids()
    if rng.random() < 0.5:
        return [pr.box([mid[0], mid[1], TERRAIN_HEIGHT + 0.6], [length, 0.08, 1.2], yaw=yaw, label=L["fence"],
                       color=_color_jitter(rng, (0.55, 0.42, 0.3)), instance=inst)]
    return [pr.box([mid[0], mid[1], TERRAIN_HEIGHT + 0.55], [length, 0.8, 1.1], yaw=yaw, label=L["vegetation"],
                   color=_color_jitter(rng, (0.18, 0.35, 0.12)), instance=inst)]
