"""Triangle meshes with per-face semantics: the procedural worlds, baselines and proxies."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import InputError


@dataclass
class TriangleMesh:
    """vertices (V, 3) float64 metres in the local frame of `origin` (float64, world);
    faces (F, 3) int32; labels (F,) int16 label ids; instances (F,) int32 (0 = static scene);
    colors (F, 3) float32 albedo in [0, 1] or None."""

    vertices: np.ndarray
    faces: np.ndarray
    labels: np.ndarray | None = None
    instances: np.ndarray | None = None
    colors: np.ndarray | None = None
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, np.int32).reshape(-1, 3)
        f = self.faces.shape[0]
        self.labels = np.zeros(f, np.int16) if self.labels is None else np.asarray(self.labels, np.int16).reshape(f)
        self.instances = (np.zeros(f, np.int32) if self.instances is None
                          else np.asarray(self.instances, np.int32).reshape(f))
        if self.colors is not None:
            self.colors = np.asarray(self.colors, np.float32).reshape(f, 3)
        self.origin = np.asarray(self.origin, np.float64).reshape(3)
        if not np.all(np.isfinite(self.vertices)):
            raise InputError("TriangleMesh: vertices contain NaN or Inf")
        if f and (self.faces.min() < 0 or self.faces.max() >= self.vertices.shape[0]):
            raise InputError("TriangleMesh: a face indexes a vertex that does not exist")

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def triangles(self) -> np.ndarray:
        """(F, 3, 3) float64 corner positions."""
        return self.vertices[self.faces]

    def face_normals(self) -> np.ndarray:
        """(F, 3) float64 unit normals (right-hand rule); zero for degenerate faces."""
        t = self.triangles()
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        ln = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)

    def face_areas(self) -> np.ndarray:
        t = self.triangles()
        return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)

    @staticmethod
    def concatenate(meshes: list["TriangleMesh"]) -> "TriangleMesh":
        """Join meshes that share an origin (the first one's)."""
        if not meshes:
            return TriangleMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32))
        origin = meshes[0].origin
        verts, faces, labels, inst, cols = [], [], [], [], []
        base = 0
        any_color = any(m.colors is not None for m in meshes)
        for m in meshes:
            verts.append(m.vertices + (m.origin - origin))
            faces.append(m.faces + base)
            base += m.vertices.shape[0]
            labels.append(m.labels)
            inst.append(m.instances)
            if any_color:
                cols.append(m.colors if m.colors is not None else np.full((m.num_faces, 3), 0.5, np.float32))
        return TriangleMesh(np.concatenate(verts), np.concatenate(faces), np.concatenate(labels),
                            np.concatenate(inst), np.concatenate(cols) if any_color else None, origin)

    def distance(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 3) world-frame points -> (N,) float64 metres to the nearest point of the surface
        (open3d's RaycastingScene; float32 inside, in the mesh's local frame)."""
        import open3d as o3d

        p = np.asarray(points_world, np.float64).reshape(-1, 3) - self.origin
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                            o3d.core.Tensor(self.faces.astype(np.uint32)))
        return scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy().astype(np.float64)

    def sample_surface_grid(self, spacing: float) -> dict[str, np.ndarray]:
        """Deterministic, stratified surface samples: each triangle is cut into n x n similar
        sub-triangles (n = ceil(longest edge / spacing)) and sampled at their centroids.

        Unlike random sampling, the samples' first and second moments match the surface's area
        moments closely, which is what a Gaussian fit needs. Returns the dict of
        `sample_surface` plus weights (N,) float64: the area (m^2) each sample stands for, and
        patch_cov (F, 6): the covariance (xx, xy, xz, yy, yz, zz) of the sub-triangle a sample of
        face f stands for (the face's covariance / n^2; uniform on a triangle it is
        1/12 sum (v_i - c)(v_i - c)^T)."""
        tri = self.triangles()
        edges = np.stack([np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1),
                          np.linalg.norm(tri[:, 2] - tri[:, 1], axis=1),
                          np.linalg.norm(tri[:, 0] - tri[:, 2], axis=1)], 1).max(1)
        nsub = np.maximum(1, np.ceil(edges / spacing)).astype(np.int64)
        areas = self.face_areas()
        pts, faces, wts = [], [], []
        for n in np.unique(nsub):
            sel = np.nonzero(nsub == n)[0]
            # Barycentric centroids of the n^2 sub-triangles (upright and inverted ones).
            i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
            up = (i + j) <= n - 1
            bu = np.stack([(i[up] + 1 / 3) / n, (j[up] + 1 / 3) / n], 1)
            dn = (i + j) <= n - 2
            bd = np.stack([(i[dn] + 2 / 3) / n, (j[dn] + 2 / 3) / n], 1)
            bary = np.vstack([bu, bd])  # (n^2, 2): weights of corners 1 and 2
            t = tri[sel]
            p = (t[:, None, 0] + bary[None, :, 0:1] * (t[:, None, 1] - t[:, None, 0])
                 + bary[None, :, 1:2] * (t[:, None, 2] - t[:, None, 0]))
            pts.append(p.reshape(-1, 3))
            faces.append(np.repeat(sel, bary.shape[0]))
            wts.append(np.repeat(areas[sel] / (n * n), bary.shape[0]))
        c = tri.mean(axis=1, keepdims=True)
        dv = tri - c
        cov = np.einsum("fvi,fvj->fij", dv, dv) / 12.0 / (nsub.astype(np.float64) ** 2)[:, None, None]
        patch_cov = np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 1], cov[:, 1, 2], cov[:, 2, 2]], 1)
        if not pts:
            return dict(points=np.zeros((0, 3)), normals=np.zeros((0, 3)), face=np.zeros(0, np.int64),
                        labels=np.zeros(0, np.int16), colors=np.zeros((0, 3), np.float32), weights=np.zeros(0),
                        patch_cov=patch_cov)
        face = np.concatenate(faces)
        colors = (self.colors[face] if self.colors is not None
                  else np.full((face.shape[0], 3), 0.5, np.float32))
        return dict(points=np.concatenate(pts), normals=self.face_normals()[face], face=face,
                    labels=self.labels[face], colors=colors, weights=np.concatenate(wts), patch_cov=patch_cov)

    def sample_surface(self, density: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
        """Area-uniform surface samples: about `density` points per square metre.

        Returns dict with points (N, 3) float64 local, normals (N, 3), face (N,) int64,
        labels (N,) int16, colors (N, 3) float32 (grey when the mesh has none)."""
        areas = self.face_areas()
        expected = areas * density
        # Stratified count per face keeps small faces (poles, signs) represented deterministically.
        counts = np.floor(expected).astype(np.int64)
        counts += rng.random(counts.shape[0]) < (expected - counts)
        face = np.repeat(np.arange(self.num_faces), counts)
        t = self.triangles()[face]
        u, v = rng.random((2, face.shape[0]))
        flip = u + v > 1
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        pts = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
        colors = (self.colors[face] if self.colors is not None
                  else np.full((face.shape[0], 3), 0.5, np.float32))
        return dict(points=pts, normals=self.face_normals()[face], face=face,
                    labels=self.labels[face], colors=colors)
