"""Lifting image features into a voxel grid with per-pixel depth distributions (paper Eq. 1, LSS).

Each feature pixel j of camera i carries a feature F_ij (C,) and a softmax distribution theta_ij
over D depth bins; the point at the centre of bin d on the pixel's ray falls in voxel v, and

    F_ijd = theta_ijd * F_ij,       C_v = sum over (i, j, d) landing in v of F_ijd.

The ablation (`broadcast`) puts F_ij in every voxel its ray's bin centres fall in (theta = 1).
Bins split [z_near, z_far] (camera-z depth, metres) into D intervals whose widths grow linearly
(the paper: 0.1 to 90 m, D = 64). Frames: chunk (x forward, y left, z up, metres); cameras
OpenCV (x right, y down, z forward), poses camera-to-chunk; voxel (i, j, k) of a `LiftGrid`
spans origin + [ijk, ijk + 1) * voxel_size, 0 <= ijk < dims.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ...camera.model import Intrinsics
from ...worlds.groundtruth import CHUNK_CORNER
from .encoding import majority_labels

__all__ = ["LiftGrid", "depth_bin_centres", "depth_bin_edges", "depth_focal_loss", "depth_to_bin",
           "feature_intrinsics", "frustum_points", "grid_in_box", "lift"]


def depth_bin_edges(bins: int, near: float = 0.1, far: float = 90.0) -> torch.Tensor:
    """(D + 1,) float64 edges: bin k spans [e_k, e_k+1), widths growing linearly with k,
    e_k = near + (far - near) k (k + 1) / (D (D + 1))."""
    if bins < 1 or not 0 < near < far:
        raise ValueError(f"depth bins: expected bins >= 1 and 0 < near < far, got {bins}, {near}, {far}")
    k = torch.arange(bins + 1, dtype=torch.float64)
    return near + (far - near) * k * (k + 1) / (bins * (bins + 1))


def depth_bin_centres(bins: int, near: float = 0.1, far: float = 90.0) -> torch.Tensor:
    """(D,) float64 midpoints of the bins of `depth_bin_edges`."""
    e = depth_bin_edges(bins, near, far)
    return 0.5 * (e[1:] + e[:-1])


def depth_to_bin(depth: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Camera-z depths (any shape, metres; inf, nan, 0 allowed) -> long bin indices, -1 outside
    [edges[0], edges[-1])."""
    d = depth.double()
    idx = torch.searchsorted(edges, torch.nan_to_num(d, nan=-1.0, posinf=np.inf).contiguous(), right=True) - 1
    ok = torch.isfinite(d) & (d >= edges[0]) & (d < edges[-1])
    return torch.where(ok, idx, torch.full_like(idx, -1))


def feature_intrinsics(K: torch.Tensor, stride: int) -> torch.Tensor:
    """(3, 3) K of a feature map whose pixel j covers image pixels [stride j, stride j + stride):
    fx, fy, cx, cy divided by the stride (pixel centres at integer + 0.5 in both)."""
    k = torch.as_tensor(K, dtype=torch.float64).clone()
    k[:2] /= stride
    return k


def frustum_points(K: torch.Tensor, distortion, cam_to_chunk: torch.Tensor, height: int, width: int,
                   depths: torch.Tensor) -> torch.Tensor:
    """(D, height, width, 3) float64 chunk-frame points at camera-z `depths` (D,) along the rays
    through the pixel centres of a (height, width) image with intrinsics K (3, 3) and OpenCV
    distortion [k1, k2, p1, p2, k3] (or None / zeros), undistorted exactly (`Intrinsics`)."""
    k = np.asarray(torch.as_tensor(K, dtype=torch.float64))
    dist = [float(v) for v in torch.as_tensor(distortion).reshape(-1)] if distortion is not None else []
    intr = Intrinsics(width, height, k[0, 0], k[1, 1], k[0, 2], k[1, 2], "opencv" if any(dist) else "pinhole",
                      dist if any(dist) else ())
    rays = torch.from_numpy(np.array(intr.pixel_rays()))  # (H, W, 3) unit, camera frame
    rays = rays / rays[..., 2:3]  # camera z = 1: scaling by depth gives camera-z depth
    pose = torch.as_tensor(cam_to_chunk, dtype=torch.float64)
    pts = depths.double()[:, None, None, None] * rays[None]
    return pts @ pose[:3, :3].T + pose[:3, 3]


