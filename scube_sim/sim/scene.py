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
from ..raytrace.compose import nearest_hits
from ..raytrace.contracts import HardMode, SoftMode, TraceableScene, trace_mode
from ..raytrace.hits import Hits
from ..raytrace.tracer import Tracer
from ..transforms import PoseFn, check_pose, check_poses
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

    def __post_init__(self):
        if self.pose is not None:
            self.pose = check_pose(self.pose, f"{self._what()}: pose")

    def _what(self) -> str:
        return f"part {self.name!r}" if self.name else f"part (instance {self.instance})"

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
            times = np.atleast_1d(times)
            return check_poses(self.pose_fn(times), f"{self._what()}: pose_fn", times, count=times.shape[0])
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

    @property
    def has_provenance(self) -> bool:
        """Whether a part now in the scene is a converted VoxSplat whose hits carry observed /
        confidence (`Tracer.has_provenance`)."""
        return any(getattr(p.tracer, "has_provenance", False) for p in self.parts())

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
        d = d / np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
        n = o.shape[0]
        tmin = np.broadcast_to(np.asarray(t_min, np.float64), (n,))
        tmax = np.broadcast_to(np.asarray(t_max, np.float64), (n,))
        times = np.full(n, self.time) if times is None else np.asarray(times, np.float64)
        best = Hits.empty(n)
        if n == 0:
            return best
        rays = _RayBatch(o, d, tmin, tmax, times)
        for part in self.parts():
            self._trace_part(part, rays, best)
        # One world point per hit, whichever part it came from: rigid motions keep ranges. All
        # rays at once, then NaN where nothing was hit (t = inf there): no gathers.
        with np.errstate(invalid="ignore"):
            np.add(o, best.t[:, None] * d, out=best.points)
        np.copyto(best.points, np.nan, where=~best.hit[:, None])
        return best

    @staticmethod
    def _trace_part(part: Part, rays: "_RayBatch", best: Hits) -> None:
        """Trace the rays that can reach `part` in its frame and keep its hits nearer than `best`'s."""
        o, d, times = rays.o, rays.d, rays.times
        idx = rays.near(part, best.t)
        if idx is None or not idx.size:
            return
        dense = idx.size == o.shape[0]  # every ray: no gathers, masks instead of index lists
        o_i, d_i = (o, d) if dense else (np.take(o, idx, axis=0), np.take(d, idx, axis=0))
        tmin_i = rays.tmin if dense else rays.tmin[idx]
        best_i = best.t if dense else best.t[idx]
        tmax_i = np.minimum(rays.tmax if dense else rays.tmax[idx], best_i)
        rot = None  # part-to-world rotation: None (identity), (3, 3), or (M, 3, 3) per ray
        if part.moving:
            poses = part.poses_at(times if dense else times[idx])
            rot = poses[:, :3, :3]
            # R^T (o - t), R^T d per ray: einsum "nji" reads R transposed without a copy
            o_l = np.einsum("nji,nj->ni", rot, o_i - poses[:, :3, 3])
            d_l = np.einsum("nji,nj->ni", rot, d_i)
        elif part.pose is not None and not _is_identity(part.pose):
            rot, tr = part.pose[:3, :3], part.pose[:3, 3]
            o_l = np.einsum("ji,nj->ni", rot, o_i - tr)  # einsum, not `@`: no BLAS threads
            d_l = np.einsum("ji,nj->ni", rot, d_i)
        else:  # a part in world coordinates (chunks, the static world): its rays as they are
            o_l, d_l = o_i, d_i
        h = part.tracer.trace_world(o_l, d_l, tmin_i, tmax_i)
        take = h.hit & (h.t < best_i)  # ties keep the earlier part's hit, as the order of parts says
        if not np.any(take):
            return
        nrm = h.normals
        if rot is not None:  # normals back to the world, in float64 as before
            spec = "ij,nj->ni" if rot.ndim == 2 else "nij,nj->ni"
            nrm = np.einsum(spec, rot, nrm.astype(np.float64)).astype(np.float32)
        inst = np.where(h.instance != 0, h.instance, np.int32(part.instance)).astype(best.instance.dtype)
        fields = (("hit", h.hit), ("t", h.t), ("normals", nrm), ("gaussian", h.gaussian), ("voxel", h.voxel),
                  ("face", h.face), ("label", h.label), ("instance", inst), ("color", h.color),
                  ("alpha", h.alpha), ("reflectance", h.reflectance), ("observed", h.observed),
                  ("confidence", h.confidence))
        if dense:  # masked copies over all rays: no index arrays
            for name, src in fields:
                dst = getattr(best, name)
                np.copyto(dst, src, where=take if dst.ndim == 1 else take[:, None])
        else:
            sel = idx[take]
            for name, src in fields:
                getattr(best, name)[sel] = src[take]


