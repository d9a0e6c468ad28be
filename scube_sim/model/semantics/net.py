"""Stage `voxel-semantics`: the semantic label of each ground-truth voxel from the grid's shape.

The foundation's end-to-end stage: worlds samples -> sparse grid -> `SparseUNet` -> per-voxel
label logits, trained with the one trainer and evaluated by mean IoU. It is the semantic head the
converter's geometry stage needs on its predicted grids (the paper's voxels carry semantic
logits), trained here on the ground-truth grids alone, so that the sparse stack, the data and the
trainer are exercised together on real worlds data before either converter stage exists.

Input per voxel: a constant 1 and the voxel centre's height (z, chunk frame, in units of 10 m),
nothing else: the labels must come from the shape of the neighbourhood. Output: one logit per
label of `scube_sim.labels`. Loss: cross-entropy, the mean over each sample's voxels, then over
the samples (the trainer's contract). Metrics: mean IoU over the labels present in the split's
ground truth or predictions (primary), and voxel accuracy.
"""

from __future__ import annotations

import torch
from pydantic import Field
from torch import nn

from ...config import StrictModel
from ...labels import NUM_LABELS
from ..nn.sparse import SparseTensor, SparseUNet


class VoxelSemanticsModel(StrictModel):
    """The sparse U-Net: widths per level (depth = their count), residual blocks per level, norm."""

    widths: tuple[int, ...] = Field(default=(16, 32, 64), min_length=1)
    blocks: int = Field(default=1, ge=1)
    norm: str = Field(default="batch", pattern="^(batch|group|none)$")


class VoxelSemanticsNet(nn.Module):
    def __init__(self, cfg: VoxelSemanticsModel):
        super().__init__()
        self.unet = SparseUNet(2, NUM_LABELS, widths=cfg.widths, blocks=cfg.blocks, norm=cfg.norm)

    def forward(self, batch: dict) -> torch.Tensor:
        """A collated batch (sites in grid order) -> (V, L) label logits, one row per site."""
        x = SparseTensor.from_coords(batch["coords"], batch["feats"], batch_size=batch["batch_size"])
        return self.unet(x).feats


