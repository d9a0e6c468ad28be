"""The contracts of the tracing layer, written down as Protocols.

- `TraceableScene`: what the LiDAR and camera models trace (a `Tracer`, a list of them through
  `compose.nearest_hits`, the simulator's scene with moving actors).
- `TracerBackend`: an Embree engine over triangles (first hit; optionally every crossing in one
  traversal, declared by `lists_all_hits`).
- `TraceCore`: the traversal of Gaussians, given as `SceneGaussians`, in a `HardMode` or `SoftMode`
  (`compiled.py`: Embree user geometry with the exact test inside, the default; `reference.py`:
  the NumPy face walk over triangle proxies, the reference the compiled core is tested against).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Iterator, Protocol, runtime_checkable

import numpy as np

from ..errors import InputError
from ..voxsplat import Gaussians, VoxSplat
from . import gaussian_math as gm
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


MODES = ("entry", "max_response", "soft")


def _check_k(k: float) -> None:
    if not (np.isfinite(k) and k > 0):
        raise InputError(f"k: expected a positive number of standard deviations, got {k}")


@dataclass(frozen=True)
class HardMode:
    """A hard-opacity trace: each Gaussian at or above `opacity_floor` is a solid k-sigma
    ellipsoid (alpha 1), the rest are dropped when the scene is built.

    name: 'entry' (where the ray enters the ellipsoid: a solid surface) | 'max_response' (the
    point of maximum response along the ray, 3DGRT's depth: the chord midpoint); k: the
    ellipsoid's size in standard deviations."""

    name: str = "entry"
    k: float = 3.0
    opacity_floor: float = 0.05

    def __post_init__(self):
        if self.name not in ("entry", "max_response"):
            raise InputError(f"mode: expected one of {MODES}, got {self.name!r}")
        _check_k(self.k)


@dataclass(frozen=True)
class SoftMode:
    """A soft-opacity trace: front-to-back compositing of every Gaussian the ray meets, each with
    alpha = opacity * exp(-d2 / 2) at its peak along the ray, until the transmittance falls below
    `min_transmittance`; contributions fainter than `alpha_min` are dropped (and the scene keeps
    no Gaussian below it). The range is the alpha-weighted depth; the ray returns where the
    accumulated alpha reaches `hit_alpha`. For splat files trained without a scaffold."""

    k: float = 3.0
    min_transmittance: float = 1e-3
    alpha_min: float = 1.0 / 255.0
    hit_alpha: float = 0.5
    name: str = field(default="soft", init=False)

    def __post_init__(self):
        _check_k(self.k)
        if not 0.0 <= float(self.alpha_min) < 1.0:
            raise InputError(f"soft_alpha_min: expected a value in [0, 1), got {self.alpha_min}")
        if not 0.0 < float(self.min_transmittance) <= 1.0:
            raise InputError(f"soft_min_transmittance: expected a value in (0, 1], got {self.min_transmittance}")

    @property
    def opacity_floor(self) -> float:
        """The opacity below which a Gaussian is left out of the scene: `alpha_min`."""
        return self.alpha_min


TraceMode = HardMode | SoftMode


def trace_mode(mode: str | HardMode | SoftMode) -> HardMode | SoftMode:
    """A mode's options: a name ('entry' | 'max_response' | 'soft') gives its defaults."""
    if isinstance(mode, (HardMode, SoftMode)):
        return mode
    if mode == "soft":
        return SoftMode()
    if isinstance(mode, str) and mode in MODES:
        return HardMode(mode)
    raise InputError(f"mode: expected one of {MODES} or a HardMode / SoftMode, got {mode!r}")


@dataclass
class SceneGaussians:
    """The Gaussians a core builds its acceleration structure over, prepared once by `Tracer`
    (local frame, float64 unless said).

    gaussians: the kept Gaussians (|scales| floored); k sigma; labels (G,) int16; colors (G, 3)
    float32; voxel (G,) int64 (-1: none); pad (m): the float32 slack rays need against bounds;
    voxsplat: the source VoxSplat, if any (voxel-box proxies); soft_alpha_min: set when the
    scene is built for soft mode: a core may then bound each Gaussian by where its response
    reaches this alpha (it must still answer a hard mode exactly). The derived arrays (rot, a,
    flat_axis, aabb_lo / aabb_hi) are computed on first use: the compiled core derives its own in
    C++ and never asks for them."""

    gaussians: Gaussians
    k: float
    labels: np.ndarray
    colors: np.ndarray
    voxel: np.ndarray
    pad: float
    voxsplat: VoxSplat | None = None
    soft_alpha_min: float | None = None

    @property
    def mu(self) -> np.ndarray:
        """(G, 3) means."""
        return self.gaussians.means

    @property
    def opacity(self) -> np.ndarray:
        return self.gaussians.opacities

    @cached_property
    def rot(self) -> np.ndarray:
        """(G, 3, 3) rotations."""
        return self.gaussians.rotations()

    @cached_property
    def a(self) -> np.ndarray:
        """(G, 3, 3) world-to-unit-frame matrices (gaussian_math)."""
        return gm.unit_frame_matrices(self.rot, self.gaussians.scales)

    @cached_property
    def flat_axis(self) -> np.ndarray:
        """(G, 3) unit axis of least spread (the max-response normal)."""
        n = len(self.gaussians)
        return self.rot[np.arange(n), :, np.argmin(self.gaussians.scales, axis=1)] if n else np.zeros((0, 3))

    @cached_property
    def _aabbs(self) -> tuple[np.ndarray, np.ndarray]:
        if not len(self.gaussians):
            return np.zeros((0, 3)), np.zeros((0, 3))
        return gm.gaussian_aabbs(self.mu, self.rot, self.gaussians.scales, self.k)

    @property
    def aabb_lo(self) -> np.ndarray:
        """(G, 3) lower corners of the k-sigma boxes."""
        return self._aabbs[0]

    @property
    def aabb_hi(self) -> np.ndarray:
        return self._aabbs[1]


class PreparedScene(Protocol):
    """A core's built scene: `lo`, `hi` (3,) float64 corners of the box it searches (local frame,
    padded so that a ray clipped to it never starts inside a primitive it cannot then leave)."""

    lo: np.ndarray
    hi: np.ndarray


class TraceCore(Protocol):
    """The traversal of Gaussians: `prepare` builds once per scene, `trace` answers ray batches.

    trace: o, d (N, 3) float64 local frame (d unit); tmin, tmax (N,) the asked range (the core
    searches only its part inside `prepared.lo / hi`; exact tests use the whole range). Returns
    the nearest hit per ray (hard modes) or the composited one (soft) as `Hits`, points in the
    local frame."""

    name: str

    def prepare(self, scene: SceneGaussians) -> PreparedScene: ...

    def trace(self, prepared: PreparedScene, mode: TraceMode, o, d, tmin, tmax, stats: TraceStats) -> Hits: ...
