"""Images resized for a network and the camera models that go with them: bilinear for colour,
nearest for masks and labels, intrinsics scaled to the new size, and a camera's OpenCV distortion
coefficients. Images (C, H, W) float tensors or (H, W, ...) arrays; sizes (rows, columns).
"""

from __future__ import annotations

import numpy as np
import torch

from ..errors import InputError
from .frames import CameraImage


def scale_intrinsics(k: np.ndarray, size: tuple[int, int], new_size: tuple[int, int]) -> np.ndarray:
    """(3, 3) float64 K of an image of `size` (height, width) resized to `new_size`: with pixel
    (u, v) spanning [u, u + 1), a resize maps image coordinate x to x * new_w / w (y likewise),
    so fx and cx scale by new_w / w, fy and cy by new_h / h, exactly."""
    sy, sx = new_size[0] / size[0], new_size[1] / size[1]
    out = np.array(k, np.float64, copy=True)
    out[0, :] *= sx
    out[1, :] *= sy
    return out


def resize_bilinear(img: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(C, H, W) float -> (C, h, w) by bilinear interpolation at the new pixel centres (torch's
    align_corners=False is this pixel-centre convention), antialiased when shrinking: exact for
    enlarging and integer factors; shrinking by another factor, the filter (truncated to whole
    source pixels) sits up to ~0.1 source pixel off the centre `scale_intrinsics` assumes."""
    if tuple(img.shape[1:]) == tuple(size):
        return img.clone()
    return torch.nn.functional.interpolate(img[None], size=tuple(size), mode="bilinear", align_corners=False,
                                           antialias=True)[0]


def nearest_index(n: int, new_n: int) -> np.ndarray:
    """(new_n,) int64: the source pixel (of n) whose span holds each new pixel's centre,
    floor((i + 0.5) * n / new_n)."""
    return np.minimum(np.floor((np.arange(new_n) + 0.5) * (n / new_n)).astype(np.int64), n - 1)


def resize_nearest(a: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W) array of any dtype -> (h, w): each new pixel takes the value of the source pixel
    holding its centre (no values are mixed: labels, ids and depths stay as stored)."""
    if a.shape == tuple(size):
        return a.copy()
    return a[nearest_index(a.shape[0], size[0])[:, None], nearest_index(a.shape[1], size[1])[None, :]]


def camera_distortion(im: CameraImage) -> np.ndarray:
    """(5,) float64 OpenCV [k1, k2, p1, p2, k3] of a pinhole or OpenCV camera (zeros for pinhole;
    shorter OpenCV lists padded with zeros); an InputError for any other lens model."""
    intr = im.intrinsics
    if intr.model == "pinhole" or not intr.dist:
        return np.zeros(5)
    if intr.model == "opencv":
        d = np.zeros(5)
        d[: len(intr.dist)] = intr.dist
        return d
    raise InputError(f"camera {im.name!r}: distortion model {intr.model!r}; the networks take "
                     f"'pinhole' or 'opencv' cameras")
