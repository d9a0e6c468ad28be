"""The sky panorama (paper section 3.2): an equirectangular feature panorama of what the input
cameras saw as sky, sampled along each novel-view ray and decoded to RGB by a small CNN.

Panorama frame: the chunk frame (x forward, y left, z up); only a ray's direction decides its sky,
so camera translations are zeroed. Pixel (r, c) of an (Hp, Wp) panorama looks along azimuth
phi = 2 pi (c + 0.5) / Wp - pi (phi = atan2(y, x): 0 forward, +pi/2 left) at elevation
e = pi/2 - pi (r + 0.5) / Hp (row 0 at the zenith). Sampling is bilinear, wrapping in azimuth.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ...camera.model import Intrinsics
from .camera import project

__all__ = ["panorama_directions", "build_panorama", "sample_panorama", "camera_ray_directions", "SkyDecoder"]


def panorama_directions(hp: int, wp: int, dtype=torch.float32) -> torch.Tensor:
    """(Hp, Wp, 3) unit directions of the panorama's pixel centres, chunk frame."""
    phi = (torch.arange(wp, dtype=torch.float64) + 0.5) / wp * 2 * math.pi - math.pi
    elev = math.pi / 2 - (torch.arange(hp, dtype=torch.float64) + 0.5) / hp * math.pi
    e, p = torch.meshgrid(elev, phi, indexing="ij")
    return torch.stack([torch.cos(e) * torch.cos(p), torch.cos(e) * torch.sin(p), torch.sin(e)], -1).to(dtype)


def camera_ray_directions(K, distortion, cam_to_chunk, height: int, width: int) -> torch.Tensor:
    """(H, W, 3) float32 unit directions, chunk frame, through the pixel centres of a camera
    (K (3, 3) pixels, OpenCV [k1, k2, p1, p2, k3] or zeros; cam_to_chunk (4, 4); the rays
    of `camera.model.Intrinsics.pixel_rays`, undistorted, rotated, translation ignored)."""
    k = np.asarray(torch.as_tensor(K, dtype=torch.float64))
    dist = [float(v) for v in torch.as_tensor(distortion).reshape(-1)] if distortion is not None else []
    intr = Intrinsics(width, height, k[0, 0], k[1, 1], k[0, 2], k[1, 2], "opencv" if any(dist) else "pinhole",
                      dist if any(dist) else ())
    rays = torch.from_numpy(np.array(intr.pixel_rays()))  # (H, W, 3) camera frame, float64
    rot = torch.as_tensor(cam_to_chunk, dtype=torch.float64)[:3, :3]
    return (rays @ rot.T).to(torch.float32)


def _grid(dirs: torch.Tensor) -> torch.Tensor:
    """Unit directions (..., 3) -> grid_sample coordinates (..., 2) on the panorama (x: azimuth
    phi / pi, y: -2 e / pi, both in [-1, 1])."""
    phi = torch.atan2(dirs[..., 1], dirs[..., 0])
    elev = torch.asin(dirs[..., 2].clamp(-1.0, 1.0))
    return torch.stack([phi / math.pi, -2.0 * elev / math.pi], -1)


def sample_panorama(pano: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of a (C, Hp, Wp) panorama along unit directions (..., 3) (chunk frame),
    wrapping in azimuth: (C, ...)."""
    c, hp, wp = pano.shape
    wrapped = torch.cat([pano[:, :, -1:], pano, pano[:, :, :1]], 2)  # one column each side
    g = _grid(dirs.to(pano.dtype)).reshape(1, 1, -1, 2)
    # x in [-1, 1] over Wp columns -> the same points in the (Wp + 2)-wide padded panorama
    g = torch.stack([g[..., 0] * wp / (wp + 2), g[..., 1]], -1)
    out = F.grid_sample(wrapped[None], g, mode="bilinear", padding_mode="border", align_corners=False)
    return out.reshape((c,) + dirs.shape[:-1])


def build_panorama(features: torch.Tensor, sky: torch.Tensor, cam_to_chunk: torch.Tensor, K: torch.Tensor,
                   distortion: torch.Tensor | None, hp: int, wp: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The feature panorama of N input cameras: each panorama direction, rotated into every
    camera (translation zeroed) and projected through its lens, takes the camera's feature
    there (bilinear), weighted by its sky mask; the panorama is the weighted mean over cameras.

    features (N, C, h, w) on the feature map's pixel grid; sky (N, h, w) bool or [0, 1] weights
    on the same grid; cam_to_chunk (N, 4, 4); K (N, 3, 3) pixels of the feature map; distortion
    (N, 5) OpenCV or None. Returns pano (C, Hp, Wp) and weight (Hp, Wp) (0: no camera saw sky)."""
    n, c, h, w = features.shape
    dirs = panorama_directions(hp, wp, torch.float64).reshape(-1, 3)
    acc = features.new_zeros((c, hp * wp))
    weight = features.new_zeros(hp * wp)
    for i in range(n):
        rot = cam_to_chunk[i, :3, :3].to(torch.float64)
        d_cam = dirs @ rot  # R^T d for every direction
        coeffs = tuple(float(v) for v in distortion[i]) if distortion is not None else ()
        model = "opencv" if any(coeffs) else "pinhole"
        uv, valid = project(d_cam, K[i].to(torch.float64), model, coeffs if model == "opencv" else ())
        inside = valid & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        g = torch.stack([2 * uv[:, 0] / w - 1, 2 * uv[:, 1] / h - 1], -1).to(features.dtype).reshape(1, 1, -1, 2)
        g = torch.where(inside.reshape(1, 1, -1, 1), g, torch.zeros_like(g))
        f = F.grid_sample(features[i:i + 1], g, mode="bilinear", padding_mode="border", align_corners=False)[0, :, 0]
        m = F.grid_sample(sky[i:i + 1, None].to(features.dtype), g, mode="bilinear", padding_mode="border",
                          align_corners=False)[0, 0, 0]
        wi = m * inside.to(features.dtype)
        acc = acc + f * wi
        weight = weight + wi
    pano = acc / weight.clamp_min(1e-6)
    return pano.reshape(c, hp, wp), weight.reshape(hp, wp)


class SkyDecoder(nn.Module):
    """Sampled sky features (B, C, H, W) -> RGB (B, 3, H, W) in [0, 1]: conv C -> 16 -> 3, kernel 3,
    stride 1 (appendix B: 32 -> 16 -> 3, the spatial size unchanged)."""

    def __init__(self, channels: int = 32, hidden: int = 16):
        super().__init__()
        self.net = nn.Sequential(nn.Conv2d(channels, hidden, 3, padding=1), nn.ReLU(inplace=True),
                                 nn.Conv2d(hidden, 3, 3, padding=1))

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.net(feats))
