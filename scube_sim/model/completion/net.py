"""The completion network: a dense 3D U-Net over the coarse evidence grid (`features`), per cell
an occupancy logit and label logits.

Dense, not sparse: completion must be able to put a voxel anywhere in the chunk (the far side of a
car, the wall behind a parked van), and the coarse grid (128 x 128 x 32 at 0.8 m) is half a
million cells. Levels halve the box; each has `blocks` residual blocks (`geometry.dense_nets`
`ResBlock3d`, GroupNorm); the decoder concatenates the encoder's features of the same level
(skip connections keep the observed cells' detail, which the merge trusts anyway).

Sub-cells (`CompletionModel.subcells` s > 1): a second head gives each cell s x s x s occupancy
logits at voxel_size / s, trained only inside the cells the truth holds occupied: where in a cell
the network would place its surface (the merge puts an added cell's Gaussians there instead of one
sphere at its centre). `train_subcells_only` freezes everything but that head, so that the cells'
occupancy and labels stay the warm start's (`train.init`) and a comparison measures the placement
alone.
"""

from __future__ import annotations

import torch
from pydantic import Field, field_validator, model_validator
from torch import nn
from torch.nn import functional as F

from ...config import StrictModel
from ...labels import NUM_LABELS
from ..nn.dense import ResBlock3d
from .features import FEATURES, INPUTS_V1

__all__ = ["CompletionModel", "CompletionNet"]


class CompletionModel(StrictModel):
    """features: the input channels the network reads, names from `features.FEATURES` (default:
    the first checkpoint's, `INPUTS_V1`); widths: channels per level (the first at the grid's
    resolution; each next one halves the box); blocks: residual blocks per level and side; groups:
    GroupNorm groups. The loss
    (`stage`): `label_weight` times the label cross-entropy on the occupied cells is added to the
    occupancy BCE, whose occupied cells weigh `pos_weight`; with `subcells` s > 1, `subcell_weight`
    times the sub-cells' BCE inside the truth's occupied cells (module docstring)."""

    features: list[str] = Field(default_factory=lambda: list(INPUTS_V1), min_length=1)
    widths: list[int] = Field(default_factory=lambda: [12, 24, 48, 64], min_length=1, max_length=6)
    blocks: int = Field(default=1, ge=1, le=4)
    groups: int = Field(default=4, ge=1, le=32)
    label_weight: float = Field(default=0.5, ge=0, le=100)
    pos_weight: float = Field(default=1.0, gt=0, le=100)
    subcells: int = Field(default=1, ge=1, le=4)
    subcell_weight: float = Field(default=1.0, ge=0, le=100)
    train_subcells_only: bool = False

    @model_validator(mode="before")
    @classmethod
    def _no_diffusion(cls, data):
        # checkpoints written while a diffusion variant existed store `diffusion: null`
        if isinstance(data, dict) and "diffusion" in data:
            if data["diffusion"] is not None:
                raise ValueError("diffusion: the diffusion completion was removed; a completion model is the "
                                 "deterministic network only")
            data = {k: v for k, v in data.items() if k != "diffusion"}
        return data

    @field_validator("features")
    @classmethod
    def _known(cls, v):
        unknown = [f for f in v if f not in FEATURES]
        if unknown or len(set(v)) != len(v):
            raise ValueError(f"features: each once, from {list(FEATURES)}, got {v}")
        return v

    @field_validator("widths")
    @classmethod
    def _positive(cls, v):
        if any(w < 1 or w > 512 for w in v):
            raise ValueError(f"widths: each from 1 to 512, got {v}")
        return v


class CompletionNet(nn.Module):
    """(B, len(FEATURES), X, Y, Z) -> (occupancy logits (B, X, Y, Z), label logits (B, NUM_LABELS,
    X, Y, Z)); X, Y, Z divisible by 2 ** (levels - 1). Reads the channels `cfg.features` names."""

    def __init__(self, cfg: CompletionModel):
        super().__init__()
        self.cfg = cfg
        w, g = cfg.widths, cfg.groups
        self.inputs = [FEATURES.index(f) for f in cfg.features]
        self.stem = nn.Conv3d(len(self.inputs), w[0], 3, padding=1)
        self.down = nn.ModuleList()
        self.enc = nn.ModuleList()
        for lvl, width in enumerate(w):
            cin = w[max(lvl - 1, 0)]
            self.down.append(nn.Identity() if lvl == 0 else nn.Conv3d(cin, width, 3, stride=2, padding=1))
            self.enc.append(nn.Sequential(*[ResBlock3d(width, width, g) for _ in range(cfg.blocks)]))
        self.dec = nn.ModuleList()
        for lvl in range(len(w) - 2, -1, -1):
            blocks = [ResBlock3d(w[lvl + 1] + w[lvl], w[lvl], g)]
            blocks += [ResBlock3d(w[lvl], w[lvl], g) for _ in range(cfg.blocks - 1)]
            self.dec.append(nn.Sequential(*blocks))
        self.head = nn.Conv3d(w[0], 1 + NUM_LABELS, 1)
        s = cfg.subcells
        self.subcell_head = (nn.Sequential(nn.Conv3d(w[0], 2 * w[0], 3, padding=1), nn.SiLU(),
                                           nn.Conv3d(2 * w[0], s ** 3, 1)) if s > 1 else None)
        if cfg.train_subcells_only:
            if self.subcell_head is None:
                raise ValueError("CompletionModel: train_subcells_only needs subcells > 1")
            for name, p in self.named_parameters():
                p.requires_grad_(name.startswith("subcell_head."))

    # parameters a warm start (`train.init`) from a checkpoint without sub-cells may lack
    init_optional_prefixes = ("subcell_head.",)

    @property
    def multiple(self) -> int:
        """The box's sides must be multiples of this."""
        return 2 ** (len(self.cfg.widths) - 1)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        occ, lab, _ = self.forward_with_subcells(x)
        return occ, lab

    def forward_with_subcells(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """As `forward`, and the sub-cells' occupancy logits (B, s X, s Y, s Z) at voxel_size / s
        (None where `subcells` is 1)."""
        if x.ndim != 5 or x.shape[1] != len(FEATURES):
            raise ValueError(f"CompletionNet: expected (B, {len(FEATURES)}, X, Y, Z), got {tuple(x.shape)}")
        if any(s % self.multiple for s in x.shape[2:]):
            raise ValueError(f"CompletionNet: box {tuple(x.shape[2:])} not divisible by {self.multiple}")
        h = self.stem(x[:, self.inputs])
        skips = []
        for down, enc in zip(self.down, self.enc):
            h = enc(down(h))
            skips.append(h)
        h = skips.pop()
        for dec in self.dec:
            skip = skips.pop()
            h = dec(torch.cat([F.interpolate(h, size=skip.shape[2:], mode="nearest"), skip], 1))
        out = self.head(F.silu(h))
        sub = None
        if self.subcell_head is not None:
            s = self.cfg.subcells
            b, _, nx, ny, nz = h.shape
            sub = self.subcell_head(F.silu(h)).reshape(b, s, s, s, nx, ny, nz)
            sub = sub.permute(0, 4, 1, 5, 2, 6, 3).reshape(b, nx * s, ny * s, nz * s)
        return out[:, 0], out[:, 1:], sub
