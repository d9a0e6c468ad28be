"""Ground-truth products of a world (the paper's data pipeline, section 4.1).

A *chunk* is a 102.4 m cube in the ego frame at the reference time T: x from -10.24 m (the ego
near the back edge, facing inward) to 92.16 m, y within +-51.2 m, z from -3.23 m to 99.17 m.
Voxel (i, j, k) of a grid with voxel size v spans ``corner + [i, i+1) v`` in the chunk frame
(``corner = CHUNK_CORNER``), and the chunk frame maps to the world by the ego pose at T.

- `voxelize_mesh`: a mesh -> every voxel its surface passes through (conservative scan conversion);
- `voxelize`: surface samples -> occupied voxels with the majority (area-weighted) label;
- `coarsen`: a fine grid -> a coarser one (occupied if any fine voxel is; label by area);
- `mark_visible`: voxels holding a surface point seen by the input cameras (their depth maps);
- `gt_voxsplat`: Gaussians fitted to the surface with albedo colours (`fit.fit_voxsplat`), the
  upper bound of what the converter can produce.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fit import FitOptions, fit_voxsplat
from ..mesh import TriangleMesh
from ..transforms import invert_pose, transform_points
from ..voxsplat import VoxSplat, voxel_keys
from .generator import _poses_along
from .textures import albedo

CHUNK_SIZE = 102.4
# z starts 3.23 m below the ego's ground so that the generated worlds' flat surfaces (road 0 m,
# terrain 0.10 m, sidewalks 0.15 m) lie inside voxels of 0.1 / 0.2 / 0.4 m, not on their faces.
CHUNK_CORNER = np.array([-10.24, -51.2, -3.23])


@dataclass
class VoxelGrid:
    """Occupied voxels of a chunk: ijk (V, 3) int32 (0 <= ijk < CHUNK_SIZE / voxel_size), labels
    (V,) int16, area (V,) float32 surface area inside (m^2), visible (V,) bool or None."""

    ijk: np.ndarray
    labels: np.ndarray
    area: np.ndarray
    voxel_size: float
    visible: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.ijk.shape[0])

    @property
    def dims(self) -> int:
        return int(round(CHUNK_SIZE / self.voxel_size))

    def centers(self) -> np.ndarray:
        """(V, 3) voxel centres in the chunk frame."""
        return CHUNK_CORNER + (self.ijk + 0.5) * self.voxel_size

    def keys(self) -> np.ndarray:
        return voxel_keys(self.ijk)


def chunk_samples(mesh: TriangleMesh, chunk_to_world: np.ndarray, spacing: float, margin: float = 0.0):
    """Stratified surface samples of the faces that reach into the chunk, in the chunk frame.

    Returns the `TriangleMesh.sample_surface_grid` dict (points in the chunk frame; samples
    outside the chunk dropped)."""
    to_chunk = invert_pose(chunk_to_world)
    v = transform_points(to_chunk, mesh.vertices + mesh.origin)
    tri = v[mesh.faces]
    lo, hi = tri.min(1), tri.max(1)
    inside = np.all((hi >= CHUNK_CORNER - margin) & (lo < CHUNK_CORNER + CHUNK_SIZE + margin), axis=1)
    sub = TriangleMesh(v, mesh.faces[inside], mesh.labels[inside], mesh.instances[inside],
                       None if mesh.colors is None else mesh.colors[inside])
    s = sub.sample_surface_grid(spacing)
    keep = np.all((s["points"] >= CHUNK_CORNER) & (s["points"] < CHUNK_CORNER + CHUNK_SIZE), axis=1)
    s = {k: (a if k == "patch_cov" else a[keep]) for k, a in s.items()}  # patch_cov is per face
    s["face"] = np.nonzero(inside)[0][s["face"]]
    s["instances"] = mesh.instances[s["face"]]
    return s


def _majority_grid(key: np.ndarray, labels: np.ndarray, weights: np.ndarray, n: int, voxel_size: float,
                   area_scale: float = 1.0) -> VoxelGrid:
    """Flat voxel keys (i * n + j) * n + k with a label and a weight each -> a VoxelGrid whose
    label per voxel is the one with the most weight (ties: the smaller id)."""
    up, inv = np.unique(key * 64 + labels.astype(np.int64), return_inverse=True)
    w = np.bincount(inv.reshape(-1), weights=weights)
    pkey, plab = up // 64, up % 64
    order = np.lexsort((plab, -w, pkey))
    first = np.r_[True, pkey[order][1:] != pkey[order][:-1]]
    vox, vlab = pkey[order][first], plab[order][first]
    area = np.bincount(np.searchsorted(vox, pkey), weights=w, minlength=len(vox)) * area_scale
    ijk = np.stack([vox // (n * n), (vox // n) % n, vox % n], 1)
    return VoxelGrid(ijk.astype(np.int32), vlab.astype(np.int16), area.astype(np.float32), float(voxel_size))


def voxelize_mesh(mesh: TriangleMesh, chunk_to_world: np.ndarray, voxel_size: float,
                  batch: int = 4_000_000) -> VoxelGrid:
    """Every voxel of the chunk that the mesh's surface passes through.

    Each triangle is scan-converted along its dominant axis a: for every voxel column (in the
    other two axes) whose square overlaps the projected triangle (separating-axis test), the
    a-range of the part of the triangle above that square gives the voxels it crosses. The result
    holds every point of the surface (and a voxel whose face the surface merely touches).
    Area: the surface inside each voxel, from the covered fraction of each column (4 x 4 sub-cell
    centres), shared evenly among the voxels the column's piece crosses. Label: the label with
    the most area in the voxel (ties: smaller id).
    """
    to_chunk = invert_pose(chunk_to_world)
    v = transform_points(to_chunk, mesh.vertices + mesh.origin) - CHUNK_CORNER
    tri_all = v[mesh.faces]
    n = int(round(CHUNK_SIZE / voxel_size))
    inside = np.all((tri_all.max(1) >= 0) & (tri_all.min(1) < CHUNK_SIZE), axis=1)
    tri_all, lab_all = tri_all[inside] / voxel_size, mesh.labels[inside]  # in voxel units
    nrm = np.cross(tri_all[:, 1] - tri_all[:, 0], tri_all[:, 2] - tri_all[:, 0])
    nl = np.linalg.norm(nrm, axis=1)
    good = nl > 1e-12
    tri_all, lab_all, nrm = tri_all[good], lab_all[good], nrm[good] / nl[good, None]
    keys, labs, wts = [], [], []
    for a in range(3):
        u, w = [k for k in range(3) if k != a]
        sel = np.argmax(np.abs(nrm), axis=1) == a
        tri, lab, nr = tri_all[sel], lab_all[sel], nrm[sel]
        if not len(tri):
            continue
        lo = np.clip(np.floor(tri[:, :, [u, w]].min(1)).astype(np.int64), 0, n - 1)
        hi = np.clip(np.floor(tri[:, :, [u, w]].max(1)).astype(np.int64), 0, n - 1)
        cnt = (hi[:, 0] - lo[:, 0] + 1) * (hi[:, 1] - lo[:, 1] + 1)
        ends = np.cumsum(cnt)
        first = 0
        while first < len(tri):
            last = int(np.searchsorted(ends, (ends[first - 1] if first else 0) + batch, side="right"))
            last = max(last, first + 1)
            sl = slice(first, last)
            k = _scan_columns(tri[sl], nr[sl], lo[sl], hi[sl], cnt[sl], a, u, w, n)
            if k is not None:
                col_t, ku, kw, k0, k1, weight = k
                span = k1 - k0 + 1
                rep = np.repeat(np.arange(len(col_t)), span)
                kk = k0[rep] + (np.arange(len(rep)) - np.repeat(np.cumsum(span) - span, span))
                ijk = np.empty((len(rep), 3), np.int64)
                ijk[:, a], ijk[:, u], ijk[:, w] = kk, ku[rep], kw[rep]
                keys.append((ijk[:, 0] * n + ijk[:, 1]) * n + ijk[:, 2])
                labs.append(lab[sl][col_t][rep].astype(np.int64))
                wts.append((weight / span)[rep])
            first = last
    if not keys:
        return VoxelGrid(np.zeros((0, 3), np.int32), np.zeros(0, np.int16), np.zeros(0, np.float32), float(voxel_size))
    return _majority_grid(np.concatenate(keys), np.concatenate(labs), np.concatenate(wts), n, voxel_size,
                          area_scale=voxel_size**2)


_EPS = 1e-9  # voxel units
_SUB = (np.arange(4) + 0.5) / 4  # 4 x 4 sub-cell centres of a column square
_SUB_X, _SUB_Y = np.repeat(_SUB, 4), np.tile(_SUB, 4)


def _edge_functions(q: np.ndarray):
    """2D triangles (T, 3, 2) -> (A, B, C) (T, 3): E_e(x, y) = A x + B y + C is >= 0 inside the
    triangle for each of its three edges (either winding)."""
    p, r = q, np.roll(q, -1, axis=1)
    area2 = ((q[:, 1, 0] - q[:, 0, 0]) * (q[:, 2, 1] - q[:, 0, 1]) - (q[:, 1, 1] - q[:, 0, 1]) * (q[:, 2, 0] - q[:, 0, 0]))
    o = np.where(area2 >= 0, 1.0, -1.0)[:, None]
    a = -o * (r[:, :, 1] - p[:, :, 1])
    b = o * (r[:, :, 0] - p[:, :, 0])
    c = o * ((r[:, :, 1] - p[:, :, 1]) * p[:, :, 0] - (r[:, :, 0] - p[:, :, 0]) * p[:, :, 1])
    return a, b, c


def _partial_columns(q, av, cu, cw, corner_a, corner_in, e0, ea, eb):
    """Columns the triangle covers in part: the a-range over (square & triangle), reached at its
    vertices — square corners inside the triangle, triangle vertices inside the square, crossings
    of the triangle's edges with the square's sides — and the covered fraction of the square
    (4 x 4 sub-cell centres). q (N, 3, 2) projected triangles, av (N, 3) their a coordinates;
    e0, ea, eb (N, 3): edge functions at the square's corner (cu, cw) and their x / y slopes."""
    vals = [np.where(corner_in, corner_a, np.nan)]
    in_sq = ((q[:, :, 0] >= cu[:, None] - _EPS) & (q[:, :, 0] <= cu[:, None] + 1 + _EPS)
             & (q[:, :, 1] >= cw[:, None] - _EPS) & (q[:, :, 1] <= cw[:, None] + 1 + _EPS))
    vals.append(np.where(in_sq, av, np.nan))
    for e in range(3):
        p, r = q[:, e], q[:, (e + 1) % 3]
        ap, ar = av[:, e], av[:, (e + 1) % 3]
        for axis in (0, 1):
            lo_side, lo_other = (cu, cw) if axis == 0 else (cw, cu)
            den = r[:, axis] - p[:, axis]
            has = np.abs(den) > 1e-15
            safe = np.where(has, den, 1.0)
            for side in (lo_side, lo_side + 1):
                s_ = (side - p[:, axis]) / safe
                y = p[:, 1 - axis] + s_ * (r[:, 1 - axis] - p[:, 1 - axis])
                ok = has & (s_ >= -_EPS) & (s_ <= 1 + _EPS) & (y >= lo_other - _EPS) & (y <= lo_other + 1 + _EPS)
                vals.append(np.where(ok, ap + s_ * (ar - ap), np.nan)[:, None])
    allv = np.concatenate(vals, axis=1)
    empty = np.all(np.isnan(allv), axis=1)  # only by rounding: keep the whole square's range
    filled = np.where(empty[:, None], corner_a.mean(1, keepdims=True), allv)
    amin = np.where(empty, corner_a.min(1), np.nanmin(filled, axis=1))
    amax = np.where(empty, corner_a.max(1), np.nanmax(filled, axis=1))
    covered = np.ones((len(cu), _SUB_X.size), bool)
    for e in range(3):
        covered &= (e0[:, e, None] + ea[:, e, None] * _SUB_X + eb[:, e, None] * _SUB_Y) >= -_EPS
    return amin, amax, covered.mean(axis=1)


