"""`Tracer`: ray tracing of VoxSplats (hard or soft opacity) and triangle meshes with Embree.

Gaussians are handed, once per static scene, to a `TraceCore` that builds its BVH and answers
ray batches with exact float64 tests: the compiled core (`compiled.py`, Embree user geometry, one
traversal per ray, the default wherever it is built) or the NumPy reference walk over triangle
proxies (`reference.py`). This class validates rays and hands them to the core (which searches
only inside its padded bounds); meshes are traced here with Embree's own triangles.

Depth definitions (`HardMode`, alpha := 1 for Gaussians at or above `opacity_floor`; `SoftMode`):
- ``entry``: where the ray enters the k-sigma ellipsoid (a solid surface).
- ``max_response``: the point of maximum Gaussian response along the ray (3DGRT), the chord
  midpoint of the same ellipsoid.
- ``soft``: front-to-back compositing of every Gaussian the ray meets, each with its own
  opacity times its peak response along the ray (``alpha_i = o_i exp(-d2_i / 2)``), ordered by
  their max-response points, until the transmittance falls below `min_transmittance`.
  The range is the composited (alpha-weighted, normalised) depth; the ray returns if the
  accumulated alpha reaches `hit_alpha`. For splat files trained without a scaffold.

Frames: rays and hit points are in the scene's local frame (world = local + `origin`); use
`trace_world` to pass float64 world coordinates. Ranges are metres for unit directions.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..mesh import TriangleMesh
from ..voxsplat import Gaussians, VoxSplat
from . import compiled
from .backends import MeshEngine, make_backend
from .contracts import MODES, HardMode, SceneGaussians, SoftMode, TraceCore, trace_mode
from .hits import Hits, TraceStats
from .reference import ReferenceCore

__all__ = ["MODES", "HardMode", "MeshEngine", "SoftMode", "Tracer"]

MIN_SCALE = 1e-9  # metres


def _row_max(a: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N,) the largest of each row: `a.max(axis=1)`'s values, column by column (a
    reduction over a length-3 axis pays per row; this pays per column)."""
    return np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])


def _make_core(core: str | TraceCore | None) -> TraceCore:
    if core is None:
        core = compiled.default_core_name()
    if core == "compiled":
        return compiled.CompiledCore()
    if core == "reference":
        return ReferenceCore()
    if isinstance(core, str):
        raise InputError(f"core: expected 'compiled', 'reference' or a TraceCore, got {core!r}")
    return core


