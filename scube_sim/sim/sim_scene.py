"""The simulated world: static parts built once, rigid actors traced as instances, chunks loaded
by distance.

Instancing without rebuilding: every part has its own `Tracer`, built once in the part's own
frame. A ray is moved into that frame (the inverse of the part's pose), traced there, and its hit
moved back: rigid motions keep ray lengths, so ranges are unchanged. Actors move by changing their
pose, per tick or per ray (a LiDAR's rays fire at different times: the actor is where it is at
each ray's fire time, so motion distortion applies to actors too). Rays are culled per part by a
bounding sphere first, so an actor costs only the rays that come near it.

`SimScene` is the simulator's `SimulatedScene`; `StaticScene` makes a bare `Tracer` (or a list of
them) one without touching its rays.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..boxes import Box
from ..mesh import TriangleMesh
from ..raytrace.compose import nearest_hits
from ..raytrace.contracts import TraceableScene
from ..raytrace.hits import Hits
from ..raytrace.tracer import Tracer
from ..transforms import PoseFn
from ..voxsplat import VoxSplat
from .contracts import SimulatedScene


def _bounding_sphere(tracer: Tracer) -> tuple[np.ndarray, float]:
    """Centre (the frame the tracer traces in: its local frame + origin) and radius (metres) of
    the tracer's bounds."""
    lo, hi = tracer.bounds
    return 0.5 * (lo + hi) + tracer.origin, float(0.5 * np.linalg.norm(hi - lo))


@dataclass
class Part:
    """One traced piece of the world: a tracer in its own frame and where that frame is.

    pose: fixed part-to-world (4, 4), or None for identity; pose_fn: times -> poses for moving
    parts (overrides `pose`). instance / label / size / name: for boxes of actors (size (3,)
    l w h metres in the part frame, the footprint's centre at the part's origin)."""

    tracer: Tracer
    pose: np.ndarray | None = None
    pose_fn: PoseFn | None = None
    instance: int = 0
    label: int = 0
    size: np.ndarray | None = None
    name: str = ""
    _sphere: tuple = field(default=None, init=False, repr=False)

    @property
    def moving(self) -> bool:
        return self.pose_fn is not None

    def sphere(self) -> tuple[np.ndarray, float]:
        """Bounding sphere (centre (3,) in the part frame, radius m) of the part's geometry."""
        if self._sphere is None:
            self._sphere = _bounding_sphere(self.tracer)
        return self._sphere

    def poses_at(self, times: np.ndarray) -> np.ndarray:
        if self.pose_fn is not None:
            return np.asarray(self.pose_fn(np.atleast_1d(times)), np.float64)
        p = np.eye(4) if self.pose is None else self.pose
        return np.broadcast_to(p, (np.atleast_1d(times).shape[0], 4, 4))

    def box_at(self, t: float) -> Box:
        """The part's box at time t (world frame; a zero-size box when `size` is None)."""
        p = self.poses_at(np.array([t]))[0]
        size = np.zeros(3) if self.size is None else self.size
        return Box.on_ground(p, size, label=self.label, instance=self.instance)


