"""The completion network's input: the evidence (`reconstruct.evidence.Evidence`) summarised on a dense
coarse grid over the chunk, one channel per `FEATURES` entry.

Grid: `voxel_size` metres (default 0.8, the paper's coarse level), anchored at the evidence's
corner, (X, Y, Z) = (102.4, 102.4, 25.6) m / voxel_size cells; cell (i, j, k) spans
corner + [ijk, ijk + 1) * voxel_size, chunk frame.

Channels, each in [0, 1] (or [-1, 1]) so that no scale is learned from one log:

- ``occupied``: share of the cell's fine voxels the fusion holds occupied, over 16 (a flat
  surface through a 4 x 4 x 4 block fills about 16), clipped at 1
- ``probability``: the highest fused occupancy probability in the cell (0: none)
- ``ground``: share of the cell's observed points labelled ground by the geometry
- ``free_images``: images whose confident rays crossed the cell short of their surface, over 4,
  clipped (the free space the cameras saw: what completion must leave empty)
- ``free_rays``: log(1 + ray samples in the cell) / log(1 + 64), clipped
- ``red``, ``green``, ``blue``: the observed points' mean colour (0: none)
- ``height``: (cell centre z - ground height field there) / 4 m, clipped to [-1, 1]
- ``ground_observed``: 1 where the height field's cell was measured, 0 where it was filled
- ``z``: the cell's height in the box, (k + 0.5) / Z
- ``looked``: images in which the cell's centre, in front of the camera and within
  `max_depth_m` along its axis, falls on a pixel with no confident depth (sky, a blank wall, the direction
  of travel seen by a camera moving along it), over 4, clipped: the camera looked, stereo measured
  nothing. A cell no camera looked at (outside every image, or beyond the range) holds 0 here and
  in ``free_images``; one a camera saw through holds ``free_images``; a confident surface in front
  of the cell hides it, and the cell counts in neither (its pixel holds a depth)

`INPUTS_V1`: the channels the first checkpoint (`completion-cpu`) reads, all but ``looked``.

Free-space rays: every confident pixel of a grid spaced `ray_spacing_rad` apart in each reference
image (its depth finite, confidence at least the fusion's `min_confidence`), sampled every half
cell from 0.5 m to its point less a band of one cell and 5 % of the depth (the depth's error).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ...camera.depth import project_to_pixels
from ...reconstruct.config import CHUNK_HEIGHT_SHARE, GROUND_LABEL

if TYPE_CHECKING:  # the record only: features need no stereo, so no torch
    from ...reconstruct.evidence import Evidence
from ...worlds.groundtruth import CHUNK_SIZE

__all__ = ["FEATURES", "INPUTS_V1", "completion_input", "coarse_dims"]

FEATURES = ("occupied", "probability", "ground", "free_images", "free_rays", "red", "green", "blue", "height",
            "ground_observed", "z", "looked")
INPUTS_V1 = FEATURES[:11]
OCCUPIED_FULL = 16.0  # fine voxels of a flat surface through a 4 x 4 x 4 block
FREE_IMAGES_FULL = 4.0
FREE_RAYS_FULL = 64.0
HEIGHT_SCALE_M = 4.0
RAY_NEAR_M = 0.5
BAND_REL = 0.05


def coarse_dims(voxel_size: float) -> tuple[int, int, int]:
    """(X, Y, Z) cells of the chunk at `voxel_size` metres."""
    n = int(round(CHUNK_SIZE / voxel_size))
    return n, n, int(round(CHUNK_SIZE * CHUNK_HEIGHT_SHARE / voxel_size))


def _linear(ijk: np.ndarray, dims) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) int cells -> (flat index (M,), keep (N,) bool) of those inside `dims`."""
    keep = np.all((ijk >= 0) & (ijk < np.asarray(dims)), 1)
    i = ijk[keep]
    return (i[:, 0] * dims[1] + i[:, 1]) * dims[2] + i[:, 2], keep


def _free_space(ev: Evidence, vs: float, dims, min_confidence: float, spacing: float, pixel_stride: int):
    """(images (X*Y*Z,), samples (X*Y*Z,)) float64: per cell, the images whose confident rays
    crossed it short of their surface, and the ray samples that fell in it."""
    n = int(np.prod(dims))
    images, samples = np.zeros(n), np.zeros(n)
    step = vs / 2
    for obs in ev.observations:
        intr = obs.image.intrinsics
        s = max(pixel_stride, int(round(spacing * intr.fx)))
        d = np.asarray(obs.depth, np.float64)[::s, ::s]
        c = np.asarray(obs.confidence, np.float32)[::s, ::s]
        keep = np.isfinite(d) & (d > 0) & (c >= min_confidence) & (c > 0)
        if obs.image.sky is not None:
            keep &= ~np.asarray(obs.image.sky, bool)[::s, ::s]
        if not keep.any():
            continue
        rays = intr.pixel_rays()[::s, ::s][keep]  # unit, camera frame
        depth = d[keep]
        dist = depth / rays[:, 2]  # along the ray
        stop = dist - np.maximum(vs, BAND_REL * dist)
        pose = obs.image.cam_to_world
        dirs = rays @ pose[:3, :3].T
        most = int(np.ceil(max(0.0, float(stop.max()) - RAY_NEAR_M) / step)) + 1
        t = RAY_NEAR_M + step * np.arange(most)
        for lo in range(0, len(dirs), 4096):  # bounded memory: 4096 rays x `most` samples at a time
            hi = min(lo + 4096, len(dirs))
            ok = t[None, :] <= stop[lo:hi, None]
            r, k = np.nonzero(ok)
            pts = pose[:3, 3] + dirs[lo:hi][r] * t[k][:, None]
            idx, _ = _linear(np.floor((pts - ev.corner) / vs).astype(np.int64), dims)
            samples += np.bincount(idx, minlength=n)
            images[np.unique(idx)] += 1
    return images, samples


