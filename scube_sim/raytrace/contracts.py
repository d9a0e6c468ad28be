"""The contracts of the tracing layer, written down as Protocols.

- `TraceableScene`: what the LiDAR and camera models trace (a `Tracer`, a list of them through
  `compose.nearest_hits`, the simulator's scene with moving actors).
- `TracerBackend`: an Embree engine over triangles (first hit; optionally every crossing in one
  traversal, declared by `lists_all_hits`).
- `TraceCore`: the traversal of prepared Gaussians (`reference.py` is the NumPy reference; a
  compiled core implements the same two functions and is tested against it).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Iterator, Protocol, runtime_checkable

import numpy as np

from .hits import Hits, TraceStats

if TYPE_CHECKING:  # annotations only: the prepared scene is built by the tracer
    from .reference import PreparedGaussians, TraceOptions


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


class TraceCore(Protocol):
    """Traversal of prepared Gaussians for rays already clipped to the scene bounds.

    scene: the proxies and Gaussians, built once; opts: this call's mode and walk settings;
    o, d (N, 3) float64 local frame (d unit); tmin, tmax (N,) the asked range; t_lo, t_hi (N,)
    the part of it inside the bounds. Both return per-ray (t (N,) float64, inf on a miss;
    gaussian (N,) int64, -1 on a miss); `trace_soft` also the accumulated alpha (N,)."""

    name: str

    def trace_hard(self, scene: "PreparedGaussians", opts: "TraceOptions", o, d, tmin, tmax, t_lo, t_hi,
                   stats: TraceStats) -> tuple[np.ndarray, np.ndarray]: ...

    def trace_soft(self, scene: "PreparedGaussians", opts: "TraceOptions", o, d, tmin, tmax, t_lo, t_hi,
                   stats: TraceStats) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...
