"""The ground under a scene: a plane (RANSAC) and a height field over it (roads slope, kerbs
step), fitted to measured surface points, filled where nothing was measured.

`fit_ground_plane`: RANSAC over the lower half of the points by height, the plane tilted at most
`max_tilt_deg` from `up`, then a least-squares refit of its inliers (kept only if it does not tilt
beyond the limit: a wall among the inliers). Deterministic for a seed. Real sweeps are split into
ground and above-ground returns by it (`eval depth`, `fidelity --regions`).

`fit_height_field` (frame: z up, the plane roughly horizontal): per cell, the heights of the
points over the plane; a cell's first estimate is a low quantile of those within `search_m` of
the plane (the ground is the lowest surface; cars and walls stand on it), smoothed by the median
of its neighbourhood (a cell under a car sees the car's underside, its neighbours the road); the
final height is the median of the points within `band_m` of that estimate. Cells with at least
`min_points` such points are observed; the others take the mean of their filled neighbours,
ring by ring outwards from the observed ones (a hole between two slopes is bridged, not
flattened to the plane), each ring's height over the plane a step nearer the plane where
`fill_decay_m` is given: past the last measured cells, far stereo's noisiest heights would
otherwise be carried to the chunk's edge, well above a flat road. No cell observed: the plane
itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

__all__ = ["GroundPlane", "HeightField", "RANSAC_INLIER_M", "fit_ground_plane", "fit_height_field",
           "flat_height_field"]

RANSAC_ITERATIONS = 200
RANSAC_INLIER_M = 0.15


@dataclass(frozen=True)
class GroundPlane:
    """A plane through `origin` + `centre` ((3,) each: the points' mean and the plane's centre
    relative to it, so that distances keep their precision far from the frame's origin) with unit
    `normal` (3,) pointing along `up`."""

    origin: np.ndarray
    centre: np.ndarray
    normal: np.ndarray

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) -> (N,) signed distance along the normal, metres."""
        return ((np.asarray(points, np.float64) - self.origin) - self.centre) @ self.normal

    def z_at(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) -> (N,) the plane's z over each point (frame z up)."""
        n, c = self.normal, self.origin + self.centre
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        return c[2] - ((xy[:, 0] - c[0]) * n[0] + (xy[:, 1] - c[1]) * n[1]) / n[2]


def fit_ground_plane(points: np.ndarray, up=(0.0, 0.0, 1.0), *, seed: int = 0, max_tilt_deg: float = 15.0,
                     inlier_m: float = RANSAC_INLIER_M) -> GroundPlane | None:
    """The ground plane of (N, 3) points (module docstring); None when fewer than 3 points or no
    plane within the tilt."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    if len(p) < 3:
        return None
    origin = p.mean(0)
    q = p - origin  # local coordinates: world frames may sit 10^6 m from their origin
    height = q @ up
    cand = q[height <= np.median(height)]
    if len(cand) < 3:
        return None
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(cand), size=(RANSAC_ITERATIONS, 3))
    a, b, c = cand[picks[:, 0]], cand[picks[:, 1]], cand[picks[:, 2]]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    n[ok] /= norm[ok, None]
    n *= np.where(n @ up < 0, -1.0, 1.0)[:, None]
    cos_tilt = math.cos(math.radians(max_tilt_deg))
    ok &= n @ up >= cos_tilt
    if not ok.any():
        return None
    n, a = n[ok], a[ok]
    counts = [(np.abs((cand - a0) @ n0) < inlier_m).sum() for n0, a0 in zip(n, a)]
    k = int(np.argmax(counts))
    inl = cand[np.abs((cand - a[k]) @ n[k]) < inlier_m]
    centre = inl.mean(0)
    normal = np.linalg.svd(inl - centre, full_matrices=False)[2][-1]  # least squares: smallest singular vector
    normal *= 1.0 if normal @ up >= 0 else -1.0
    if normal @ up < cos_tilt:
        normal, centre = n[k], a[k]  # the refit tilted too far (a wall among the inliers): keep the RANSAC plane
    return GroundPlane(origin, centre, normal)


@dataclass
class HeightField:
    """Ground height z (frame z up) on a grid of square cells: cell (i, j) spans x in
    [origin[0] + i cell, + cell), y in [origin[1] + j cell, + cell). heights (nx, ny) float64
    metres at the cell centres; observed (nx, ny) bool (measured, not filled); plane: the plane
    it was fitted over."""

    origin: np.ndarray
    cell: float
    heights: np.ndarray
    observed: np.ndarray
    plane: GroundPlane

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) -> (N,) bilinear between cell centres, the edge cells' heights beyond them."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        nx, ny = self.heights.shape
        f = (xy - self.origin) / self.cell - 0.5
        i0 = np.clip(np.floor(f[:, 0]), 0, nx - 1).astype(np.int64)
        j0 = np.clip(np.floor(f[:, 1]), 0, ny - 1).astype(np.int64)
        i1, j1 = np.minimum(i0 + 1, nx - 1), np.minimum(j0 + 1, ny - 1)
        tx = np.clip(f[:, 0] - i0, 0.0, 1.0)
        ty = np.clip(f[:, 1] - j0, 0.0, 1.0)
        h = self.heights
        return ((1 - tx) * (1 - ty) * h[i0, j0] + tx * (1 - ty) * h[i1, j0]
                + (1 - tx) * ty * h[i0, j1] + tx * ty * h[i1, j1])

    def centres(self) -> np.ndarray:
        """(nx, ny, 2) the cells' centres (x, y)."""
        nx, ny = self.heights.shape
        i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
        return self.origin + (np.stack([i, j], -1) + 0.5) * self.cell


def _cell_stat(cell_id: np.ndarray, values: np.ndarray, n_cells: int, q: float) -> tuple[np.ndarray, np.ndarray]:
    """Per cell the `q` quantile of its values (NaN where it has none) and its count."""
    order = np.lexsort((values, cell_id))
    cid, val = cell_id[order], values[order]
    counts = np.bincount(cid, minlength=n_cells)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    out = np.full(n_cells, np.nan)
    has = counts > 0
    pos = start[has] + np.floor(q * (counts[has] - 1)).astype(np.int64)
    out[has] = val[pos]
    return out, counts


def _neighbourhood_median(grid: np.ndarray, radius: int) -> np.ndarray:
    """(nx, ny) with NaN holes -> the median of the finite values in each (2r+1)^2 window (NaN
    where there are none)."""
    nx, ny = grid.shape
    padded = np.pad(grid, radius, constant_values=np.nan)
    windows = np.stack([padded[di:di + nx, dj:dj + ny] for di in range(2 * radius + 1)
                        for dj in range(2 * radius + 1)], -1)
    out = np.full(grid.shape, np.nan)
    any_finite = np.isfinite(windows).any(-1)
    out[any_finite] = np.nanmedian(windows[any_finite], axis=-1)
    return out


def _fill(grid: np.ndarray, factor: float = 1.0) -> np.ndarray:
    """NaN cells take the mean of their filled 8-neighbours times `factor`, ring by ring outwards
    (factor < 1: each ring a step nearer zero)."""
    g = grid.copy()
    nx, ny = g.shape
    while np.isnan(g).any():
        padded = np.pad(g, 1, constant_values=np.nan)
        nb = np.stack([padded[1 + di:1 + di + nx, 1 + dj:1 + dj + ny] for di in (-1, 0, 1) for dj in (-1, 0, 1)
                       if di or dj], -1)
        cnt = np.isfinite(nb).sum(-1)
        total = np.nansum(nb, -1)
        ring = np.isnan(g) & (cnt > 0)
        if not ring.any():
            break
        g[ring] = factor * total[ring] / cnt[ring]
    return g


def flat_height_field(extent: tuple[float, float, float, float], *, cell: float = 1.0, z: float = 0.0) -> HeightField:
    """A level ground at height `z` over `extent` (xmin, xmax, ymin, ymax) metres, no cell observed:
    the ground where nothing measured one (the road under the ego, frame z up)."""
    xmin, xmax, ymin, ymax = (float(v) for v in extent)
    nx, ny = math.ceil((xmax - xmin) / cell), math.ceil((ymax - ymin) / cell)
    plane = GroundPlane(np.array([0.0, 0.0, float(z)]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    return HeightField(np.array([xmin, ymin]), float(cell), np.full((nx, ny), float(z)), np.zeros((nx, ny), bool),
                       plane)


def fit_height_field(points: np.ndarray, extent: tuple[float, float, float, float], *, cell: float = 1.0,
                     search_m: float = 1.0, band_m: float = 0.2, low_quantile: float = 0.2, smooth_cells: int = 2,
                     min_points: int = 3, seed: int = 0, max_tilt_deg: float = 15.0,
                     fill_decay_m: float | None = None) -> HeightField | None:
    """The ground's height field (module docstring) over `extent` (xmin, xmax, ymin, ymax) metres
    from (N, 3) surface points (frame z up, metres). None when no ground plane is found.
    fill_decay_m: an unobserved cell's height over the plane decays as exp(-d / fill_decay_m) with
    its distance d from the observed cells (None: carried unchanged)."""
    if not (cell > 0 and band_m > 0 and search_m > 0 and 0 <= low_quantile <= 1):
        raise InputError(f"fit_height_field: need cell, band_m, search_m > 0 and low_quantile in [0, 1], got "
                         f"cell={cell}, band_m={band_m}, search_m={search_m}, low_quantile={low_quantile}")
    xmin, xmax, ymin, ymax = (float(v) for v in extent)
    if not (xmax > xmin and ymax > ymin):
        raise InputError(f"fit_height_field: extent {extent}: expected xmin < xmax and ymin < ymax")
    p = np.asarray(points, np.float64).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), 1)]
    plane = fit_ground_plane(p, seed=seed, max_tilt_deg=max_tilt_deg)
    if plane is None:
        return None
    nx, ny = int(math.ceil((xmax - xmin) / cell)), int(math.ceil((ymax - ymin) / cell))
    origin = np.array([xmin, ymin])
    ij = np.floor((p[:, :2] - origin) / cell).astype(np.int64)
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < nx) & (ij[:, 1] >= 0) & (ij[:, 1] < ny)
    p, ij = p[inside], ij[inside]
    dz = p[:, 2] - plane.z_at(p[:, :2])  # height over the plane
    cid = ij[:, 0] * ny + ij[:, 1]
    near = np.abs(dz) <= search_m
    low, _ = _cell_stat(cid[near], dz[near], nx * ny, low_quantile)
    first = _neighbourhood_median(low.reshape(nx, ny), smooth_cells)
    first = _fill(first)
    first = np.where(np.isnan(first), 0.0, first)
    keep = np.abs(dz - first.reshape(-1)[cid]) <= band_m
    med, counts = _cell_stat(cid[keep], dz[keep], nx * ny, 0.5)
    observed = (counts >= min_points).reshape(nx, ny)
    dz_grid = np.where(observed, med.reshape(nx, ny), np.nan)
    factor = 1.0 if fill_decay_m is None else math.exp(-cell / fill_decay_m)
    dz_grid = _fill(dz_grid, factor) if observed.any() else np.zeros((nx, ny))
    field = HeightField(origin, float(cell), np.zeros((nx, ny)), observed, plane)
    base = plane.z_at(field.centres().reshape(-1, 2)).reshape(nx, ny)
    field.heights = base + dz_grid
    return field
