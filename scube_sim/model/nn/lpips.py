"""LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual
Metric", v0.1) from weight files a user already has: nothing is downloaded.

The distance between two images is, summed over five layers of an ImageNet backbone, the spatial
mean of a learnt channel weighting of the squared difference of their unit-normalised features.
Two files make it up, in the layouts their projects publish them:

- the backbone: torchvision's ImageNet state dict (``alexnet-owt-7be5be79.pth`` or
  ``vgg16-397923af.pth``; keys ``features.<i>.weight`` / ``.bias``, the ``classifier`` is ignored);
- the linear layers: the ``lpips`` package's ``weights/v0.1/alex.pth`` or ``vgg.pth`` (keys
  ``lin<k>.model.1.weight``, (1, C_k, 1, 1)).

Both are read with ``torch.load(weights_only=True)`` (no arbitrary unpickling) and checked key by
key and shape by shape. Images are (B, 3, H, W) in [0, 1]; masks (B, H, W) choose the pixels each
layer's spatial mean runs over (all of them without one), so padding and moving actors are left
out as in the other losses.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from pydantic import Field
from torch import nn

from ...config import StrictModel
from ...errors import InputError

# The LPIPS input normalisation (its ScalingLayer), on images in [-1, 1].
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
# torchvision's `features` layers: ("conv", in, out, kernel, stride, padding) | ("relu",) | ("pool",
# kernel, stride); and the indices after which LPIPS taps a feature map (its five slices' ends).
ARCHS = {
    "alex": {
        "layers": [("conv", 3, 64, 11, 4, 2), ("relu",), ("pool", 3, 2), ("conv", 64, 192, 5, 1, 2), ("relu",),
                   ("pool", 3, 2), ("conv", 192, 384, 3, 1, 1), ("relu",), ("conv", 384, 256, 3, 1, 1), ("relu",),
                   ("conv", 256, 256, 3, 1, 1), ("relu",)],
        "taps": (1, 4, 7, 9, 11),
    },
    "vgg": {
        "layers": [("conv", 3, 64, 3, 1, 1), ("relu",), ("conv", 64, 64, 3, 1, 1), ("relu",), ("pool", 2, 2),
                   ("conv", 64, 128, 3, 1, 1), ("relu",), ("conv", 128, 128, 3, 1, 1), ("relu",), ("pool", 2, 2),
                   ("conv", 128, 256, 3, 1, 1), ("relu",), ("conv", 256, 256, 3, 1, 1), ("relu",),
                   ("conv", 256, 256, 3, 1, 1), ("relu",), ("pool", 2, 2),
                   ("conv", 256, 512, 3, 1, 1), ("relu",), ("conv", 512, 512, 3, 1, 1), ("relu",),
                   ("conv", 512, 512, 3, 1, 1), ("relu",), ("pool", 2, 2),
                   ("conv", 512, 512, 3, 1, 1), ("relu",), ("conv", 512, 512, 3, 1, 1), ("relu",),
                   ("conv", 512, 512, 3, 1, 1), ("relu",)],
        "taps": (3, 8, 15, 22, 29),
    },
}


class LPIPSConfig(StrictModel):
    """The LPIPS term of the appearance loss (paper: weight 0.6): `net` alex | vgg, the two weight
    files (module docstring; a relative path is taken from the working directory) and its weight."""

    net: str = Field(default="alex", pattern="^(alex|vgg)$")
    backbone: str
    linear: str
    weight: float = Field(default=0.6, ge=0)


def tap_channels(net: str) -> list[int]:
    """The channels of the five tapped feature maps of `net`."""
    layers = ARCHS[net]["layers"]
    return [next(layers[j][2] for j in range(i, -1, -1) if layers[j][0] == "conv") for i in ARCHS[net]["taps"]]


class LPIPS(nn.Module):
    """The frozen LPIPS network of `net` (random weights until `load_weights`)."""

    def __init__(self, net: str = "alex"):
        super().__init__()
        if net not in ARCHS:
            raise InputError(f"lpips net: expected one of {sorted(ARCHS)}, got {net!r}")
        self.net = net
        self.features = nn.Sequential(*[
            nn.Conv2d(spec[1], spec[2], spec[3], spec[4], spec[5]) if spec[0] == "conv"
            else nn.ReLU() if spec[0] == "relu" else nn.MaxPool2d(spec[1], spec[2])
            for spec in ARCHS[net]["layers"]])
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in tap_channels(net))
        self.register_buffer("shift", torch.tensor(SHIFT)[None, :, None, None], persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE)[None, :, None, None], persistent=False)
        for p in self.parameters():
            p.requires_grad_(False)
        self.eval()

    def load_weights(self, backbone: str | Path, linear: str | Path) -> "LPIPS":
        """Loads the torchvision backbone and the lpips linear layers (module docstring)."""
        bb = _read(backbone, "backbone")
        want = {f"features.{k}": v for k, v in self.features.state_dict().items()}
        self.features.load_state_dict({k[len("features."):]: _take(bb, k, v.shape, backbone) for k, v in want.items()})
        lin = _read(linear, "linear")
        self.lins.load_state_dict({f"{k}.weight": _take(lin, f"lin{k}.model.1.weight", m.weight.shape, linear)
                                   for k, m in enumerate(self.lins)})
        return self

    def forward(self, a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """a, b (B, 3, H, W) in [0, 1]; mask (B, H, W) bool or float -> (B,) distances."""
        if a.shape != b.shape or a.ndim != 4 or a.shape[1] != 3:
            raise InputError(f"lpips: expected two (B, 3, H, W) images of one shape, got {tuple(a.shape)} "
                             f"and {tuple(b.shape)}")
        x = torch.cat([a, b]).to(self.shift.dtype) * 2 - 1
        x = (x - self.shift) / self.scale
        taps = set(ARCHS[self.net]["taps"])
        m = None if mask is None else mask.to(x.dtype)[:, None]
        total = x.new_zeros(a.shape[0])
        k = 0
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i not in taps:
                continue
            fa, fb = _unit(x[: a.shape[0]]), _unit(x[a.shape[0]:])
            d = self.lins[k]((fa - fb) ** 2)[:, 0]  # (B, h, w)
            if m is None:
                total = total + d.mean((1, 2))
            else:  # the share of kept pixels under each feature pixel weighs it
                w = F.adaptive_avg_pool2d(m, d.shape[1:])[:, 0]
                total = total + (d * w).sum((1, 2)) / w.sum((1, 2)).clamp_min(1e-12)
            k += 1
        return total


def _unit(x: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    return x / (x.pow(2).sum(1, keepdim=True).sqrt() + eps)


def _read(path: str | Path, what: str) -> dict:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"lpips {what} weights {p}: no such file")
    try:
        sd = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # a pickle of anything but tensors is refused here
        raise InputError(f"lpips {what} weights {p}: not a tensor state dict ({type(e).__name__}: {e})") from e
    if not isinstance(sd, dict):
        raise InputError(f"lpips {what} weights {p}: expected a state dict (name -> tensor), got {type(sd).__name__}")
    return sd


def _take(sd: dict, key: str, shape: torch.Size, path) -> torch.Tensor:
    if key not in sd:
        raise InputError(f"lpips weights {path}: no key {key!r} (expected the layout in scube_sim/model/lpips.py)")
    t = sd[key]
    if not isinstance(t, torch.Tensor) or tuple(t.shape) != tuple(shape):
        got = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
        raise InputError(f"lpips weights {path}: {key!r} is {got}, expected {tuple(shape)}")
    return t.float()


def load_lpips(cfg: LPIPSConfig) -> LPIPS:
    """The configured network with its weights loaded."""
    return LPIPS(cfg.net).load_weights(cfg.backbone, cfg.linear)
