"""The geometry stage's data: the level's grid over its region (`GeometryDataConfig`) and worlds
samples with their ground-truth voxels cut to that box (`GeometryDataset`).

Frames: chunk (x forward, y left, z up, metres; `CHUNK_CORNER`); voxel (i, j, k) of the level's
box spans region[:3] + [ijk, ijk + 1) * voxel_size.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from pydantic import Field, model_validator
from torch.utils.data import Dataset

from ...config import StrictModel
from ...errors import InputError
from ...worlds.groundtruth import CHUNK_CORNER, CHUNK_SIZE
from ..data.augment import AugmentConfig, CameraSelection
from ..data.worlds import DataConfig, WorldsTorchDataset, item_generator
from ..nn.lifting import LiftGrid, grid_in_box

# The cpu profile's box: the whole 102.4 m chunk in x and y, the lowest 25.6 m in z.
DEFAULT_REGION = (float(CHUNK_CORNER[0]), float(CHUNK_CORNER[1]), float(CHUNK_CORNER[2]),
                  float(CHUNK_CORNER[0] + CHUNK_SIZE), float(CHUNK_CORNER[1] + CHUNK_SIZE),
                  float(CHUNK_CORNER[2] + 25.6))


# ---------------------------------------------------------------------------- configs
class GeometryDataConfig(StrictModel):
    """The level (`coarse` | `fine`) and its grid: `voxel_size` metres (a stored grid coarsened by
    an integer factor: the coarse level reads the stored coarse grid, the fine level the stored
    fine one) over `region` (x_min, y_min, z_min, x_max, y_max, z_max, chunk frame metres, a whole
    number of `coarse_voxel_size` voxels from CHUNK_CORNER). `coarse_voxel_size` (None: the coarse
    level's voxel_size) is the grid the images are lifted into, and the fine level's latent grid.
    `crop`: training items keep a random `crop` x `crop` metre window in x, y (whole coarse
    voxels; the fine level trains on windows, the whole box is evaluated). The input images at
    `image_scale` of the stored ones; in training, rig randomisation and photometric augmentation
    of the inputs."""

    level: str = Field(default="coarse", pattern="^(coarse|fine)$")
    voxel_size: float = Field(default=0.8, gt=0)
    coarse_voxel_size: float | None = Field(default=None, gt=0)
    region: tuple[float, float, float, float, float, float] = DEFAULT_REGION
    crop: float | None = Field(default=None, gt=0)
    image_scale: float = Field(default=0.67, gt=0, le=1)
    augment: AugmentConfig = Field(default_factory=AugmentConfig)
    cameras: CameraSelection = Field(default_factory=CameraSelection)

    @property
    def lift_voxel_size(self) -> float:
        return float(self.coarse_voxel_size if self.coarse_voxel_size is not None else self.voxel_size)

    @model_validator(mode="after")
    def _whole_voxels(self):
        vs = self.lift_voxel_size
        if self.level == "coarse" and abs(vs - self.voxel_size) > 1e-9:
            raise ValueError(f"coarse level: coarse_voxel_size ({vs}) must equal voxel_size ({self.voxel_size})")
        ratio = vs / self.voxel_size
        if ratio < 1 or abs(ratio - round(ratio)) > 1e-6:
            raise ValueError(f"coarse_voxel_size ({vs}) must be a whole multiple of voxel_size ({self.voxel_size})")
        lo, hi = np.array(self.region[:3]), np.array(self.region[3:])
        for name, v in (("region's corner", (lo - CHUNK_CORNER) / vs), ("region's size", (hi - lo) / vs)):
            if np.any(np.abs(v - np.round(v)) > 1e-6) or (name == "region's size" and np.any(np.round(v) < 1)):
                raise ValueError(f"{name} must be a positive whole number of {vs} m voxels "
                                 f"(from CHUNK_CORNER {CHUNK_CORNER.tolist()}), got region {list(self.region)}")
        if self.crop is not None:
            c = self.crop / vs
            if abs(c - round(c)) > 1e-6 or self.crop > min(hi[:2] - lo[:2]) + 1e-9:
                raise ValueError(f"crop ({self.crop} m) must be a whole number of {vs} m voxels and fit the region")
        return self

    def grid(self, size: float | None = None, lo=None, hi=None) -> LiftGrid:
        """The box (default: the region) at `size` metres (default: the lifting grid's)."""
        lo = np.array(self.region[:3]) if lo is None else np.asarray(lo, float)
        hi = np.array(self.region[3:]) if hi is None else np.asarray(hi, float)
        size = self.lift_voxel_size if size is None else size
        dims = np.round((hi - lo) / size).astype(int)
        return LiftGrid(tuple(float(v) for v in lo), float(size), tuple(int(d) for d in dims))


# ---------------------------------------------------------------------------- data
class GeometryDataset(Dataset):
    """Worlds samples as the geometry stage reads them: the `WorldsTorchDataset` item (images at
    `image_scale`, cameras, depth, valid) plus ``gt_ijk`` (V, 3) int64 the level's ground-truth
    voxels inside the box (relative to its corner), ``gt_labels`` (V,) int64, ``gt_visible`` (V,)
    bool, the same at the coarse voxel size as ``coarse_gt_*`` (the fine level's latent grid),
    ``lift_grid`` the box at the lifting voxel size and ``level``. The box is the region, or in
    training a random `crop` window of it (seeded by seed, epoch and index). Training items keep
    the cameras `cameras` picks and augment the input images."""

    def __init__(self, root: Path, split: str, cfg: GeometryDataConfig, seed: int = 0):
        self.cfg = cfg
        self.seed = seed
        self.train = split == "train"
        self.base = WorldsTorchDataset(root, split=split, train=self.train,
                                       config=DataConfig(image_scale=cfg.image_scale, seed=seed,
                                                         augment=cfg.augment, cameras=cfg.cameras))

    @property
    def grid(self) -> LiftGrid:
        return self.cfg.grid()

    def __len__(self) -> int:
        return len(self.base)

    def set_epoch(self, epoch: int) -> None:
        self.base.set_epoch(epoch)

    def box(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) of item `index`'s box, chunk frame metres."""
        lo, hi = np.array(self.cfg.region[:3]), np.array(self.cfg.region[3:])
        if self.cfg.crop is None or not self.train:
            return lo, hi
        vs = self.cfg.lift_voxel_size
        gen = item_generator(self.seed + 3, self.base.epoch, index % len(self))
        room = np.round((hi[:2] - lo[:2] - self.cfg.crop) / vs).astype(int)
        shift = [int(torch.randint(0, int(r) + 1, (1,), generator=gen)) for r in room]
        lo = lo.copy()
        lo[:2] += np.array(shift) * vs
        hi = hi.copy()
        hi[:2] = lo[:2] + self.cfg.crop
        return lo, hi

    def __getitem__(self, index: int) -> dict:
        item = self.base[index]
        lo, hi = self.box(index)
        cfg = self.cfg
        for prefix, level, size in (("gt", cfg.level, cfg.voxel_size), ("coarse_gt", "coarse", cfg.lift_voxel_size)):
            stored = float(item[f"{level}_voxel_size"])
            ratio = size / stored
            factor = int(round(ratio))
            if factor < 1 or abs(ratio - factor) > 1e-6:
                raise InputError(f"{item['sample']}: voxel size {size} m is not a whole multiple of the stored "
                                 f"{level} grid's {stored} m")
            gt = grid_in_box(item[f"{level}_ijk"], item[f"{level}_labels"], item[f"{level}_visible"], factor,
                             stored, cfg.grid(size, lo, hi))
            item[f"{prefix}_ijk"], item[f"{prefix}_labels"], item[f"{prefix}_visible"] = gt
        item["lift_grid"] = cfg.grid(None, lo, hi)
        item["gt_grid"] = cfg.grid(cfg.voxel_size, lo, hi)
        item["level"] = cfg.level
        return item


def dense_target(ijk: torch.Tensor, labels: torch.Tensor, dims) -> tuple[torch.Tensor, torch.Tensor]:
    """(occupancy (X, Y, Z) float, labels (X, Y, Z) long, -1 where empty) of a box's voxels."""
    occ = torch.zeros(tuple(dims), dtype=torch.float32)
    lab = torch.full(tuple(dims), -1, dtype=torch.int64)
    if len(ijk):
        occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = 1.0
        lab[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = labels
    return occ, lab


