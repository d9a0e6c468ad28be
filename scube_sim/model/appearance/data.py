"""The appearance stage's data: worlds samples with the input views at T and the views the loss and
the metrics use (the paper's novel-view instants T+5, T+10 are never in the loss).
"""

from __future__ import annotations

from pathlib import Path

import torch
from pydantic import Field, field_validator
from torch.utils.data import Dataset

from ...config import StrictModel
from ...errors import InputError
from ...worlds.dataset import EVAL_OFFSETS
from ...worlds.groundtruth import CHUNK_CORNER
from ..data.augment import AugmentConfig, photometric
from ..data.worlds import DataConfig, WorldsTorchDataset, item_generator
from ..nn.encoding import majority_labels
from .net import first_hit_voxels

NO_AUGMENT = AugmentConfig(**{k: {"p": 0.0} for k in ("color_jitter", "exposure", "blur", "noise", "jpeg")})




class AppearanceDataConfig(StrictModel):
    """Which ground-truth grid (level fine | coarse, optionally coarsened by `coarsen`: fine x 2
    is 0.2 m in the worlds), the part of the chunk kept (x_min, y_min, z_min, x_max, y_max, z_max,
    chunk frame metres; None: all), the image scale of the stored images, and the views rendered
    for the loss: the cameras at the stored instants `loss_offsets` (frames after T; 0 is the
    input instant; never the evaluation's T+5 and T+10, so a dataset for it is generated with
    e.g. ``--frame-offsets 0,2,7``), all of them or `train_views` drawn per item (seeded by seed,
    epoch and index: rendering is most of a step's time on a CPU). Moving actors are masked out
    of the loss at the instants after T (the grid holds them where they were at T).
    `augment`: the photometric augmentation of the network's *input* images in training (the
    rendered views are compared with the clean images). `eval_cameras`: the cameras evaluated,
    ``front`` (the three forward-facing ones, the paper's protocol) or ``all``."""

    level: str = Field(default="coarse", pattern="^(fine|coarse)$")
    coarsen: int = Field(default=1, ge=1, le=8)
    region: tuple[float, float, float, float, float, float] | None = None
    image_scale: float = Field(default=0.5, gt=0, le=1)
    eval_frames: bool = False
    loss_offsets: list[int] = Field(default_factory=lambda: [0], min_length=1)
    train_views: int | None = Field(default=None, ge=1)  # views rendered per training item (None: all)
    augment: AugmentConfig = Field(default_factory=AugmentConfig)  # of the network's input images only
    eval_cameras: str = Field(default="front", pattern="^(front|all)$")

    @field_validator("loss_offsets")
    @classmethod
    def _not_the_evaluation(cls, v: list[int]) -> list[int]:
        bad = sorted(set(v) & set(EVAL_OFFSETS))
        if bad or any(k < 0 for k in v) or len(set(v)) != len(v):
            raise ValueError(f"expected distinct frame offsets >= 0 other than the evaluation's "
                             f"{list(EVAL_OFFSETS)}, got {v}")
        return sorted(v)


