"""Image losses and metrics: SSIM (Wang et al. 2004, Gaussian window) and PSNR, with masks.

Images (B, C, H, W) float in [0, data_range]; masks (B, 1, H, W) or (B, H, W), 1 where a pixel
counts. SSIM uses an 11 x 11 Gaussian window (sigma 1.5), C1 = (0.01 L)^2, C2 = (0.03 L)^2, on
the window positions fully inside the image ('valid'), as pytorch-msssim and the 3DGS code do.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["ssim", "psnr"]


def _window(size: int, sigma: float, dtype) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return g / g.sum()


def _blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    c = x.shape[1]
    x = F.conv2d(x, g.reshape(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(x, g.reshape(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def _as_mask(mask, like: torch.Tensor) -> torch.Tensor:
    if mask is None:
        return torch.ones_like(like[:, :1])
    m = mask.to(like.dtype)
    return m[:, None] if m.dim() == 3 else m


def ssim(x: torch.Tensor, y: torch.Tensor, mask=None, *, window: int = 11, sigma: float = 1.5,
         data_range: float = 1.0) -> torch.Tensor:
    """Mean SSIM over the channels and the valid window positions whose centre pixel is in `mask`
    (scalar; 1 for identical images). Differentiable."""
    if min(x.shape[-2:]) < window:
        raise ValueError(f"ssim: images of {tuple(x.shape[-2:])} pixels are smaller than the {window}-pixel window")
    g = _window(window, sigma, x.dtype)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    mx, my = _blur(x, g), _blur(y, g)
    sxx = _blur(x * x, g) - mx * mx
    syy = _blur(y * y, g) - my * my
    sxy = _blur(x * y, g) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    half = window // 2
    m = _as_mask(mask, x)[..., half:x.shape[-2] - half, half:x.shape[-1] - half]
    return (s * m).sum() / (m.sum() * x.shape[1]).clamp_min(1e-12)


def psnr(x: torch.Tensor, y: torch.Tensor, mask=None, *, data_range: float = 1.0) -> float:
    """10 log10(L^2 / MSE) over the masked pixels (all channels), in dB; inf for equal images."""
    m = _as_mask(mask, x)
    mse = float((((x - y) ** 2) * m).sum() / (m.sum() * x.shape[1]).clamp_min(1e-12))
    return math.inf if mse == 0 else 10.0 * math.log10(data_range ** 2 / mse)