def _is_identity(pose: np.ndarray) -> bool:
    return bool(np.array_equal(pose, np.eye(4)))


class _RayBatch:
    """One `SimScene.trace_world` batch: world rays o, d (N, 3) (d unit), tmin, tmax, fire times
    (N,), and what every part's cull shares. `near(part, best_t)` lists the rays that may hit a
    part, in three conservative steps (each keeps every ray the next one would keep):

    1. Blocks: consecutive rays in blocks of `BLOCK` (a LiDAR's rays come in firing order, so a
       block is a narrow fan), each with a cone about its mean direction that holds all its
       directions. A ray that passes near the part is within the part's angular radius of the
       direction to it, so its block's cone is within that plus the cone's half-angle.
    2. Coarse, per ray: the origins lie in a ball (centre `c_o`, radius `r_o`). A ray o + t d that
       passes within r of a sphere's centre c at some t in [tmin, tmax] has a twin from c_o (o's
       ray moved by |o - c_o| <= r_o) that passes within r + r_o of c at a t within r_o of it:
       distances to a line and positions along it change by at most the move. One dot product
       per ray.
    3. Exact, per ray: the old sphere test (`_sphere_test`) with each ray's own origin, on the
       candidates, for moving parts (whose sphere covers the part over the batch's time span) and
       where the origins spread wider than the part. A static part's sphere holds its geometry,
       so a ray kept by step 2 that step 3 would drop misses the part anyway."""

    BLOCK = 128

    def __init__(self, o, d, tmin, tmax, times):
        self.o, self.d, self.tmin, self.tmax, self.times = o, d, tmin, tmax, times
        # per column: a reduction over axis 0 of an (N, 3) array runs several times slower
        lo = np.array([o[:, j].min() for j in range(3)])
        hi = np.array([o[:, j].max() for j in range(3)])
        self.c_o = 0.5 * (lo + hi)
        self.r_o = float(0.5 * np.linalg.norm(hi - lo))
        self.t_span = (float(times.min()), float(times.max()))
        self.tmin_lo = float(tmin.min())
        self.tmax_hi = float(tmax.max())
        self._cones()

    def _cones(self) -> None:
        """Per block of rays: unit axis (B, 3) and half-angle (B,) radians of a cone holding its dirs."""
        n, k = self.d.shape[0], self.BLOCK
        nb = -(-n // k)
        d = self.d if nb * k == n else np.concatenate([self.d, np.repeat(self.d[-1:], nb * k - n, axis=0)])
        d = d.reshape(nb, k, 3)  # the last block padded with copies of the last ray: no wider cone
        axis = np.einsum("nkj->nj", d)  # d.sum(axis=1) at a fraction of its time
        norm = np.sqrt(np.einsum("ij,ij->i", axis, axis))
        flat = norm < 1e-6 * k  # directions that cancel out: no useful axis, a cone of every direction
        axis = axis / np.where(flat, 1.0, norm)[:, None]
        cos_min = np.einsum("nkj,nj->nk", d, axis).min(axis=1)
        self.cone_axis = axis
        self.cone_half = np.where(flat, np.pi, np.arccos(np.clip(cos_min, -1.0, 1.0)))

    def sphere(self, part: Part) -> tuple[np.ndarray, float]:
        """The part's bounding sphere in the world over this batch's time span: centre (3,), radius m."""
        centre, radius = part.sphere()
        if part.moving:
            ends = part.poses_at(np.array(self.t_span))
            c_ends = np.einsum("nij,j->ni", ends[:, :3, :3], centre) + ends[:, :3, 3]
            return c_ends.mean(axis=0), radius + 0.5 * float(np.linalg.norm(c_ends[1] - c_ends[0]))
        if part.pose is None:
            return centre, radius
        return part.pose[:3, :3] @ centre + part.pose[:3, 3], radius

    def near(self, part: Part, best_t: np.ndarray) -> np.ndarray | None:
        """Indices (ascending) of the rays that may hit `part` before their limits; None: none."""
        c, r = self.sphere(part)
        cw = c - self.c_o
        dist = float(np.sqrt(cw @ cw))
        # the coarse radius, padded far beyond float64 rounding of both tests
        big_r = (r + self.r_o) * (1.0 + 1e-9) + 1e-9 * dist + 1e-12
        if dist - big_r > self.tmax_hi or dist + big_r < self.tmin_lo:
            return None  # the part is out of every ray's reach
        n = self.d.shape[0]
        sub = None  # None: every ray
        # Step 1 holds when no ray can pass the part backwards: a ray whose line passes within
        # big_r of c behind its origin then has along <= -sqrt(dist^2 - big_r^2) < -big_r <= tmin - big_r.
        if self.tmin_lo >= 0.0 and dist * dist > 2.0 * big_r * big_r:
            alpha = np.arcsin(big_r / dist)  # the part's angular radius seen from c_o
            ang = np.arccos(np.clip(self.cone_axis @ (cw / dist), -1.0, 1.0))
            blocks = np.nonzero(ang <= alpha + self.cone_half + 1e-6)[0]  # 1e-6 rad: arccos rounding near 1
            if not blocks.size:
                return None
            if blocks.size < self.cone_half.shape[0]:
                sub = (blocks[:, None] * self.BLOCK + np.arange(self.BLOCK)).ravel()
                sub = sub[sub < n]
        d = self.d if sub is None else np.take(self.d, sub, axis=0)
        tmin = self.tmin if sub is None else self.tmin[sub]
        limit = np.minimum(self.tmax, best_t) if sub is None else np.minimum(self.tmax[sub], best_t[sub])
        along = np.einsum("ij,j->i", d, cw)
        keep = along * along >= dist * dist - big_r * big_r  # within big_r of the line ...
        keep &= along + big_r >= tmin  # ... and of the segment [tmin, min(tmax, best)]
        keep &= along - big_r <= limit
        idx = np.nonzero(keep)[0]
        if sub is not None:
            idx = sub[idx]
        if idx.size and (part.moving or self.r_o > r):
            limit = np.minimum(self.tmax[idx], best_t[idx])
            o, d = np.take(self.o, idx, axis=0), np.take(self.d, idx, axis=0)
            idx = idx[_sphere_test(o, d, self.tmin[idx], limit, c, r)]
        return idx


def _sphere_test(o, d, tmin, tmax, c, r) -> np.ndarray:
    """Per ray (N,) bool: the line o + t d (d unit) passes within r of c, at a t within r of
    [tmin, tmax] (a superset of the rays whose segment meets the ball)."""
    oc = c - o
    along = np.einsum("ij,ij->i", oc, d)
    perp2 = np.einsum("ij,ij->i", oc, oc) - along**2
    return (perp2 <= r * r) & (along + r >= tmin) & (along - r <= tmax)


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

    def __init__(self, chunks: list[ChunkSpec], reach: float, mode: str | HardMode | SoftMode = "entry"):
        self.chunks = list(chunks)
        self.reach = float(reach)
        self.mode = trace_mode(mode)  # how every chunk is traced
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
            self._loaded[i] = Part(Tracer(VoxSplat.load(spec.path), self.mode), pose=spec.chunk_to_world,
                                   name=spec.path.stem)
            self.loads += 1

    def loaded_parts(self) -> list[Part]:
        return [self._loaded[i] for i in sorted(self._loaded)]

    @property
    def loaded(self) -> list[int]:
        return sorted(self._loaded)


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