def _scan_columns(tri, nr, lo, hi, cnt, a, u, w, n):
    """Columns (in voxel units) of a batch of triangles with dominant axis a that overlap each
    projected triangle, with the a-range of the triangle's part above each column square.

    Returns (triangle index, column u, column w, first voxel, last voxel, surface area weight)."""
    t = np.repeat(np.arange(len(tri)), cnt)
    off = np.arange(len(t)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    nu = hi[:, 0] - lo[:, 0] + 1
    cu = lo[t, 0] + off % nu[t]
    cw = lo[t, 1] + off // nu[t]
    p2 = tri[:, :, [u, w]]  # (T, 3, 2)
    fa, fb, fc = _edge_functions(p2)
    ea, eb = fa[t], fb[t]
    e0 = ea * cu[:, None] + eb * cw[:, None] + fc[t]  # (N, 3) at the square's corner (cu, cw)
    # Separating axes: the square lies outside an edge iff all its corners do (the square's own
    # axes are covered by the column range). The highest corner adds the positive slopes.
    keep = np.all(e0 + np.maximum(ea, 0) + np.maximum(eb, 0) >= -_EPS, axis=1)
    t, cu, cw, e0, ea, eb = t[keep], cu[keep], cw[keep], e0[keep], ea[keep], eb[keep]
    if not len(t):
        return None
    nt = nr[t]
    d = np.einsum("ij,ij->i", nt, tri[t, 0])
    na = nt[:, a]
    cx = np.stack([cu, cu + 1, cu, cu + 1], 1).astype(np.float64)
    cy = np.stack([cw, cw, cw + 1, cw + 1], 1).astype(np.float64)
    corner_a = (d[:, None] - nt[:, u, None] * cx - nt[:, w, None] * cy) / na[:, None]
    inside = np.stack([np.all(c >= -_EPS, axis=1) for c in (e0, e0 + ea, e0 + eb, e0 + ea + eb)], 1)  # (N, 4)
    # Columns wholly under the triangle: the range is the corners', the coverage is full.
    amin, amax = corner_a.min(1), corner_a.max(1)
    frac = np.ones(len(t))
    edge = np.nonzero(~inside.all(axis=1))[0]
    if edge.size:
        amin[edge], amax[edge], frac[edge] = _partial_columns(
            p2[t[edge]], tri[t[edge]][:, :, a], cu[edge], cw[edge], corner_a[edge], inside[edge],
            e0[edge], ea[edge], eb[edge])
    av = tri[t][:, :, a]
    amin = np.maximum(amin, av.min(1))
    amax = np.minimum(amax, av.max(1))
    k0 = np.clip(np.floor(amin).astype(np.int64), 0, n - 1)
    k1 = np.clip(np.floor(amax).astype(np.int64), 0, n - 1)
    ok = (amax >= 0) & (amin < n) & (k1 >= k0)
    return t[ok], cu[ok], cw[ok], k0[ok], k1[ok], frac[ok] / np.abs(na[ok])


def voxelize(points: np.ndarray, labels: np.ndarray, weights: np.ndarray, voxel_size: float) -> VoxelGrid:
    """Chunk-frame points -> occupied voxels, label = the label with the most weight (area)."""
    ijk = np.floor((points - CHUNK_CORNER) / voxel_size).astype(np.int64)
    n = int(round(CHUNK_SIZE / voxel_size))
    ok = np.all((ijk >= 0) & (ijk < n), axis=1)
    ijk, labels, weights = ijk[ok], labels[ok], weights[ok]
    key = (ijk[:, 0] * n + ijk[:, 1]) * n + ijk[:, 2]
    return _majority_grid(key, labels, weights, n, voxel_size)


def coarsen(fine: VoxelGrid, factor: int) -> VoxelGrid:
    """A grid `factor` times coarser: occupied where any fine voxel is; label by area; visible
    where any fine voxel is visible."""
    ijk = fine.ijk.astype(np.int64) // factor
    n = fine.dims // factor
    key = (ijk[:, 0] * n + ijk[:, 1]) * n + ijk[:, 2]
    grid = _majority_grid(key, fine.labels, fine.area, n, fine.voxel_size * factor)
    if fine.visible is not None:
        g = grid.ijk.astype(np.int64)
        vox = (g[:, 0] * n + g[:, 1]) * n + g[:, 2]
        grid.visible = np.zeros(len(grid), bool)
        grid.visible[np.searchsorted(vox, key[fine.visible])] = True
    return grid


def mark_visible(grid: VoxelGrid, seen_points: np.ndarray) -> np.ndarray:
    """(V,) bool: voxels containing at least one of the seen surface points (chunk frame)."""
    ijk = np.floor((seen_points - CHUNK_CORNER) / grid.voxel_size).astype(np.int64)
    n = grid.dims
    ok = np.all((ijk >= 0) & (ijk < n), axis=1)
    ijk = ijk[ok]
    seen = np.unique((ijk[:, 0] * n + ijk[:, 1]) * n + ijk[:, 2])
    g = grid.ijk.astype(np.int64)
    key = (g[:, 0] * n + g[:, 1]) * n + g[:, 2]
    return np.isin(key, seen)


def depth_to_points(depth: np.ndarray, intr, cam_to_world: np.ndarray) -> np.ndarray:
    """Back-project a z-depth map (H, W) (inf = nothing) into world points (K, 3)."""
    rays = intr.pixel_rays().reshape(-1, 3)
    z = depth.reshape(-1).astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    p_cam = rays[ok] * (z[ok] / rays[ok, 2])[:, None]
    return transform_points(cam_to_world, p_cam)


def gt_voxsplat(mesh: TriangleMesh, chunk_to_world: np.ndarray, voxel_size: float, *,
                gaussians_per_voxel: int = 4, albedo_fn=None, tile_m: float = 12.8,
                region: tuple | None = None) -> VoxSplat:
    """The ground-truth VoxSplat of a chunk: Gaussians fitted to stratified surface samples (with
    each sample's sub-triangle covariance, so the fit sees the surface's exact second moments)
    and their albedo as colour. Its frame is the chunk frame (origin = CHUNK_CORNER, so voxel ijk
    match `VoxelGrid`); trace it with sensor poses in the chunk frame, inv(chunk_to_world) @
    T_world_sensor (chunk_to_world is kept in its metadata). Built in slabs of `tile_m` along x
    so that memory stays bounded at fine voxel sizes. region: optional (lo (3,), hi (3,)) box in
    the chunk frame to fit only part of the chunk. albedo_fn: as `camera.render.render_camera`'s,
    called with `footprint` (no view); None: the worlds' procedural `textures.albedo` with
    vehicles textured in world coordinates (pass `textures.world_albedo(world, t)` for the
    looks of the cameras' images at t)."""
    albedo_fn = albedo_fn or albedo
    to_chunk = invert_pose(chunk_to_world)
    v = transform_points(to_chunk, mesh.vertices + mesh.origin) - CHUNK_CORNER
    tri = v[mesh.faces]
    box_lo, box_hi = np.zeros(3), np.full(3, CHUNK_SIZE)
    if region is not None:
        box_lo = np.maximum(box_lo, np.asarray(region[0], np.float64) - CHUNK_CORNER)
        box_hi = np.minimum(box_hi, np.asarray(region[1], np.float64) - CHUNK_CORNER)
    near = np.all((tri.max(1) >= box_lo) & (tri.min(1) < box_hi), axis=1)
    tri = np.where(near[:, None, None], tri, np.inf)
    lo_x, hi_x = tri[:, :, 0].min(1), tri[:, :, 0].max(1)
    spacing = voxel_size / 2.0
    tile = max(voxel_size, round(tile_m / voxel_size) * voxel_size)
    parts = []
    for x0 in np.arange(np.floor(box_lo[0] / voxel_size) * voxel_size, box_hi[0], tile):
        sel = (hi_x >= x0) & (lo_x < x0 + tile)
        if not np.any(sel):
            continue
        sub = TriangleMesh(v, mesh.faces[sel], mesh.labels[sel], mesh.instances[sel],
                           None if mesh.colors is None else mesh.colors[sel])
        s = sub.sample_surface_grid(spacing)
        p = s["points"]
        keep = (p[:, 0] >= x0) & (p[:, 0] < x0 + tile) & np.all((p >= box_lo) & (p < box_hi), axis=1)
        if not np.any(keep):
            continue
        face = s["face"][keep]
        inst = mesh.instances[sel][face]
        world_p = transform_points(chunk_to_world, p[keep] + CHUNK_CORNER)
        world_n = s["normals"][keep] @ chunk_to_world[:3, :3].T
        # each Gaussian averages the colour over its samples' spacing: detail finer than that is
        # filtered out as a pixel of that size would (the render's footprint)
        colors = albedo_fn(world_p, world_n, s["labels"][keep], s["colors"][keep], inst, footprint=spacing)
        parts.append(fit_voxsplat(p[keep], voxel_size, colors=colors, labels=s["labels"][keep],
                                  weights=s["weights"][keep], patch_cov=(s["patch_cov"], face), origin=CHUNK_CORNER,
                                  fit=FitOptions(gaussians_per_voxel=gaussians_per_voxel)))
    vs = VoxSplat(np.concatenate([q.ijk for q in parts]), np.concatenate([q.params for q in parts]), voxel_size,
                  CHUNK_CORNER, np.concatenate([q.valid for q in parts]), np.concatenate([q.labels for q in parts]))
    vs.metadata.update({"frame": "chunk", "chunk_corner": CHUNK_CORNER.tolist(),
                        "chunk_to_world": np.asarray(chunk_to_world).tolist()})
    return vs


def chunk_frames(world, spacing_m: float = 80.0) -> list[np.ndarray]:
    """Chunk-to-world poses along a route longer than one chunk: the ego's lane of the main road
    every `spacing_m` metres (consecutive chunks overlap by CHUNK_SIZE - spacing along the road),
    from the ego's start while a whole chunk still fits on the road ahead."""
    road = world.layout.main
    s0 = 20.0  # where the ego starts on its road (generator convention)
    lane = -(road.median / 2 + road.lane_width / 2)
    last = road.length - (CHUNK_SIZE + CHUNK_CORNER[0])
    s = np.arange(s0, max(last, s0) + 1e-9, spacing_m)
    return list(_poses_along(road, s, lane, 0.0))