class SimScene:
    """Static parts, actors and lazily loaded chunks, traced together (nearest hit wins): a
    `SimulatedScene`.

    `trace_world(o, d, t_min, t_max, times=None)`: float64 world rays; `times` (N,) absolute fire
    times place moving parts per ray (default: `self.time`, the current tick). static_boxes:
    boxes of static objects (e.g. parked cars), reported with the actors' by `boxes_at`."""

    accepts_times = True

    def __init__(self, static: list[Part] | None = None, actors: list[Part] | None = None,
                 chunks: ChunkSet | None = None, static_boxes: list[Box] | None = None):
        self.static = list(static or [])
        self.actors = list(actors or [])
        self.chunks = chunks
        self.static_boxes = list(static_boxes or [])
        self.time = 0.0

    def parts(self) -> list[Part]:
        loaded = self.chunks.loaded_parts() if self.chunks is not None else []
        return self.static + loaded + self.actors

    def update(self, time: float, ego_position: np.ndarray | None = None) -> None:
        """Advance to a tick: the default time for moving parts, and chunk loading around the ego."""
        self.time = float(time)
        if self.chunks is not None and ego_position is not None:
            self.chunks.update(np.asarray(ego_position, np.float64))

    def boxes_at(self, t: float) -> list[Box]:
        """The static boxes, then every actor's box at time t (world frame)."""
        return self.static_boxes + [a.box_at(t) for a in self.actors]

    def trace_world(self, origins, dirs, t_min=0.0, t_max=np.inf, times=None) -> Hits:
        o = np.asarray(origins, np.float64).reshape(-1, 3)
        d = np.asarray(dirs, np.float64).reshape(-1, 3)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        n = o.shape[0]
        tmin = np.broadcast_to(np.asarray(t_min, np.float64), (n,))
        tmax = np.broadcast_to(np.asarray(t_max, np.float64), (n,))
        times = np.full(n, self.time) if times is None else np.asarray(times, np.float64)
        best = Hits.empty(n)
        best.points = np.full((n, 3), np.nan)
        for part in self.parts():
            self._trace_part(part, o, d, tmin, np.minimum(tmax, best.t), times, best)
        return best

    @staticmethod
    def _trace_part(part: Part, o, d, tmin, tmax, times, best: Hits) -> None:
        centre, radius = part.sphere()
        if part.moving:
            t0, t1 = float(times.min()), float(times.max())
            ends = part.poses_at(np.array([t0, t1]))
            c_ends = ends[:, :3, :3] @ centre + ends[:, :3, 3]
            c = c_ends.mean(axis=0)
            r = radius + 0.5 * float(np.linalg.norm(c_ends[1] - c_ends[0]))
        else:
            p = np.eye(4) if part.pose is None else part.pose
            c, r = p[:3, :3] @ centre + p[:3, 3], radius
        # Rays that pass within the sphere before their current limit.
        oc = c - o
        along = np.einsum("ij,ij->i", oc, d)
        perp2 = np.einsum("ij,ij->i", oc, oc) - along**2
        near = (perp2 <= r * r) & (along + r >= tmin) & (along - r <= tmax)
        idx = np.nonzero(near)[0]
        if not idx.size:
            return
        poses = part.poses_at(times[idx]) if part.moving else part.poses_at(np.zeros(1))
        inv_r = np.swapaxes(poses[:, :3, :3], 1, 2)
        if part.moving:
            o_l = np.einsum("nij,nj->ni", inv_r, o[idx] - poses[:, :3, 3])
            d_l = np.einsum("nij,nj->ni", inv_r, d[idx])
        else:
            o_l = (o[idx] - poses[0, :3, 3]) @ poses[0, :3, :3]
            d_l = d[idx] @ poses[0, :3, :3]
        h = part.tracer.trace_world(o_l, d_l, tmin[idx], tmax[idx])
        take = h.hit & (h.t < best.t[idx])
        if not np.any(take):
            return
        sel = idx[take]
        rot = poses[:, :3, :3][take] if part.moving else poses[0, :3, :3]
        best.hit[sel] = True
        best.t[sel] = h.t[take]
        best.points[sel] = o[sel] + h.t[take][:, None] * d[sel]
        nrm = h.normals[take].astype(np.float64)
        best.normals[sel] = (np.einsum("nij,nj->ni", rot, nrm) if part.moving else nrm @ rot.T).astype(np.float32)
        best.gaussian[sel] = h.gaussian[take]
        best.voxel[sel] = h.voxel[take]
        best.face[sel] = h.face[take]
        best.label[sel] = h.label[take]
        best.instance[sel] = np.where(h.instance[take] != 0, h.instance[take], part.instance)
        best.color[sel] = h.color[take]
        best.alpha[sel] = h.alpha[take]
        best.reflectance[sel] = h.reflectance[take]


@dataclass
class ChunkSpec:
    """A VoxSplat chunk on disk and where it sits: chunk_to_world (4, 4) maps the VoxSplat's
    frame (its 'world' = local + origin) into the world."""

    path: Path
    chunk_to_world: np.ndarray
    centre: np.ndarray | None = None  # world, filled from the file on first need
    radius: float | None = None


