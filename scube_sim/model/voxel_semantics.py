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

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field
from torch import nn
from torch.utils.data import Dataset

from ..config import StrictModel
from ..datasets import open_dataset
from ..labels import LABEL_NAMES
from ..worlds.groundtruth import CHUNK_CORNER
from .sparse import SparseTensor, SparseUNet, site_order
from .stages import Stage, register_stage

NUM_LABELS = len(LABEL_NAMES)


class VoxelSemanticsModel(StrictModel):
    """The sparse U-Net: widths per level (depth = their count), residual blocks per level, norm."""

    widths: tuple[int, ...] = Field(default=(16, 32, 64), min_length=1)
    blocks: int = Field(default=1, ge=1)
    norm: str = Field(default="batch", pattern="^(batch|group|none)$")


class VoxelSemanticsData(StrictModel):
    """Which grid, and the part of the chunk kept (chunk frame, metres: x_min, y_min, z_min,
    x_max, y_max, z_max; None: the whole chunk)."""

    level: str = Field(default="coarse", pattern="^(fine|coarse)$")
    region: tuple[float, float, float, float, float, float] | None = None


class VoxelGridDataset(Dataset):
    """The ground-truth grids of one split: item = {'ijk' (V, 3) int64, 'labels' (V,) int64,
    'voxel_size' float, 'z' (V,) float32 voxel-centre height in metres (chunk frame)}."""

    def __init__(self, root: Path, split: str, cfg: VoxelSemanticsData):
        self.ds = open_dataset("worlds", root, split=split, eval_frames=False)
        self.cfg = cfg

    def __len__(self) -> int:
        return len(self.ds)

    def __getitem__(self, index: int) -> dict:
        gt = self.ds[index].ground_truth
        grid = gt.fine if self.cfg.level == "fine" else gt.coarse
        ijk = grid.ijk.astype(np.int64)
        centers = CHUNK_CORNER + (ijk + 0.5) * grid.voxel_size
        keep = np.ones(len(ijk), bool)
        if self.cfg.region is not None:
            lo, hi = np.asarray(self.cfg.region[:3]), np.asarray(self.cfg.region[3:])
            keep = np.all((centers >= lo) & (centers < hi), axis=1)
        return {"ijk": torch.from_numpy(ijk[keep]), "labels": torch.from_numpy(grid.labels[keep].astype(np.int64)),
                "z": torch.from_numpy(centers[keep, 2].astype(np.float32)), "voxel_size": float(grid.voxel_size)}


def collate_grids(items: list[dict]) -> dict:
    """Items -> {'coords' (sum V, 4) int64 [b, i, j, k], 'feats' (sum V, 2), 'labels' (sum V,),
    'batch_size' int}, sorted in the sparse grid's site order."""
    coords = torch.cat([torch.cat([torch.full((len(it["ijk"]), 1), b, dtype=torch.int64), it["ijk"]], 1)
                        for b, it in enumerate(items)])
    z = torch.cat([it["z"] for it in items])
    feats = torch.stack([torch.ones_like(z), z / 10.0], 1)
    labels = torch.cat([it["labels"] for it in items])
    order = site_order(coords)
    return {"coords": coords[order], "feats": feats[order], "labels": labels[order], "batch_size": len(items)}


class VoxelSemanticsNet(nn.Module):
    def __init__(self, cfg: VoxelSemanticsModel):
        super().__init__()
        self.unet = SparseUNet(2, NUM_LABELS, widths=cfg.widths, blocks=cfg.blocks, norm=cfg.norm)

    def forward(self, batch: dict) -> torch.Tensor:
        """A collated batch (sites in grid order) -> (V, L) label logits, one row per site."""
        x = SparseTensor.from_coords(batch["coords"], batch["feats"], batch_size=batch["batch_size"])
        return self.unet(x).feats


class VoxelSemanticsStage(Stage):
    name = "voxel-semantics"
    model_config = VoxelSemanticsModel
    data_config = VoxelSemanticsData
    primary_metric = "miou"
    higher_is_better = True

    def build_model(self, model_cfg: VoxelSemanticsModel) -> nn.Module:
        return VoxelSemanticsNet(model_cfg)

    def dataset(self, data_dir: Path, data_cfg: VoxelSemanticsData, split: str, seed: int) -> Dataset:
        return VoxelGridDataset(Path(data_dir), split, data_cfg)

    def collate(self, samples: list) -> dict:
        return collate_grids(samples)

    def loss(self, model: nn.Module, batch: dict) -> tuple[torch.Tensor, dict[str, float]]:
        logits, labels, b = model(batch), batch["labels"], batch["coords"][:, 0]
        per_voxel = F.cross_entropy(logits, labels, reduction="none")
        n = torch.bincount(b, minlength=batch["batch_size"]).clamp_min(1).to(per_voxel.dtype)
        per_sample = per_voxel.new_zeros(batch["batch_size"]).index_add(0, b, per_voxel) / n
        acc = float((logits.argmax(1) == labels).float().mean()) if len(labels) else 0.0
        return per_sample.mean(), {"accuracy": acc}

    def evaluate(self, model: nn.Module, batches: Iterable[dict]) -> dict[str, float]:
        conf = torch.zeros(NUM_LABELS, NUM_LABELS, dtype=torch.int64)
        for batch in batches:
            logits, labels = model(batch), batch["labels"]
            conf += torch.bincount(labels * NUM_LABELS + logits.argmax(1), minlength=NUM_LABELS ** 2
                                   ).reshape(NUM_LABELS, NUM_LABELS)
        return semantic_metrics(conf)


def semantic_metrics(conf: torch.Tensor) -> dict[str, float]:
    """conf[true, predicted] counts -> {'miou': mean IoU over labels that occur in either,
    'accuracy', and 'iou_<label>' per such label}."""
    tp = conf.diag().double()
    union = conf.sum(0).double() + conf.sum(1).double() - tp
    present = union > 0
    iou = torch.where(present, tp / union.clamp_min(1), torch.zeros_like(tp))
    out = {"miou": float(iou[present].mean()) if bool(present.any()) else 0.0,
           "accuracy": float(tp.sum() / conf.sum().clamp_min(1))}
    for i in torch.nonzero(present).squeeze(1).tolist():
        out[f"iou_{LABEL_NAMES[i]}"] = float(iou[i])
    return out


register_stage(VoxelSemanticsStage())
