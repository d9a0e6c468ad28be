"""The voxel-semantics stage's data: worlds samples' ground-truth grids as sparse tensors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from pydantic import Field
from torch.utils.data import Dataset

from ...config import StrictModel
from ...datasets import open_dataset
from ...worlds.groundtruth import CHUNK_CORNER
from ..nn.sparse import site_order


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


