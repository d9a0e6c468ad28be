"""Rays cast through a sparse voxel grid: the first voxel each ray enters, and features deposited
there (the appearance stage: each pixel ray puts its image feature in the first voxel it hits).

The grid is cast as voxels, not as a mesh, so it works on any grid, the predicted ones included.
Traversal: empty space is skipped with a Chebyshev distance field on blocks of 8 x 8 x 8 voxels (a
ray at block distance d >= 2 from any occupied block advances (d - 1) blocks at once); next to
occupied blocks it steps voxel by voxel (the exit of the current voxel along the ray), looking
each voxel up by its packed key. Frames: voxel (i, j, k) spans origin + [ijk, ijk + 1) * voxel_size.

The traversal runs in the compiled trace core (`raytrace/_core.cpp`, multithreaded over rays)
wherever it is built, and otherwise in the torch loop here; both give the same voxel and t for
every ray (tests/model/nn/test_voxel_rays.py), so the converter's output does not depend on which ran.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.ndimage import distance_transform_cdt

from ...raytrace import compiled

__all__ = ["VoxelRayCaster", "deposit_mean"]

BLOCK = 8
_EPS = 1e-6  # voxel units: past a face into the next voxel


class VoxelRayCaster:
    """First-hit queries on one grid: ijk (V, 3) int voxel indices (any order, unique),
    voxel_size metres, origin (3,) metres (the frame's position of voxel (0, 0, 0)'s corner)."""

    def __init__(self, ijk, voxel_size: float, origin=(0.0, 0.0, 0.0)):
        ijk = torch.as_tensor(ijk, dtype=torch.int64)
        if ijk.ndim != 2 or ijk.shape[1] != 3:
            raise ValueError(f"ijk: expected (V, 3), got {tuple(ijk.shape)}")
        self.voxel_size = float(voxel_size)
        self.origin = torch.as_tensor(origin, dtype=torch.float64).reshape(3)
        self.num_voxels = int(ijk.shape[0])
        if not self.num_voxels:
            return
        self.lo = ijk.min(0).values
        rel = ijk - self.lo
        self.dims = rel.max(0).values + 1
        keys = self._keys(rel)
        self._order = torch.argsort(keys)
        self._keys_sorted = keys[self._order]
        blocks = -(-self.dims // BLOCK)
        occ = np.zeros(tuple(int(b) for b in blocks), bool)
        b = (rel // BLOCK).numpy()
        occ[b[:, 0], b[:, 1], b[:, 2]] = True
        # chessboard distance, in blocks, from each block to the nearest occupied one (0 inside)
        self._dist = torch.from_numpy(distance_transform_cdt(~occ, metric="chessboard").astype(np.int64))
        self._blocks = blocks
        # what the compiled core reads, in its dtypes, once per grid
        self._arrays = tuple(np.ascontiguousarray(x.numpy()) for x in (self.origin, self.lo, self.dims,
                                                                       self._keys_sorted, self._order, self._dist))

    def _keys(self, rel: torch.Tensor) -> torch.Tensor:
        d = self.dims
        return (rel[..., 0] * d[1] + rel[..., 1]) * d[2] + rel[..., 2]

    def first_hit(self, origins, dirs, max_t: float = float("inf"), core: str | None = None):
        """Rays o + t d (origins, dirs (R, 3) metres in the grid's frame; dirs need not be unit) ->
        (index (R,) int64 row of `ijk` of the first voxel entered, -1 if none with t <= max_t;
        t (R,) float64 the ray parameter where it enters that voxel (metres for unit d), inf if
        none). core: 'compiled' or 'reference' (the torch loop); None: the tracer's default
        (`raytrace.compiled.default_core_name`: compiled where built, `SCUBE_SIM_CORE` overrides)."""
        o = torch.as_tensor(origins, dtype=torch.float64)
        d = torch.as_tensor(dirs, dtype=torch.float64)
        r = o.shape[0]
        index = torch.full((r,), -1, dtype=torch.int64)
        t_hit = torch.full((r,), float("inf"), dtype=torch.float64)
        if not self.num_voxels or not r:
            return index, t_hit
        name = core or compiled.default_core_name()
        if name == "compiled":
            if not compiled.available():
                raise compiled.CoreUnavailable(f"core='compiled': the compiled core is not built "
                                               f"({compiled.load_error()})")
            origin, lo, dims, keys, order, dist = self._arrays
            compiled.voxel_first_hit(o.numpy(), d.numpy(), origin, self.voxel_size, lo, dims, keys, order, dist,
                                     max_t, index.numpy(), t_hit.numpy())
            return index, t_hit
        if name != "reference":
            raise ValueError(f"core: expected 'compiled' or 'reference', got {name!r}")
        # voxel units, relative to the grid's low corner: p(t) = p0 + t dv, t the rays' own parameter
        p0 = (o - self.origin) / self.voxel_size - self.lo.to(torch.float64)
        dv = d / self.voxel_size
        inv = 1.0 / torch.where(dv == 0, torch.full_like(dv, 1e-300), dv)
        per_voxel = 1.0 / dv.abs().max(1).values.clamp_min(1e-300)  # t per voxel of L-inf travel
        dims = self.dims.to(torch.float64)
        ta, tb = (0.0 - p0) * inv, (dims - p0) * inv
        t_enter = torch.minimum(ta, tb).max(1).values.clamp_min(0.0)
        t_exit = torch.maximum(ta, tb).min(1).values.clamp_max(max_t)
        live = torch.nonzero(t_enter < t_exit).squeeze(1)
        t = t_enter[live]
        step_dir = (dv > 0).to(torch.float64)
        zero, hi = torch.zeros_like(self.lo), self.dims - 1
        while live.numel():
            pl = p0[live]
            p = pl + t[:, None] * dv[live]
            cell = torch.minimum(torch.maximum(torch.floor(p).to(torch.int64), zero), hi)
            blk = cell // BLOCK
            dist = self._dist[blk[:, 0], blk[:, 1], blk[:, 2]]
            near = dist <= 1
            hit = torch.zeros_like(near)
            if bool(near.any()):
                key = self._keys(cell[near])
                pos = torch.searchsorted(self._keys_sorted, key).clamp_max(len(self._keys_sorted) - 1)
                found = self._keys_sorted[pos] == key
                hit[near] = found
                sel = live[near][found]
                index[sel] = self._order[pos[found]]
                # where the ray enters that voxel: the near end of its slab test
                c = cell[near][found].to(torch.float64)
                a0, a1 = (c - pl[near][found]) * inv[sel], (c + 1 - pl[near][found]) * inv[sel]
                t_hit[sel] = torch.minimum(a0, a1).max(1).values.clamp_min(0.0)
            # advance: whole free blocks at once, or to the exit of the current voxel
            skip = (dist - 1).clamp_min(0).to(torch.float64) * BLOCK * per_voxel[live]
            t_face = ((cell.to(torch.float64) + step_dir[live] - p) * inv[live]).abs().min(1).values
            t_next = torch.where(near, t + t_face + _EPS * per_voxel[live], t + skip)
            keep = ~hit & (t_next < t_exit[live])
            live, t = live[keep], t_next[keep]
        return index, t_hit


def deposit_mean(features: torch.Tensor, index: torch.Tensor, num_voxels: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean of the features (R, C) of the rays whose first voxel is `index` (R,) (-1: none):
    (V, C) features (0 where no ray landed) and (V,) ray counts. Differentiable in `features`."""
    ok = index >= 0
    idx = index[ok]
    acc = features.new_zeros((num_voxels, features.shape[1])).index_add(0, idx, features[ok])
    count = torch.bincount(idx, minlength=num_voxels).to(features.dtype)
    return acc / count.clamp_min(1)[:, None], count
