"""Dense 3D building blocks the stages share: a pre-norm residual block with an optional
embedding (`ResBlock3d`) on (B, C, X, Y, Z) tensors, GroupNorm sized to divide the channels, and
2x resampling of the box."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["ResBlock3d", "group_norm", "resample_box"]


# ---------------------------------------------------------------------------- building blocks
def group_norm(channels: int, groups: int) -> nn.GroupNorm:
    return nn.GroupNorm(math.gcd(groups, channels), channels)


def resample_box(x: torch.Tensor, how: str) -> torch.Tensor:
    return F.avg_pool3d(x, 2) if how == "down" else F.interpolate(x, scale_factor=2, mode="nearest")


class ResBlock3d(nn.Module):
    """Pre-norm residual block: (B, C, X, Y, Z) -> (B, C_out, X, Y, Z), optionally adding a
    per-sample embedding (B, E) after the first convolution. scale_shift: the embedding gives a
    scale and a shift of the second normalisation instead (FiLM, LDM's use_scale_shift_norm).
    resample ``down`` / ``up``: the block halves (average pooling) / doubles (nearest) the box,
    applied to both branches after the first normalisation (LDM's resblock_updown)."""

    def __init__(self, cin: int, cout: int, groups: int, emb: int = 0, scale_shift: bool = False,
                 resample: str | None = None):
        super().__init__()
        if scale_shift and not emb:
            raise ValueError("scale_shift needs an embedding (emb > 0)")
        if resample not in (None, "down", "up"):
            raise ValueError(f"resample: expected None, 'down' or 'up', got {resample!r}")
        self.n1, self.c1 = group_norm(cin, groups), nn.Conv3d(cin, cout, 3, padding=1)
        self.n2, self.c2 = group_norm(cout, groups), nn.Conv3d(cout, cout, 3, padding=1)
        self.emb = nn.Linear(emb, (2 if scale_shift else 1) * cout) if emb else None
        self.skip = nn.Conv3d(cin, cout, 1) if cin != cout else nn.Identity()
        self.scale_shift, self.resample = scale_shift, resample

    def forward(self, x, emb=None):
        h = F.silu(self.n1(x))
        if self.resample is not None:
            h, x = resample_box(h, self.resample), resample_box(x, self.resample)
        h = self.c1(h)
        if self.scale_shift:
            scale, shift = self.emb(emb)[:, :, None, None, None].chunk(2, 1)
            return self.skip(x) + self.c2(F.silu(self.n2(h) * (1 + scale) + shift))
        if self.emb is not None:
            h = h + self.emb(emb)[:, :, None, None, None]
        return self.skip(x) + self.c2(F.silu(self.n2(h)))