# ---------------------------------------------------------------------------- data
class AppearanceDataset(Dataset):
    """Worlds samples with a ground-truth grid and each input camera's first-hit voxels.

    Item: the `WorldsTorchDataset` item (images at `image_scale`, cameras, sky masks, ...) plus
    ``ijk`` (V, 3) int64 voxels (chunk frame, origin CHUNK_CORNER), ``voxel_size``, and ``hits``
    (N, h, w) int64, the row of ``ijk`` each half-resolution feature pixel's ray enters first (-1:
    none), ``loss_views`` the (frame offset, camera index) pairs the loss renders, ``eval_cameras``
    the config's choice, and in training ``input_images``, the
    network's augmented inputs (``images`` stay clean: the loss's targets). Pinhole and OpenCV
    cameras."""

    def __init__(self, root: Path, split: str, cfg: AppearanceDataConfig, seed: int = 0):
        self.cfg = cfg
        self.seed = seed
        self.train = split == "train"
        # clean images from the base (they are the loss's targets); inputs are augmented here
        later = self.train and any(k != 0 for k in cfg.loss_offsets)
        self.base = WorldsTorchDataset(root, split=split, train=split == "train",
                                       config=DataConfig(image_scale=cfg.image_scale,
                                                         eval_frames=cfg.eval_frames or later,
                                                         seed=seed, augment=NO_AUGMENT))

    def __len__(self) -> int:
        return len(self.base)

    def set_epoch(self, epoch: int) -> None:
        self.base.set_epoch(epoch)

    def __getitem__(self, index: int) -> dict:
        item = self.base[index]
        ijk = item[f"{self.cfg.level}_ijk"]
        labels = item[f"{self.cfg.level}_labels"].to(torch.int64)
        vs = float(item[f"{self.cfg.level}_voxel_size"])
        if self.cfg.coarsen > 1:
            ijk, inv = torch.unique(ijk // self.cfg.coarsen, dim=0, return_inverse=True)
            labels = majority_labels(inv, labels, len(ijk))
            vs *= self.cfg.coarsen
        if self.cfg.region is not None:
            centres = torch.as_tensor(CHUNK_CORNER) + (ijk.double() + 0.5) * vs
            lo, hi = torch.tensor(self.cfg.region[:3]), torch.tensor(self.cfg.region[3:])
            inside = ((centres >= lo) & (centres < hi)).all(1)
            ijk, labels = ijk[inside], labels[inside]
        item["ijk"], item["labels"], item["voxel_size"] = ijk, labels, vs
        item["hits"] = first_hit_voxels(item, ijk, vs)
        offsets = self.cfg.loss_offsets if self.train else [0]
        views = [(k, i) for k in offsets for i in range(frame_at(item, k)["images"].shape[0])]
        if self.train and self.cfg.train_views is not None and self.cfg.train_views < len(views):
            gen = item_generator(self.seed + 1, self.base.epoch, index % len(self))  # not the augmentation's stream
            views = [views[j] for j in sorted(torch.randperm(len(views), generator=gen)[: self.cfg.train_views].tolist())]
        item["loss_views"] = views
        item["eval_cameras"] = self.cfg.eval_cameras
        if self.train:
            gen = item_generator(self.seed + 2, self.base.epoch, index % len(self))
            item["input_images"] = torch.stack([photometric(im, gen, self.cfg.augment) for im in item["images"]])
        return item


def frame_at(item: dict, offset: int) -> dict:
    """The item's cameras at frame offset `offset` (0: the item itself, else its ``eval_frames``
    entry); an error naming the sample and the stored offsets when it has none there."""
    if offset == 0:
        return item
    for f in item.get("eval_frames", []):
        if f["offset"] == offset:
            return f
    have = [0] + [f["offset"] for f in item.get("eval_frames", [])]
    raise InputError(f"sample {item.get('sample')}: no frame at offset {offset} (stored: {have}); generate the "
                     f"training split with `scube-sim worlds generate --frame-offsets ...` that include it")


def static_mask(frame: dict, i: int, moving: torch.Tensor) -> torch.Tensor:
    """(H, W) bool of camera i of `frame`: inside the image and not on a moving actor."""
    hh, ww = (int(s) for s in frame["image_size"][i])
    inst = frame["instance"][i, :hh, :ww]
    return frame["valid"][i, :hh, :ww] & ~torch.isin(inst, moving)


def is_front_camera(name: str) -> bool:
    """The forward-facing cameras of the shipped rigs: waymo-5 FRONT, FRONT_LEFT, FRONT_RIGHT;
    nuscenes-6 CAM_FRONT, CAM_FRONT_LEFT, CAM_FRONT_RIGHT."""
    return "FRONT" in name.upper()