@dataclass(frozen=True)
class LiftGrid:
    """A dense voxel box: origin (3,) metres (corner of voxel (0, 0, 0)), voxel_size metres, dims
    (X, Y, Z) voxels."""

    origin: tuple[float, float, float]
    voxel_size: float
    dims: tuple[int, int, int]

    def voxel_index(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., 3) float points -> ((...,) long flat index i * Y * Z + j * Z + k, (...,) bool
        inside the box)."""
        rel = (points.double() - torch.tensor(self.origin, dtype=torch.float64)) / self.voxel_size
        ijk = torch.floor(rel).to(torch.int64)
        dims = torch.tensor(self.dims, dtype=torch.int64)
        inside = ((ijk >= 0) & (ijk < dims)).all(-1)
        ijk = torch.where(inside[..., None], ijk, torch.zeros_like(ijk))
        return (ijk[..., 0] * dims[1] + ijk[..., 1]) * dims[2] + ijk[..., 2], inside


def lift(features: torch.Tensor, weights: torch.Tensor | None, points: torch.Tensor, grid: LiftGrid,
         valid: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 1 into a dense box.

    features (N, C, h, w); weights (N, D, h, w) depth distributions (None: the broadcast ablation,
    weight 1 in every bin); points (N, D, h, w, 3) chunk-frame bin centres (`frustum_points`);
    valid (N, h, w) bool pixels that take part (None: all). Returns (volume (C, X, Y, Z) the sum
    of the weighted features per voxel, hits (X, Y, Z) float the number of (pixel, bin) points
    that fell in each voxel: where it is 0, no frustum reached the voxel). Differentiable in
    features and weights."""
    n, c, h, w = features.shape
    d = points.shape[1]
    if points.shape != (n, d, h, w, 3):
        raise ValueError(f"points: expected (N, D, h, w, 3) = ({n}, {d}, {h}, {w}, 3), got {tuple(points.shape)}")
    index, inside = grid.voxel_index(points)  # (N, D, h, w)
    if valid is not None:
        inside = inside & valid[:, None]
    x, y, z = grid.dims
    f = features.permute(0, 2, 3, 1)[:, None]  # (N, 1, h, w, C)
    wts = inside.to(features.dtype) if weights is None else weights * inside.to(weights.dtype)
    contrib = (f * wts[..., None]).reshape(-1, c)
    flat = index.reshape(-1)
    volume = features.new_zeros((x * y * z, c)).index_add(0, flat, contrib)
    hits = torch.zeros(x * y * z, dtype=features.dtype).index_add(0, flat, inside.reshape(-1).to(features.dtype))
    return volume.T.reshape(c, x, y, z), hits.reshape(x, y, z)


def depth_focal_loss(probs: torch.Tensor, target: torch.Tensor, gamma: float = 2.0) -> torch.Tensor:
    """Multi-class focal loss (Lin et al. 2017) of depth distributions probs (N, D, h, w)
    (softmax over D) against target bins (N, h, w) long (-1: no target, e.g. sky); the mean of
    -(1 - p_t)^gamma log p_t over the pixels with a target (0 when there are none)."""
    ok = target >= 0
    if not bool(ok.any()):
        return probs.sum() * 0.0
    p = probs.permute(0, 2, 3, 1)[ok]  # (P, D)
    pt = p.gather(1, target[ok][:, None]).squeeze(1).clamp_min(1e-12)
    return (-(1 - pt) ** gamma * torch.log(pt)).mean()


def grid_in_box(ijk: torch.Tensor, labels: torch.Tensor, visible: torch.Tensor, factor: int, stored_size: float,
                grid: LiftGrid):
    """A chunk grid (ijk from CHUNK_CORNER at `stored_size`) coarsened by `factor` (a coarse voxel
    takes the most frequent label of its children and is visible if any child is) and cut to
    `grid`'s box: (ijk (V, 3) relative to the box's corner, labels, visible), sorted by voxel."""
    ijk = ijk.to(torch.int64) // factor
    shift = torch.round((torch.tensor(grid.origin, dtype=torch.float64) - torch.as_tensor(CHUNK_CORNER))
                        / grid.voxel_size).to(torch.int64)
    rel = ijk - shift
    dims = torch.tensor(grid.dims)
    keep = ((rel >= 0) & (rel < dims)).all(1)
    rel, labels, visible = rel[keep], labels[keep].to(torch.int64), visible[keep]
    key = (rel[:, 0] * dims[1] + rel[:, 1]) * dims[2] + rel[:, 2]
    if factor == 1:  # the stored grid itself: unique voxels already
        order = torch.argsort(key)
        return rel[order], labels[order], visible[order]
    uniq, inv = torch.unique(key, return_inverse=True)
    vis = torch.zeros(len(uniq), dtype=torch.bool).index_put_((inv,), visible, accumulate=True)
    out = torch.stack([uniq // (dims[1] * dims[2]), (uniq // dims[2]) % dims[1], uniq % dims[2]], 1)
    return out, majority_labels(inv, labels, len(uniq)), vis
