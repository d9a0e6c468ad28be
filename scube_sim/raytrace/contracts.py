"""The contracts of the tracing layer, written down as Protocols.

- `TraceableScene`: what the LiDAR and camera models trace (a `Tracer`, a list of them through
  `compose.nearest_hits`, the simulator's scene with moving actors).
- `TracerBackend`: an Embree engine over triangles (first hit; optionally every crossing in one
  traversal, declared by `lists_all_hits`).
- `TraceCore`: the traversal of Gaussians, given as `SceneGaussians` with `TraceOptions`
  (`compiled.py`: Embree user geometry with the exact test inside, the default; `reference.py`:
  the NumPy face walk over triangle proxies, the reference the compiled core is tested against).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Protocol, runtime_checkable

import numpy as np

from ..voxsplat import Gaussians, VoxSplat
from .hits import Hits, TraceStats


@runtime_checkable
class TraceableScene(Protocol):
    """Rays in, nearest hits out.

    `trace_world(origins, dirs, t_min, t_max, times=None)`: float64 world-frame origins (N, 3)
    and directions (N, 3), ranges [t_min, t_max] (scalars or (N,), metres); `times` (N,) absolute
    fire times in seconds, used only where `accepts_times` is True (moving parts)."""

    accepts_times: bool

    def trace_world(self, origins, dirs, t_min=0.0, t_max=np.inf, *args, **kwargs) -> Hits: ...


@runtime_checkable
class BoundedScene(Protocol):
    """A scene with a known extent: `origin` (3,) float64 world, `bounds` (lo, hi) local frame."""

    origin: np.ndarray

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]: ...


class TracerBackend(Protocol):
    """An Embree engine over one triangle mesh, BVH built at construction (float32, mesh frame)."""

    name: str
    num_faces: int
    lists_all_hits: bool  # True: `all_hits` lists every crossing in one traversal

    def first_hit(self, origins: np.ndarray, dirs: np.ndarray, t_far: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) float32 origins, unit dirs, (N,) far limits -> t (N,) float32 (inf on a miss),
        prim (N,) int64 (-1 on a miss)."""
        ...

    def all_hits(self, origins: np.ndarray, dirs: np.ndarray,
                 t_far: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Only where `lists_all_hits`: yields (ray index (K,), t (K,) float32, prim (K,))."""
        ...


@dataclass(frozen=True)
class TraceOptions:
    """How one trace call runs (read from the `Tracer` at each call, so its settings may change
    between calls): mode 'entry' | 'max_response' | 'soft'; exact_order False stops a reference
    hard ray at its first exact hit (the compiled core is exact at no cost and ignores it);
    max_iterations caps the casts (reference) or soft re-traversals (compiled) per ray;
    soft_min_transmittance ends a soft ray; soft_alpha_min drops fainter soft contributions;
    soft_hit_alpha: the accumulated alpha a soft ray needs to return; k_buffer: the compiled soft
    mode's contributions per traversal; threads: the compiled core's threads (0: all cores)."""

    mode: str = "entry"
    exact_order: bool = True
    max_iterations: int = 1000
    soft_min_transmittance: float = 1e-3
    soft_alpha_min: float = 1.0 / 255.0
    soft_hit_alpha: float = 0.5
    k_buffer: int = 16
    threads: int = 0


@dataclass
class SceneGaussians:
    """The Gaussians a core builds its acceleration structure over, prepared once by `Tracer`
    (local frame, float64 unless said).

    gaussians: the kept Gaussians (|scales| floored); rot (G, 3, 3) rotations; mu (G, 3) means;
    a (G, 3, 3) world-to-unit-frame matrices (gaussian_math); opacity (G,); k sigma; labels (G,)
    int16; colors (G, 3) float32; voxel (G,) int64 (-1: none); flat_axis (G, 3) unit axis of least
    spread (max-response normals); aabb_lo / aabb_hi (G, 3) k-sigma boxes; pad (m): the float32
    slack rays need against bounds; voxsplat: the source VoxSplat, if any (voxel-box proxies)."""

    gaussians: Gaussians
    rot: np.ndarray
    mu: np.ndarray
    a: np.ndarray
    opacity: np.ndarray
    k: float
    labels: np.ndarray
    colors: np.ndarray
    voxel: np.ndarray
    flat_axis: np.ndarray
    aabb_lo: np.ndarray
    aabb_hi: np.ndarray
    pad: float
    voxsplat: VoxSplat | None = None


class PreparedScene(Protocol):
    """A core's built scene: `lo`, `hi` (3,) float64 corners of what it searches (local frame)."""

    lo: np.ndarray
    hi: np.ndarray


class TraceCore(Protocol):
    """The traversal of Gaussians: `prepare` builds once per scene, `trace` answers ray batches.

    trace: o, d (N, 3) float64 local frame (d unit); tmin, tmax (N,) the asked range; t_lo, t_hi
    (N,) the part of it inside the prepared bounds (empty: t_lo > t_hi). Returns the nearest hit
    per ray (hard modes) or the composited one (soft) as `Hits`, points in the local frame."""

    name: str

    def prepare(self, scene: SceneGaussians) -> PreparedScene: ...

    def trace(self, prepared: PreparedScene, opts: TraceOptions, o, d, tmin, tmax, t_lo, t_hi,
              stats: TraceStats) -> Hits: ...
