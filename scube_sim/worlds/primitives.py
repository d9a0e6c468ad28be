"""Closed triangle-mesh primitives with a semantic label, an instance id and an albedo.

All faces wind counter-clockwise seen from outside (outward normals by the right-hand rule).
Positions are metres in the scene's local frame (z up).
"""

from __future__ import annotations

import numpy as np

from ..mesh import TriangleMesh
from ..raytrace.gaussian_math import _ICO_F, _ICO_V

_BOX_V = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
_BOX_F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                   [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _mesh(v, f, label, color, instance) -> TriangleMesh:
    nf = len(f)
    return TriangleMesh(v, f, np.full(nf, label, np.int16), np.full(nf, instance, np.int32),
                        np.tile(np.asarray(color, np.float32), (nf, 1)))


def box(center, size, *, yaw: float = 0.0, label: int = 0, color=(0.5, 0.5, 0.5), instance: int = 0) -> TriangleMesh:
    """A box of `size` (length x, width y, height z) centred at `center`, turned by `yaw` rad."""
    v = (_BOX_V * np.asarray(size, np.float64)) @ _rot_z(yaw).T + np.asarray(center, np.float64)
    # _BOX_F is wound for the template's outward normals (checked in tests).
    return _mesh(v, _BOX_F, label, color, instance)


def cylinder(base, radius: float, height: float, *, segments: int = 12, label: int = 0,
             color=(0.5, 0.5, 0.5), instance: int = 0, axis: str = "z") -> TriangleMesh:
    """A closed prism approximating a cylinder standing on `base` (axis z), or lying along x/y."""
    a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], 1)
    bottom = np.c_[ring, np.zeros(segments)]
    top = np.c_[ring, np.full(segments, height)]
    v = np.vstack([bottom, top, [[0, 0, 0], [0, 0, height]]])
    i = np.arange(segments)
    j = (i + 1) % segments
    side = np.vstack([np.c_[i, j, j + segments], np.c_[i, j + segments, i + segments]])
    cb, ct = 2 * segments, 2 * segments + 1
    caps = np.vstack([np.c_[np.full(segments, cb), j, i], np.c_[np.full(segments, ct), i + segments, j + segments]])
    f = np.vstack([side, caps])
    if axis == "x":
        v = v @ np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], np.float64).T
    elif axis == "y":
        v = v @ np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], np.float64).T
    return _mesh(v + np.asarray(base, np.float64), f, label, color, instance)


def icosphere(center, radius, *, subdivisions: int = 1, label: int = 0, color=(0.5, 0.5, 0.5),
              instance: int = 0, squash=(1.0, 1.0, 1.0)) -> TriangleMesh:
    """A subdivided icosahedron (an ellipsoid with `squash` per-axis factors)."""
    v, f = _ICO_V.copy(), _ICO_F.copy()
    for _ in range(subdivisions):
        edges = {}
        new_f = []
        verts = list(v)

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in edges:
                m = (verts[a] + verts[b]) / 2
                verts.append(m / np.linalg.norm(m))
                edges[key] = len(verts) - 1
            return edges[key]

        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new_f += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        v, f = np.array(verts), np.array(new_f)
    v = v * radius * np.asarray(squash, np.float64) + np.asarray(center, np.float64)
    return _mesh(v, f, label, color, instance)


def quad(corners, *, label: int = 0, color=(0.5, 0.5, 0.5), instance: int = 0) -> TriangleMesh:
    """A planar quad from 4 corners in counter-clockwise order seen from its front side."""
    return _mesh(np.asarray(corners, np.float64), np.array([[0, 1, 2], [0, 2, 3]]), label, color, instance)


def ground_grid(x0, y0, x1, y1, z, cell: float, *, label: int, color, instance: int = 0) -> TriangleMesh:
    """A flat, upward-facing rectangle split into cells (so per-face textures can vary)."""
    nx = max(1, int(round((x1 - x0) / cell)))
    ny = max(1, int(round((y1 - y0) / cell)))
    xs = np.linspace(x0, x1, nx + 1)
    ys = np.linspace(y0, y1, ny + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    v = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, z)]
    idx = np.arange((nx + 1) * (ny + 1)).reshape(nx + 1, ny + 1)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.vstack([np.c_[a, b, c], np.c_[a, c, d]])
    return _mesh(v, f, label, color, instance)