def _looked(ev: Evidence, centres: np.ndarray, min_confidence: float, max_depth_m: float) -> np.ndarray:
    """(X*Y*Z,) float64: per cell centre (chunk frame), the images in which it lies in front of
    the camera, at most `max_depth_m` along its axis (the fusion's limit), on a pixel without a
    confident depth."""
    looked = np.zeros(len(centres))
    for obs in ev.observations:
        kept, flat, z = project_to_pixels(centres, obs.image)
        d = np.asarray(obs.depth, np.float64).reshape(-1)[flat]
        c = np.asarray(obs.confidence, np.float32).reshape(-1)[flat]
        with np.errstate(invalid="ignore"):
            measured = np.isfinite(d) & (d > 0) & (c >= min_confidence) & (c > 0)
        looked[kept[~measured & (z <= max_depth_m)]] += 1
    return looked


def completion_input(ev: Evidence, voxel_size: float = 0.8, *, min_confidence: float = 0.5,
                     ray_spacing_rad: float = 0.012, pixel_stride: int = 1, max_depth_m: float = 80.0) -> np.ndarray:
    """(len(FEATURES), X, Y, Z) float32 (module docstring) of the evidence `ev`."""
    vs = float(voxel_size)
    dims = coarse_dims(vs)
    n = int(np.prod(dims))
    out = np.zeros((len(FEATURES), n), np.float32)
    g = ev.grid
    if len(g.ijk):
        factor = vs / g.voxel_size
        cells = np.floor((g.ijk + 0.5) / factor).astype(np.int64)
        idx, keep = _linear(cells, dims)
        out[0] = np.minimum(np.bincount(idx, minlength=n) / OCCUPIED_FULL, 1.0)
        prob = np.zeros(n)
        np.maximum.at(prob, idx, g.probability[keep])
        out[1] = prob
    if len(g.points):
        idx, keep = _linear(np.floor((g.points - ev.corner) / vs).astype(np.int64), dims)
        count = np.bincount(idx, minlength=n)
        has = count > 0
        w = np.maximum(count, 1)
        out[2] = np.bincount(idx, weights=(ev.labels[keep] == GROUND_LABEL).astype(np.float64), minlength=n) / w
        for ch in range(3):
            out[5 + ch] = np.where(has, np.bincount(idx, weights=g.colors[keep, ch], minlength=n) / w, 0.0)
    images, samples = _free_space(ev, vs, dims, min_confidence, ray_spacing_rad, pixel_stride)
    out[3] = np.minimum(images / FREE_IMAGES_FULL, 1.0)
    out[4] = np.minimum(np.log1p(samples) / np.log1p(FREE_RAYS_FULL), 1.0)
    ii, jj, kk = np.meshgrid(*(np.arange(d) for d in dims), indexing="ij")
    centres = ev.corner + (np.stack([ii, jj, kk], -1).reshape(-1, 3) + 0.5) * vs
    if ev.field is not None:
        cols = centres.reshape(dims[0], dims[1], dims[2], 3)[:, :, 0, :2].reshape(-1, 2)
        ground = ev.field.height_at(cols)
        out[8] = np.clip((centres[:, 2] - np.repeat(ground, dims[2])) / HEIGHT_SCALE_M, -1.0, 1.0)
        f = ev.field
        fi = np.clip(np.floor((cols - f.origin) / f.cell).astype(np.int64), 0, np.array(f.heights.shape) - 1)
        out[9] = np.repeat(f.observed[fi[:, 0], fi[:, 1]].astype(np.float32), dims[2]) if ev.measured else 0.0
    else:
        out[8] = np.clip((centres[:, 2]) / HEIGHT_SCALE_M, -1.0, 1.0)
    out[10] = (kk.reshape(-1) + 0.5) / dims[2]
    out[11] = np.minimum(_looked(ev, centres, min_confidence, max_depth_m) / FREE_IMAGES_FULL, 1.0)
    return out.reshape(len(FEATURES), *dims)
