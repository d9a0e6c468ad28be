"""Ground-truth products of a world (the paper's data pipeline, section 4.1).

A *chunk* is a 102.4 m cube in the ego frame at the reference time T: x from -10.24 m (the ego
near the back edge, facing inward) to 92.16 m, y within +-51.2 m, z from -3.2 m to 99.2 m.
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

from ..fit import fit_voxsplat
from ..mesh import TriangleMesh
from ..transforms import invert_pose, transform_points
from ..voxsplat import VoxSplat, voxel_keys

CHUNK_SIZE = 102.4
CHUNK_CORNER = np.array([-10.24, -51.2, -3.2])


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
    s = {k: a[keep] for k, a in s.items()}
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
    """Every voxel of the chunk that the mesh's surface passes through (conservative).

    Each triangle is scan-converted along its dominant axis a: for every voxel column (in the
    other two axes) whose square overlaps the projected triangle (separating-axis test), the
    plane's a-range over the square, clipped to the triangle's, gives the voxels it crosses. The
    result contains every point of the surface (it may add a voxel where the surface only grazes
    a face). Label: the label with the most surface area in the voxel (ties: smaller id).
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


def _scan_columns(tri, nr, lo, hi, cnt, a, u, w, n):
    """Columns (in voxel units) of a batch of triangles with dominant axis a that overlap each
    projected triangle, with the a-range of the plane over each column square.

    Returns (triangle index, column u, column w, first voxel, last voxel, surface area weight)."""
    t = np.repeat(np.arange(len(tri)), cnt)
    off = np.arange(len(t)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    nu = hi[:, 0] - lo[:, 0] + 1
    cu = lo[t, 0] + off % nu[t]
    cw = lo[t, 1] + off // nu[t]
    p2 = tri[:, :, [u, w]]  # (T, 3, 2)
    # Separating axes: the three edge normals of the projected triangle (the square's own axes
    # are covered by the column range). Orient each normal away from the opposite vertex.
    keep = np.ones(len(t), bool)
    for e in range(3):
        p, q, r = p2[:, e], p2[:, (e + 1) % 3], p2[:, (e + 2) % 3]
        m = np.stack([q[:, 1] - p[:, 1], p[:, 0] - q[:, 0]], 1)
        h = np.einsum("ij,ij->i", m, p)
        flip = np.einsum("ij,ij->i", m, r) > h
        m[flip] *= -1
        h[flip] *= -1
        mt = m[t]
        # The square [cu, cu+1] x [cw, cw+1]: its lowest projection onto m.
        low = mt[:, 0] * (cu + (mt[:, 0] < 0)) + mt[:, 1] * (cw + (mt[:, 1] < 0))
        keep &= low <= h[t] + 1e-9
    t, cu, cw = t[keep], cu[keep], cw[keep]
    if not len(t):
        return None
    nt = nr[t]
    d = np.einsum("ij,ij->i", nt, tri[t, 0])
    na = nt[:, a]
    # Plane coordinate along a at the four corners of the column square.
    corners = [(cu + du, cw + dw) for du in (0, 1) for dw in (0, 1)]
    vals = np.stack([(d - nt[:, u] * x - nt[:, w] * y) / na for x, y in corners], 1)
    amin = np.maximum(vals.min(1), tri[t, :, a].min(1))
    amax = np.minimum(vals.max(1), tri[t, :, a].max(1))
    k0 = np.clip(np.floor(amin).astype(np.int64), 0, n - 1)
    k1 = np.clip(np.floor(amax).astype(np.int64), 0, n - 1)
    ok = (amax >= 0) & (amin < n) & (k1 >= k0)
    return t[ok], cu[ok], cw[ok], k0[ok], k1[ok], 1.0 / np.abs(na[ok])


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
    the chunk frame to fit only part of the chunk."""
    from .textures import albedo as default_albedo

    albedo_fn = albedo_fn or default_albedo
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
        colors = albedo_fn(world_p, world_n, s["labels"][keep], s["colors"][keep], inst)
        parts.append(fit_voxsplat(p[keep], voxel_size, gaussians_per_voxel=gaussians_per_voxel, colors=colors,
                                  labels=s["labels"][keep], weights=s["weights"][keep],
                                  patch_cov=(s["patch_cov"], face), origin=CHUNK_CORNER))
    vs = VoxSplat(np.concatenate([q.ijk for q in parts]), np.concatenate([q.params for q in parts]), voxel_size,
                  CHUNK_CORNER, np.concatenate([q.valid for q in parts]), np.concatenate([q.labels for q in parts]))
    vs.metadata.update({"frame": "chunk", "chunk_corner": CHUNK_CORNER.tolist(),
                        "chunk_to_world": np.asarray(chunk_to_world).tolist()})
    return vs


def chunk_frames(world, spacing_m: float = 80.0) -> list[np.ndarray]:
    """Chunk-to-world poses along a route longer than one chunk: the ego's lane of the main road
    every `spacing_m` metres (consecutive chunks overlap by CHUNK_SIZE - spacing along the road),
    from the ego's start while a whole chunk still fits on the road ahead."""
    from .generator import _poses_along

    road = world.layout.main
    s0 = 20.0  # where the ego starts on its road (generator convention)
    lane = -(road.median / 2 + road.lane_width / 2)
    last = road.length - (CHUNK_SIZE + CHUNK_CORNER[0])
    s = np.arange(s0, max(last, s0) + 1e-9, spacing_m)
    return list(_poses_along(road, s, lane, 0.0))
