"""Exact ray-Gaussian intersection and the bounding proxies that Embree traverses.

A Gaussian (mean mu, rotation R, scales s) at hard opacity is the solid k-sigma ellipsoid
``|A (x - mu)| <= k`` with ``A = S^-1 R^T`` (its "unit frame"). For a ray ``o + t d``:
``o' = A (o - mu)``, ``d' = A d``; the squared Mahalanobis distance along the ray is smallest at
``t* = -(o'.d') / (d'.d')`` (the point of maximum response, 3DGRT), where it equals
``d2 = |o' x d'|^2 / |d'|^2``; the ray meets the ellipsoid iff ``d2 <= k^2``, on the chord
``t* -+ sqrt((k^2 - d2) / |d'|^2)``. This form never subtracts two large squares, so it holds for
scales from 1e-9 to 1e4 m in float64.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

# --- exact test ------------------------------------------------------------------------------


def unit_frame_matrices(rotations: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations and (N, 3) scales (m) -> (N, 3, 3) float64 A = S^-1 R^T."""
    inv_s = 1.0 / np.asarray(scales, np.float64)
    return np.swapaxes(rotations, 1, 2) * inv_s[:, :, None]


def _matvec(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(n, 3, 3) @ (n, 3) -> (n, 3), written out (faster than einsum for 3x3)."""
    return np.stack([
        a[:, 0, 0] * v[:, 0] + a[:, 0, 1] * v[:, 1] + a[:, 0, 2] * v[:, 2],
        a[:, 1, 0] * v[:, 0] + a[:, 1, 1] * v[:, 1] + a[:, 1, 2] * v[:, 2],
        a[:, 2, 0] * v[:, 0] + a[:, 2, 1] * v[:, 1] + a[:, 2, 2] * v[:, 2],
    ], axis=1)


def ray_ellipsoid(origins: np.ndarray, dirs: np.ndarray, means: np.ndarray, a_mats: np.ndarray,
                  k: float):
    """Per (ray, Gaussian) pair, all (n, ...) float64 in one frame.

    Returns (t_star, d2, half_chord): the max-response parameter, the squared Mahalanobis
    distance there, and the half chord length of the k-sigma ellipsoid (NaN-free: 0 on a miss).
    t is in units of |dirs| (metres for unit directions). A miss is d2 > k^2.
    """
    op = _matvec(a_mats, origins - means)
    dp = _matvec(a_mats, dirs)
    aa = np.einsum("ij,ij->i", dp, dp)
    aa = np.maximum(aa, 1e-300)  # a zero direction cannot arise from unit rays; keep it finite
    b = np.einsum("ij,ij->i", op, dp)
    t_star = -b / aa
    cr = np.cross(op, dp)
    d2 = np.einsum("ij,ij->i", cr, cr) / aa
    half = np.sqrt(np.maximum(k * k - d2, 0.0) / aa)
    return t_star, d2, half


def ellipsoid_normals(points: np.ndarray, means: np.ndarray, a_mats: np.ndarray) -> np.ndarray:
    """Outward normals of the ellipsoid level set through `points`: grad = A^T A (x - mu)."""
    up = _matvec(a_mats, points - means)
    g = _matvec(np.swapaxes(a_mats, 1, 2), up)
    n = np.linalg.norm(g, axis=1, keepdims=True)
    return np.divide(g, n, out=np.zeros_like(g), where=n > 0)


def clip_to_box(o: np.ndarray, d: np.ndarray, tmin: np.ndarray, tmax: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Shrink each ray's [tmin, tmax] (N,) to the part inside the box lo, hi (3,) (empty:
    t_lo > t_hi, or NaN). o, d (N, 3) float64. The compiled core does the same in C++."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    # A direction component of 0 gives inf/-inf or NaN (0 * inf): NaN means "inside the slab",
    # and fmax / fmin skip it (nanmax's semantics, column by column: a tenth of its time).
    near_ax, far_ax = np.minimum(t1, t2), np.maximum(t1, t2)
    near = np.fmax(np.fmax(near_ax[:, 0], near_ax[:, 1]), near_ax[:, 2])
    far = np.fmin(np.fmin(far_ax[:, 0], far_ax[:, 1]), far_ax[:, 2])
    return np.maximum(tmin, near), np.minimum(tmax, far)


# --- proxies ---------------------------------------------------------------------------------

# Unit octahedron: contains the unit sphere when scaled by sqrt(3) (face distance a / sqrt 3).
_OCTA_V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
_OCTA_F = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                    [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]], np.int64)
_OCTA_SCALE = np.sqrt(3.0)

_PHI = (1.0 + np.sqrt(5.0)) / 2.0
_ICO_V = np.array([[-1, _PHI, 0], [1, _PHI, 0], [-1, -_PHI, 0], [1, -_PHI, 0],
                   [0, -1, _PHI], [0, 1, _PHI], [0, -1, -_PHI], [0, 1, -_PHI],
                   [_PHI, 0, -1], [_PHI, 0, 1], [-_PHI, 0, -1], [-_PHI, 0, 1]], np.float64)
_ICO_V /= np.linalg.norm(_ICO_V[0])
_ICO_F = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
                   [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
                   [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
                   [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], np.int64)
# Inradius of the unit-circumradius icosahedron: scale by its inverse to contain the unit sphere.
_ICO_SCALE = 1.0 / np.linalg.norm(_ICO_V[_ICO_F].mean(axis=1), axis=1).min()

_BOX_V = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
_BOX_F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                   [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.int64)

PROXY_KINDS = ("octahedron", "icosahedron", "voxel_box")


def template_rotations(index: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(N,) integer ids and (N,) template axes (0, 1, 2) -> (N, 3, 3) rotations about those axes
    by angles that differ between neighbouring ids (a golden-ratio sequence).

    Each per-Gaussian proxy template is turned about its Gaussian's flattest axis (any rotation of
    a template that contains the unit sphere still contains it). Without this, Gaussians fitted on
    a plane share orientation and size, and their proxies' faces lie exactly in common planes: a
    ray then meets several faces at the same distance, and Embree reports only one of them. Turning
    about the flattest axis keeps a flat Gaussian's proxy flat, which keeps the BVH tight."""
    theta = 2 * np.pi * np.mod(np.asarray(index, np.float64) * 0.6180339887498949 + 0.5, 1.0)
    c, s = np.cos(theta), np.sin(theta)
    n = theta.shape[0]
    out = np.zeros((n, 3, 3))
    axis = np.asarray(axis)
    for k in range(3):
        sel = axis == k
        i, j = [m for m in range(3) if m != k]
        out[sel, k, k] = 1.0
        out[sel, i, i] = c[sel]
        out[sel, j, j] = c[sel]
        out[sel, i, j] = -s[sel]
        out[sel, j, i] = s[sel]
    return out


def _template_mesh(template_v, template_f, centers, axes_scaled):
    """Instantiate a template polyhedron per element: v = c + M @ tv.
    axes_scaled: (N, 3, 3) columns are the scaled axes. Returns float32 (N*nv, 3), int32 faces."""
    n = centers.shape[0]
    verts = centers[:, None, :] + np.einsum("nij,vj->nvi", axes_scaled, template_v)
    faces = template_f[None, :, :] + (np.arange(n, dtype=np.int64) * template_v.shape[0])[:, None, None]
    return verts.reshape(-1, 3).astype(np.float32), faces.reshape(-1, 3).astype(np.int32)


def _template(kind: str):
    if kind == "octahedron":
        return _OCTA_V, _OCTA_F, _OCTA_SCALE
    if kind == "icosahedron":
        return _ICO_V, _ICO_F, _ICO_SCALE
    if kind == "voxel_box":
        return _BOX_V, _BOX_F, 1.0
    raise InputError(f"proxy: expected one of {PROXY_KINDS}, got {kind!r}")


def template_planes(kind: str):
    """Outward unit normals (F, 3) and offsets (F,) of a proxy template's faces, in template
    coordinates (where the template's vertices are `tv`): a point y is inside iff y.n <= h."""
    tv, tf, _ = _template(kind)
    t = tv[tf]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    h = np.einsum("ij,ij->i", n, t[:, 0])
    assert np.all(h > 0), "template faces must wind outwards"
    return n, h


def gaussian_proxies(kind: str, means, rotations, scales, k: float, pad: float):
    """Closed convex polyhedra that contain each Gaussian's k-sigma ellipsoid dilated by `pad` m.

    Returns (vertices (P, 3) float32, faces (F, 3) int32, faces_per_proxy, frame_scale (N, 3)).
    The proxy of Gaussian i owns faces [i * fpp, (i + 1) * fpp). Template coordinates of a point
    x are ``Q_i^T (frame_scale * (A (x - mu)))`` with A = S^-1 R^T (`unit_frame_matrices`) and
    Q_i = template_rotations(i, argmin(s_i)). `pad` absorbs float32 rounding of rays and vertices.
    """
    tv, tf, scale = _template(kind)
    s = np.asarray(scales, np.float64)
    semi = k * s + pad
    axes = rotations * (scale * semi)[:, None, :]
    axes = axes @ template_rotations(np.arange(s.shape[0]), np.argmin(s, axis=1))
    v, f = _template_mesh(tv, tf, np.asarray(means, np.float64), axes)
    return v, f, tf.shape[0], s / (scale * semi)


def gaussian_aabbs(means, rotations, scales, k: float):
    """(N, 3) lower and upper corners of each k-sigma ellipsoid's axis-aligned bounding box."""
    half = k * np.sqrt(np.einsum("nij,nj->ni", rotations ** 2, np.asarray(scales, np.float64) ** 2))
    return means - half, means + half


def box_proxies(lo: np.ndarray, hi: np.ndarray, pad):
    """Axis-aligned boxes (N, 3) corners, dilated by pad (scalar or (N,)) ->
    (vertices float32, faces int32, 12)."""
    c = 0.5 * (lo + hi)
    h = 0.5 * (hi - lo) + np.reshape(pad, (-1, 1))
    axes = np.zeros((c.shape[0], 3, 3))
    axes[:, 0, 0], axes[:, 1, 1], axes[:, 2, 2] = h[:, 0], h[:, 1], h[:, 2]
    v, f = _template_mesh(_BOX_V, _BOX_F, c, axes)
    return v, f, _BOX_F.shape[0]