class Tracer:
    """Build once per static scene, then `trace` any number of ray batches (a `TraceableScene`).

    scene: a VoxSplat, a `Gaussians` set (e.g. from a 3DGS PLY) or a TriangleMesh.
    mode: what a Gaussian trace computes, a `HardMode` or `SoftMode` (or a mode's name for its
    defaults; ignored for meshes). The scene keeps the Gaussians at or above the mode's
    `opacity_floor`, built for its `k`; `mode` may later be set to another mode (or name), read
    at each call: the kept Gaussians and their k stay those of the build.
    core: the engine. For Gaussians a `TraceCore`: `compiled.CompiledCore(threads, k_buffer)`,
    `ReferenceCore(backend, proxy, exact_order)`, or the name 'compiled' | 'reference' for its
    defaults; default `compiled.default_core_name()` (the compiled core where it is built; the
    environment variable SCUBE_SIM_CORE overrides). For a mesh a `MeshEngine(backend, threads)`.
    labels: (N,) per-Gaussian labels for a bare `Gaussians` scene.
    A VoxSplat's `reflectance` channel (measured reflectance per Gaussian) is copied into each
    hit's `reflectance` (NaN where the scene has none); the attribute `reflectance` holds it per
    kept Gaussian ((G,) float32, None without the channel; set None to trace without it).
    A converted VoxSplat's ``observed`` and ``confidence`` channels (per voxel) go into each hit's
    `observed` and `confidence` the same way; `provenance` holds them ((V,) uint8, (V,) float32,
    or None: the scene inferred nothing) and `has_provenance` says whether there are any.
    """

    accepts_times = False  # a static scene: per-ray fire times change nothing

    def __init__(
        self,
        scene: VoxSplat | Gaussians | TriangleMesh,
        mode: str | HardMode | SoftMode = "entry",
        *,
        core: str | TraceCore | MeshEngine | None = None,
        labels: np.ndarray | None = None,
    ):
        self.mode = trace_mode(mode)
        self.stats = TraceStats()
        self.is_mesh = isinstance(scene, TriangleMesh)
        if self.is_mesh:
            if core is not None and not isinstance(core, MeshEngine):
                raise InputError(f"core: a mesh is traced by a MeshEngine(backend, threads), got {core!r}")
            self.core = core or MeshEngine()
            self._build_mesh(scene)
        else:
            if isinstance(core, MeshEngine):
                raise InputError("core: a MeshEngine traces meshes; Gaussians need 'compiled', 'reference' "
                                 "or a TraceCore")
            self.core = _make_core(core)
            self._build_gaussians(scene, labels)

    @property
    def core_name(self) -> str:
        return self.core.name

    # --- build -------------------------------------------------------------------------------
    def _build_mesh(self, mesh: TriangleMesh) -> None:
        self.origin = mesh.origin.copy()
        self.mesh = mesh
        self.reflectance = None
        self.provenance = None
        self._face_normals = mesh.face_normals()
        self._face_offset = np.einsum("ij,ij->i", self._face_normals, mesh.vertices[mesh.faces[:, 0]])
        v = mesh.vertices
        self._set_tolerances(np.abs(v).max() if v.size else 0.0)
        self._set_bounds(v.min(0) if v.size else np.zeros(3), v.max(0) if v.size else np.zeros(3))
        self.num_primitives = mesh.num_faces
        self._backend = make_backend(self.core.backend, mesh.vertices.astype(np.float32), mesh.faces)

    def _build_gaussians(self, scene, labels) -> None:
        refl = None
        self.provenance = None
        mode = self.mode
        floor = mode.opacity_floor
        if isinstance(scene, VoxSplat):
            scene.check_finite()
            # The Gaussians at or above the floor, gathered once from the raw slots: fresh arrays
            # this tracer owns (no subset copy, and the scales below are fixed in place).
            g = scene.gaussians(min_opacity=floor)
            g_labels = scene.labels[g.voxel] if len(g) else np.zeros(0, np.int16)
            self.num_voxels = scene.num_voxels
            if "reflectance" in scene.channels:
                refl = scene.channel("reflectance")[g.voxel, g.slot].astype(np.float32)  # gaussians() order
            if "observed" in scene.channels and "confidence" in scene.channels:
                self.provenance = (np.asarray(scene.channel("observed"), np.uint8),
                                   np.asarray(scene.channel("confidence"), np.float32))
            keep, owned = slice(None), True
        else:
            g = scene
            g.check_finite()
            g_labels = (np.zeros(len(g), np.int16) if labels is None
                        else np.asarray(labels, np.int16).reshape(len(g)))
            self.num_voxels = 0
            keep = g.opacities >= floor
            owned = not keep.all()
            # never change the caller's Gaussians: a mask subset copies; otherwise new attributes
            g = g.subset(keep) if owned else g.subset(slice(None))
        self.origin = g.origin.copy()
        # A zero scale is a flat (2D) Gaussian and a negative one means the same spread: keep the
        # result defined by using |s|, floored where float64 still inverts it.
        if owned:
            np.maximum(np.abs(g.scales, out=g.scales), MIN_SCALE, out=g.scales)
        else:
            g.scales = np.maximum(np.abs(g.scales), MIN_SCALE)
        self.gaussians = g
        self.labels = g_labels[keep]
        self.reflectance = refl  # VoxSplats only: already per kept Gaussian
        n = len(g)
        # The float32 tolerance follows the scene's extent, bounded per Gaussian by |mean| + k
        # times its largest scale (no rotation needed; a larger bound only widens the margins).
        extent = float(np.max(_row_max(np.abs(g.means)) + mode.k * _row_max(g.scales))) if n else 0.0
        self._set_tolerances(extent)
        self.scene_gaussians = SceneGaussians(
            gaussians=g, k=mode.k, labels=self.labels, colors=g.colors,
            voxel=g.voxel if g.voxel is not None else np.full(n, -1, np.int64), pad=self._pad,
            voxsplat=scene if isinstance(scene, VoxSplat) else None,
            soft_alpha_min=mode.alpha_min if isinstance(mode, SoftMode) else None)
        self.prepared = self.core.prepare(self.scene_gaussians)
        self._lo, self._hi = self.prepared.lo, self.prepared.hi
        self.num_primitives = int(getattr(self.prepared, "num_faces", n))

    def _set_tolerances(self, extent: float) -> None:
        """float32 tolerances for a scene reaching `extent` metres from the local origin.

        Rays are clipped to the scene bounds in float64 before they are handed to Embree in
        float32, so a float32 ray is never further from the scene than its extent: its rounding
        (origin and direction, ~1.2e-7 relative) stays below a few ulps of the extent wherever it
        meets a proxy. Proxies grow by `_pad` to absorb that."""
        self.extent = float(extent)
        eps32 = float(np.finfo(np.float32).eps)
        self._pad = 8.0 * eps32 * self.extent + 1e-12

    def _set_bounds(self, lo: np.ndarray, hi: np.ndarray) -> None:
        self._lo = np.asarray(lo, np.float64) - 2.0 * self._pad
        self._hi = np.asarray(hi, np.float64) + 2.0 * self._pad

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) (3,) float64 corners of the searched box, local frame (world = local + `origin`)."""
        return self._lo, self._hi

    # --- queries -----------------------------------------------------------------------------
    def trace_world(self, origins, dirs, t_min=0.0, t_max=np.inf) -> Hits:
        """Like `trace` with float64 world-frame origins; hit points stay in the local frame."""
        return self.trace(np.asarray(origins, np.float64) - self.origin, dirs, t_min, t_max)

    def trace(self, origins, dirs, t_min=0.0, t_max=np.inf) -> Hits:
        """origins (N, 3) local frame, dirs (N, 3) (normalised here), t_min / t_max scalars or (N,).
        Returns the nearest hit with t in [t_min, t_max] per ray."""
        o = np.asarray(origins, np.float64).reshape(-1, 3)
        d = np.asarray(dirs, np.float64).reshape(-1, 3)
        n = o.shape[0]
        if d.shape[0] != n:
            raise InputError(f"origins ({n}) and dirs ({d.shape[0]}) differ in length")
        if not (np.all(np.isfinite(o)) and np.all(np.isfinite(d))):
            raise InputError("trace: ray origins or directions contain NaN or Inf")
        norm = np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]  # linalg.norm's result at a third of its time
        if np.any(norm == 0):
            raise InputError("trace: a ray direction has zero length")
        d = d / norm
        tmin = np.broadcast_to(np.asarray(t_min, np.float64), (n,)).copy()
        tmax = np.broadcast_to(np.asarray(t_max, np.float64), (n,)).copy()
        if np.any(np.isnan(tmin)) or np.any(np.isnan(tmax)):
            raise InputError("trace: t_min / t_max contain NaN")
        if self.is_mesh:
            return self._trace_mesh(o, d, tmin, tmax)
        # The mode is read now: it may change between calls.
        out = self.core.trace(self.prepared, trace_mode(self.mode), o, d, tmin, tmax, self.stats)
        if self.reflectance is not None:
            on = out.hit & (out.gaussian >= 0)
            out.reflectance[on] = self.reflectance[out.gaussian[on]]
        if self.provenance is not None:
            on = out.hit & (out.voxel >= 0)
            out.observed[on] = self.provenance[0][out.voxel[on]]
            out.confidence[on] = self.provenance[1][out.voxel[on]]
        return out

    @property
    def has_provenance(self) -> bool:
        """Whether hits can carry an inferred surface's observed / confidence (module docstring)."""
        return self.provenance is not None

    # --- meshes ------------------------------------------------------------------------------
    def _trace_mesh(self, o, d, tmin, tmax) -> Hits:
        n = o.shape[0]
        out = Hits.empty(n)
        start = o + tmin[:, None] * d
        t32, prim = self._backend.first_hit(start.astype(np.float32), d.astype(np.float32),
                                            (tmax - tmin).astype(np.float32), threads=self.core.threads)
        self.stats.casts += 1
        self.stats.rays_cast += n
        idx = np.nonzero(prim >= 0)[0]
        f = prim[idx]
        # Refine the float32 hit in float64 on the triangle's plane.
        nrm = self._face_normals[f]
        di, oi = d[idx], o[idx]
        denom = nrm[:, 0] * di[:, 0] + nrm[:, 1] * di[:, 1] + nrm[:, 2] * di[:, 2]
        num = self._face_offset[f] - (nrm[:, 0] * oi[:, 0] + nrm[:, 1] * oi[:, 1] + nrm[:, 2] * oi[:, 2])
        ok = np.abs(denom) > 1e-12
        t = np.where(ok, num / np.where(ok, denom, 1.0), tmin[idx] + t32[idx])
        valid = (t >= tmin[idx] - 1e-9) & (t <= tmax[idx])
        idx, f, t, nrm, denom = idx[valid], f[valid], np.maximum(t[valid], tmin[idx[valid]]), nrm[valid], denom[valid]
        out.hit[idx] = True
        out.t[idx] = t
        out.points[idx] = o[idx] + t[:, None] * d[idx]
        out.normals[idx] = np.where(denom[:, None] > 0, -nrm, nrm)
        out.face[idx] = f
        out.label[idx] = self.mesh.labels[f]
        out.instance[idx] = self.mesh.instances[f]
        out.color[idx] = self.mesh.colors[f] if self.mesh.colors is not None else 0.5
        out.alpha[idx] = 1.0
        return out