class ChunkSet:
    """Scenes longer than one chunk: only chunks whose bounds come within `reach` metres of the
    ego are loaded and traced; farther ones are released, so memory follows what the sensors can
    see, not the length of the drive."""

    def __init__(self, chunks: list[ChunkSpec], reach: float, tracer_kw: dict | None = None):
        self.chunks = list(chunks)
        self.reach = float(reach)
        self.tracer_kw = dict(tracer_kw or {})
        self._loaded: dict[int, Part] = {}
        self.loads = 0  # how many times a chunk was built (for tests and reports)

    def _bounds(self, spec: ChunkSpec):
        if spec.centre is None:
            vs = VoxSplat.load(spec.path)
            centres = vs.voxel_centers()
            lo, hi = centres.min(0), centres.max(0)
            c = 0.5 * (lo + hi) + vs.origin
            spec.centre = spec.chunk_to_world[:3, :3] @ c + spec.chunk_to_world[:3, 3]
            spec.radius = float(0.5 * np.linalg.norm(hi - lo) + 3.5 * vs.voxel_size)
        return spec.centre, spec.radius

    def update(self, ego_position: np.ndarray) -> None:
        want = set()
        for i, spec in enumerate(self.chunks):
            c, r = self._bounds(spec)
            if np.linalg.norm(c - ego_position) <= r + self.reach:
                want.add(i)
        for i in list(self._loaded):
            if i not in want:
                del self._loaded[i]
        for i in sorted(want - set(self._loaded)):
            spec = self.chunks[i]
            self._loaded[i] = Part(Tracer(VoxSplat.load(spec.path), **self.tracer_kw), pose=spec.chunk_to_world,
                                   name=spec.path.stem)
            self.loads += 1

    def loaded_parts(self) -> list[Part]:
        return [self._loaded[i] for i in sorted(self._loaded)]

    @property
    def loaded(self) -> list[int]:
        return sorted(self._loaded)


def mesh_part(mesh: TriangleMesh, **kw) -> Part:
    """A part traced on a triangle mesh (its exact geometry); `kw` as for `Part`."""
    return Part(Tracer(mesh), **kw)


class StaticScene:
    """A plain `TraceableScene` (a `Tracer`, any scene with `trace_world`, or a list of tracers:
    nearest hit wins) as a `SimulatedScene`: nothing moves, there are no boxes, `update` only
    keeps the time. Rays go to the wrapped scene as they come (no culling, no re-normalising),
    so the hits are exactly the bare scene's."""

    def __init__(self, scene: TraceableScene | list[Tracer]):
        self.scene = list(scene) if isinstance(scene, (list, tuple)) else scene
        # a list traces through `nearest_hits`, which takes no fire times
        self.accepts_times = False if isinstance(self.scene, list) else bool(self.scene.accepts_times)
        self.time = 0.0

    def update(self, time: float, ego_position: np.ndarray | None = None) -> None:
        self.time = float(time)

    def boxes_at(self, t: float) -> list[Box]:
        return []

    def trace_world(self, origins, dirs, t_min=0.0, t_max=np.inf, times=None) -> Hits:
        if isinstance(self.scene, list):
            return nearest_hits(self.scene, origins, dirs, t_min, t_max)
        if self.accepts_times:
            return self.scene.trace_world(origins, dirs, t_min, t_max, times=times)
        return self.scene.trace_world(origins, dirs, t_min, t_max)


def as_simulated_scene(scene) -> SimulatedScene:
    """`scene` itself when it is a `SimulatedScene` (e.g. a `SimScene`), else a `StaticScene`
    around it (a `TraceableScene` or a list of tracers)."""
    if isinstance(scene, SimulatedScene):
        return scene
    if isinstance(scene, (list, tuple, TraceableScene)):
        return StaticScene(scene)
    raise TypeError(f"scene: expected a SimulatedScene, a TraceableScene (e.g. a Tracer) or a list of tracers, "
                    f"got {type(scene).__name__}")
