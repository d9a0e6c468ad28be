"""Embree first-hit queries on triangle meshes, behind one interface (trimesh's ray/ pattern).

Three engines: the compiled core's `MeshScene` (`_core.cpp`: the Embree device, threads and
thread-count knob the Gaussian core uses; honours the far limit in traversal), embreex (Embree 4
through Cython, one thread per call) and open3d's `RaycastingScene` (Embree inside,
multi-threaded). All take float32 rays in the mesh's frame and return the first hit up to a
per-ray limit; `threads` is the compiled engine's thread count (0: the CPUs the process may use,
`compiled.threads_for`; open3d's likewise; embreex has one). The BVH is built once, at construction.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError, ScubeSimError
from . import compiled

BACKENDS = ("open3d", "embreex", "compiled")
# From `make bench` (bench/bench_tracer.py, docs/tracer.md): open3d's multi-threaded Embree sweeps
# faster for every scene size and proxy of the reference walk. Meshes
# themselves go to the compiled core where it is built (`default_mesh_backend`).
DEFAULT_BACKEND = "open3d"


def default_mesh_backend() -> str:
    """The engine a mesh `Tracer` uses when none is named: the compiled core where it is built
    (actors and worlds on the same core as the Gaussians), else `DEFAULT_BACKEND`."""
    return "compiled" if compiled.default_core_name() == "compiled" else DEFAULT_BACKEND


class MeshEngine:
    """How a `Tracer` traces a triangle mesh: Embree's own triangles on `backend` ('open3d' |
    'embreex' | 'compiled'; default `default_mesh_backend()`), with `threads` (0: the CPUs
    the process may use; embreex runs one whatever it says)."""

    name = "mesh"

    def __init__(self, backend: str | None = None, threads: int = 0):
        if backend is not None and backend not in BACKENDS:
            raise InputError(f"backend: expected one of {BACKENDS}, got {backend!r}")
        if int(threads) < 0:
            raise InputError(f"threads: expected 0 (all usable CPUs) or a positive count, got {threads}")
        self.backend = backend or default_mesh_backend()
        self.threads = int(threads)


class BackendUnavailable(ScubeSimError, RuntimeError):
    pass


class EmbreexBackend:
    """embreex: Embree 4, single-threaded per call; honours the per-ray far limit in traversal."""

    name = "embreex"
    lists_all_hits = False

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        try:
            from embreex import mesh_construction, rtcore_scene
        except ImportError as exc:  # pragma: no cover - depends on the install
            raise BackendUnavailable(f"embreex is not importable: {exc}") from None
        self.num_faces = int(faces.shape[0])
        self._scene = rtcore_scene.EmbreeScene()
        if self.num_faces:
            mesh_construction.TriangleMesh(self._scene, np.ascontiguousarray(vertices, np.float32),
                                           np.ascontiguousarray(faces, np.int32))
            # embreex commits the BVH lazily on the first query: build it now, not mid-sweep.
            self._scene.run(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32))

    def first_hit(self, origins: np.ndarray, dirs: np.ndarray, t_far: np.ndarray, threads: int = 0):
        """(N, 3) float32 origins, unit dirs, (N,) far limits -> t (N,) float32 (inf on a miss),
        prim (N,) int64 (-1 on a miss). One thread whatever `threads` says."""
        n = origins.shape[0]
        if n == 0 or self.num_faces == 0:
            return np.full(n, np.inf, np.float32), np.full(n, -1, np.int64)
        far = np.ascontiguousarray(np.minimum(t_far, 3.0e38), np.float32)
        res = self._scene.run(np.ascontiguousarray(origins, np.float32),
                              np.ascontiguousarray(dirs, np.float32), dists=far, output=1)
        prim = res["primID"].astype(np.int64)
        t = np.where(prim >= 0, res["tfar"], np.inf).astype(np.float32)
        return t, prim


class Open3DBackend:
    """open3d RaycastingScene: multi-threaded; no far limit in traversal, so it is applied after."""

    name = "open3d"
    lists_all_hits = True

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, nthreads: int = 0):
        try:
            import open3d as o3d
        except ImportError as exc:  # pragma: no cover - depends on the install
            raise BackendUnavailable(
                f"open3d is not importable ({exc}); on Debian it needs libusb-1.0-0") from None
        self.num_faces = int(faces.shape[0])
        self._nthreads = nthreads
        self._scene = o3d.t.geometry.RaycastingScene()
        if self.num_faces:
            self._scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
                                      o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))
            # The BVH is committed on the first query: build it now.
            self._scene.cast_rays(o3d.core.Tensor(np.array([[0, 0, 0, 0, 0, 1]], np.float32)))
        self._o3d = o3d

    def first_hit(self, origins: np.ndarray, dirs: np.ndarray, t_far: np.ndarray, threads: int = 0):
        n = origins.shape[0]
        if n == 0 or self.num_faces == 0:
            return np.full(n, np.inf, np.float32), np.full(n, -1, np.int64)
        nthreads = compiled.threads_for(threads or self._nthreads)
        res = self._scene.cast_rays(self._o3d.core.Tensor(_o3d_rays(origins, dirs)), nthreads=nthreads)
        t = res["t_hit"].numpy()
        prim = res["primitive_ids"].numpy().astype(np.int64)
        miss = ~np.isfinite(t) | (t > t_far)
        prim[miss] = -1
        t = np.where(miss, np.inf, t).astype(np.float32)
        return t, prim

    def all_hits(self, origins: np.ndarray, dirs: np.ndarray, t_far: np.ndarray, chunk_hits: int = 4_000_000):
        """Every face crossing of every ray up to its far limit, in one traversal per chunk of rays
        (chunked so that at most about `chunk_hits` crossings are held at once).

        Yields (ray index (K,) int64 into the given rays, t (K,) float32, prim (K,) int64)."""
        n = origins.shape[0]
        if n == 0 or self.num_faces == 0:
            return
        rays = _o3d_rays(origins, dirs)
        counts = self._scene.count_intersections(self._o3d.core.Tensor(rays), nthreads=compiled.threads_for(self._nthreads)).numpy()
        csum = np.cumsum(counts.astype(np.int64))
        lo = 0
        while lo < n:
            base = csum[lo - 1] if lo else 0
            hi = max(lo + 1, int(np.searchsorted(csum, base + chunk_hits, side="right")))
            hi = min(hi, n)
            res = self._scene.list_intersections(self._o3d.core.Tensor(rays[lo:hi]),
                                                 nthreads=compiled.threads_for(self._nthreads))
            ray = res["ray_ids"].numpy().astype(np.int64) + lo
            t = res["t_hit"].numpy()
            prim = res["primitive_ids"].numpy().astype(np.int64)
            keep = t <= t_far[ray]
            yield ray[keep], t[keep], prim[keep]
            lo = hi


class CompiledMeshBackend:
    """The compiled core's `MeshScene`: multi-threaded (the same bytes for any thread count);
    honours the per-ray far limit in traversal."""

    name = "compiled"
    lists_all_hits = False

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        if not compiled.available():
            raise BackendUnavailable(f"the compiled tracer core is not built ({compiled.load_error()})")
        self.num_faces = int(faces.shape[0])
        compiled.device()
        self._scene = compiled._core.MeshScene(np.ascontiguousarray(vertices, np.float32),
                                              np.ascontiguousarray(faces, np.int64).reshape(-1, 3))

    def first_hit(self, origins: np.ndarray, dirs: np.ndarray, t_far: np.ndarray, threads: int = 0):
        n = origins.shape[0]
        t, prim = np.empty(n, np.float32), np.empty(n, np.int64)
        self._scene.first_hit(np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(dirs, np.float32),
                              np.ascontiguousarray(t_far, np.float32), t, prim, compiled.threads_for(threads))
        return t, prim


def _o3d_rays(origins, dirs):
    rays = np.empty((origins.shape[0], 6), np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = dirs
    return rays


def make_backend(name: str, vertices: np.ndarray, faces: np.ndarray):
    """Build a backend by name ('open3d', 'embreex' or 'compiled') over a triangle mesh."""
    if name == "open3d":
        return Open3DBackend(vertices, faces)
    if name == "embreex":
        return EmbreexBackend(vertices, faces)
    if name == "compiled":
        return CompiledMeshBackend(vertices, faces)
    raise InputError(f"backend: expected one of {BACKENDS}, got {name!r}")
