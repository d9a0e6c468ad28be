"""Procedural albedo per semantic class, evaluated at surface points (world frame).

Images need texture the converter can learn from: asphalt grain, paving joints, facade windows,
grass and foliage noise, bark, planks. Every pattern is a deterministic function of the world
position, the surface normal, the class and the face's base colour, so the camera renders and the
ground-truth VoxSplat colours agree. Colours are sRGB in [0, 1].
"""

from __future__ import annotations

import numpy as np

from ..labels import label_id

_ROAD, _MARK, _SIDEWALK, _CURB = label_id("road"), label_id("lane_marker"), label_id("sidewalk"), label_id("curb")
_TERRAIN, _BUILDING, _VEG, _TRUNK = label_id("terrain"), label_id("building"), label_id("vegetation"), label_id("tree_trunk")
_FENCE, _CAR, _TRUCK = label_id("fence"), label_id("car"), label_id("truck")


def _hash(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Integer lattice -> uniform [0, 1) values (a 32-bit integer hash)."""
    h = (ix.astype(np.int64) * 374761393 + iy.astype(np.int64) * 668265263 + seed * 2147483647) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).astype(np.float64) / float(1 << 24)


def value_noise(x: np.ndarray, y: np.ndarray, scale: float, seed: int = 0) -> np.ndarray:
    """Smooth noise in [0, 1] with features about `scale` metres across."""
    u, v = x / scale, y / scale
    i, j = np.floor(u), np.floor(v)
    fu, fv = u - i, v - j
    fu, fv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    a, b = _hash(i, j, seed), _hash(i + 1, j, seed)
    c, d = _hash(i, j + 1, seed), _hash(i + 1, j + 1, seed)
    return (a * (1 - fu) + b * fu) * (1 - fv) + (c * (1 - fu) + d * fu) * fv


def fbm(x, y, scale, octaves=3, seed=0):
    """Fractal noise in [0, 1]: `octaves` layers of value noise, each half the size."""
    total, amp, norm = 0.0, 1.0, 0.0
    for k in range(octaves):
        total = total + amp * value_noise(x, y, scale / 2**k, seed + 17 * k)
        norm += amp
        amp *= 0.5
    return total / norm


def _surface_uv(p: np.ndarray, n: np.ndarray):
    """2D coordinates on the surface: (x, y) on ground-like faces, (along-wall, z) on walls."""
    wall = np.abs(n[:, 2]) < 0.5
    t = np.stack([-n[:, 1], n[:, 0]], 1)
    tn = np.linalg.norm(t, axis=1, keepdims=True)
    t = np.divide(t, tn, out=np.zeros_like(t), where=tn > 0)
    along = t[:, 0] * p[:, 0] + t[:, 1] * p[:, 1]
    return np.where(wall, along, p[:, 0]), np.where(wall, p[:, 2], p[:, 1]), wall


def albedo(points: np.ndarray, normals: np.ndarray, labels: np.ndarray, base: np.ndarray,
           instances: np.ndarray) -> np.ndarray:
    """(N, 3) points and normals (world), (N,) labels and instance ids, (N, 3) face base colours
    -> (N, 3) float32 sRGB albedo."""
    p = np.asarray(points, np.float64)
    n = np.asarray(normals, np.float64)
    lab = np.asarray(labels)
    col = np.asarray(base, np.float64).copy()
    if len(p) == 0:
        return col.astype(np.float32)
    u, v, wall = _surface_uv(p, n)
    x, y = p[:, 0], p[:, 1]

    m = lab == _ROAD
    if m.any():
        grain = 0.8 + 0.35 * fbm(x[m], y[m], 2.0, 3, 1) + 0.12 * (_hash(np.floor(x[m] * 20), np.floor(y[m] * 20), 2) - 0.5)
        col[m] *= grain[:, None]
    m = lab == _MARK
    if m.any():
        col[m] *= (0.85 + 0.15 * value_noise(x[m], y[m], 0.3, 3))[:, None]
    m = lab == _SIDEWALK
    if m.any():
        tile = 0.6
        ju = np.abs(((x[m] / tile) % 1.0) - 0.5) > 0.46
        jv = np.abs(((y[m] / tile) % 1.0) - 0.5) > 0.46
        shade = 0.9 + 0.15 * _hash(np.floor(x[m] / tile), np.floor(y[m] / tile), 4) + 0.1 * fbm(x[m], y[m], 1.5, 2, 5)
        col[m] *= np.where(ju | jv, 0.6, shade)[:, None]
    m = lab == _CURB
    if m.any():
        col[m] *= (0.9 + 0.1 * value_noise(u[m], v[m], 0.4, 6))[:, None]
    m = lab == _TERRAIN
    if m.any():
        g = fbm(x[m], y[m], 3.0, 3, 7)
        dirt = value_noise(x[m], y[m], 7.0, 8) > 0.72
        c = col[m] * (0.7 + 0.6 * g)[:, None]
        c[dirt] = np.array([0.45, 0.36, 0.25]) * (0.8 + 0.4 * g[dirt])[:, None]
        col[m] = c
    m = (lab == _BUILDING)
    if m.any():
        col[m] = _facade(u[m], v[m], wall[m], col[m], instances[m], x[m], y[m])
    m = lab == _VEG
    if m.any():
        leaf = fbm(u[m] * 1.0, v[m] * 1.0 + 13.0 * instances[m], 0.5, 3, 9)
        col[m] *= (0.55 + 0.8 * leaf)[:, None]
    m = lab == _TRUNK
    if m.any():
        ang = np.arctan2(n[m, 1], n[m, 0])
        col[m] *= (0.7 + 0.5 * value_noise(ang * 3.0, p[m, 2] * 0.3, 0.25, 10))[:, None]
    m = lab == _FENCE
    if m.any():
        plank = (np.floor(u[m] / 0.15) % 2) == 0
        col[m] *= np.where(plank, 1.0, 0.8)[:, None] * (0.9 + 0.2 * value_noise(u[m], v[m], 0.5, 11))[:, None]
    m = (lab == _CAR) | (lab == _TRUCK)
    if m.any():
        col[m] *= (0.92 + 0.08 * value_noise(u[m], v[m], 0.8, 12))[:, None]
    return np.clip(col, 0.0, 1.0).astype(np.float32)


def _facade(u, v, wall, base, inst, x, y):
    """Walls: storeys of windows (dark glass with a light frame), a ground floor with larger shop
    windows; roofs: gravel. Window layout varies per building (instance id)."""
    out = base.copy()
    storey = 3.2 + 0.4 * _hash(inst, inst * 7, 13)
    pitch = 2.4 + 1.2 * _hash(inst, inst * 3, 14)
    wwidth = pitch * (0.45 + 0.2 * _hash(inst, inst * 5, 15))
    fu = (u % pitch) / pitch
    fz = (v % storey) / storey
    floor_no = np.floor(v / storey)
    in_win = (np.abs(fu - 0.5) < 0.5 * wwidth / pitch) & (fz > 0.3) & (fz < 0.85) & (floor_no >= 1)
    shop = (floor_no < 1) & (v > 0.5) & (v < 2.6) & (np.abs(fu - 0.5) < 0.42)
    lit = _hash(np.floor(u / pitch) + 1000 * inst, floor_no, 16)
    glass = np.stack([0.18 + 0.25 * lit, 0.22 + 0.25 * lit, 0.28 + 0.3 * lit], 1)
    brick = out * (0.85 + 0.25 * value_noise(u, v, 0.6, 17))[:, None]
    res = np.where((wall & (in_win | shop))[:, None], glass, brick)
    roof = ~wall
    res[roof] = base[roof] * (0.6 + 0.4 * value_noise(x[roof], y[roof], 0.4, 18))[:, None]
    return res
