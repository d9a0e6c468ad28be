"""The procedural worlds as torch training data: a `torch.utils.data.Dataset` and its `collate`.

    cfg = DataConfig(image_size=(256, 384), cameras=CameraSelection(mode="drop"))
    ds = WorldsTorchDataset("DIR", split="train", config=cfg, train=True)
    ds.set_epoch(epoch)                              # before each epoch's DataLoader iterator
    loader = DataLoader(ds, batch_size=4, shuffle=True, num_workers=2, collate_fn=collate)

DIR is what `scube-sim worlds generate -o DIR` wrote (docs/worlds-dataset.md); samples are read
with `open_dataset("worlds", DIR, split=...)`.

An item (`ds[i]`) is a dict. Frames: chunk = the ego frame at the sample's instant T (x forward,
y left, z up, metres; voxel (i, j, k) spans CHUNK_CORNER + [ijk, ijk + 1) * voxel_size in it);
cameras are OpenCV (x right, y down, z forward); pixel (u, v) spans [u, u + 1) x [v, v + 1)
(its centre is (u + 0.5, v + 0.5)). N: cameras, H, W: the largest returned image size of the item
(smaller images are padded at the bottom and right; `valid` marks their pixels).

- ``images`` (N, 3, H, W) float32 sRGB in [0, 1] (0 in padding);
- ``intrinsics`` (N, 3, 3) float32 K in pixels of the returned image ([[fx, 0, cx], [0, fy, cy],
  [0, 0, 1]], principal point measured from the image's top-left corner);
- ``distortion`` (N, 5) float32 OpenCV Brown-Conrady [k1, k2, p1, p2, k3] on normalised
  coordinates (zeros for a pinhole camera; a resize leaves them unchanged);
- ``image_size`` (N, 2) int64 (height, width) of each returned image;
- ``valid`` (N, H, W) bool: inside the camera's image (not padding);
- ``cam_to_chunk`` (N, 4, 4) float32 camera-to-chunk poses (each camera at its own timestamp);
- ``times`` (N,) float32 seconds of each image after T;
- ``depth`` (N, H, W) float32 metres along the optical axis, inf on sky, 0 in padding;
- ``semantic`` (N, H, W) int64 label ids (`scube_sim.labels`), -1 in padding;
- ``sky`` (N, H, W) bool;
- ``instance`` (N, H, W) int64 instance ids (0: ground surfaces and sky; each other object its
  own id; a boxed object's, such as a vehicle's or pedestrian's, is its box's ``instance``), -1 in
  padding;
- ``camera_names`` list of N str; ``camera_index`` (N,) int64: each camera's index in the rig
  (rig randomisation may keep only some);
- ``fine_ijk`` (V, 3) int64, ``fine_labels`` (V,) int64 label ids, ``fine_visible`` (V,) bool,
  ``fine_voxel_size`` float metres; the same for ``coarse_*``;
- ``chunk_to_world`` (4, 4) float64; ``sample`` str (``<split>/<index:06d>``);
- ``eval_frames`` (only with ``DataConfig.eval_frames``): one dict per later instant (T+5, T+10
  frames: every stored instant after T, none before it) with the per-camera keys above (every
  camera, the same resize, never augmented) plus ``offset`` int (frames after T) and ``time``
  float (seconds after T);
- ``moving_instances`` (K,) int64: the instance ids of the boxes that move, those whose centre
  shifts more than MOVING_SHIFT_M between the loaded instants (with ``eval_frames``) or whose
  known speed exceeds MOVING_SPEED_MPS (the evaluation masks them out of novel views).

Training mode (``train=True``) keeps the cameras `CameraSelection` picks and augments each image
photometrically (`augment.photometric`; images only). Its randomness comes from a generator seeded
by (config.seed, epoch, index), so an item does not depend on worker count or order. The test split
is never trained on.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from pydantic import Field, PositiveInt, model_validator
from torch.utils.data import Dataset

from ...camera.frames import CameraImage
from ...camera.resize import camera_distortion, resize_bilinear, resize_nearest, scale_intrinsics
from ...config import StrictModel
from ...datasets import open_dataset
from ...errors import InputError
from ...transforms import invert_pose
from .augment import AugmentConfig, CameraSelection, choose_cameras, photometric

# Keys of an item (and of each eval frame) with one entry per camera, in camera order.
CAMERA_KEYS = ("images", "intrinsics", "distortion", "image_size", "valid", "cam_to_chunk", "times", "depth",
               "semantic", "sky", "instance", "camera_names", "camera_index")
# Padding values of the per-pixel maps outside a camera's image.
PAD = {"images": 0.0, "depth": 0.0, "semantic": -1, "sky": False, "instance": -1, "valid": False}
HELD_OUT_SPLIT = "test"
MOVING_SHIFT_M = 0.05
MOVING_SPEED_MPS = 0.1


class DataConfig(StrictModel):
    """How items are made (a trainer's YAML ``data:`` section).

    image_size: (height, width) in pixels every image is resized to; or image_scale: a factor of
    each image's stored size (size rounded like `Intrinsics.scaled`); neither: as stored. augment:
    the photometric augmentations; cameras: rig randomisation; both only in training mode.
    eval_frames: add the later instants (un-augmented) as ``eval_frames``; seed: of the training
    augmentation."""

    image_size: tuple[PositiveInt, PositiveInt] | None = None
    image_scale: float | None = Field(default=None, gt=0, le=8)
    augment: AugmentConfig = Field(default_factory=AugmentConfig)
    cameras: CameraSelection = Field(default_factory=CameraSelection)
    eval_frames: bool = False
    seed: int = Field(default=0, ge=0)

    @model_validator(mode="after")
    def _one_resize(self):
        if self.image_size is not None and self.image_scale is not None:
            raise ValueError("image_size and image_scale: give at most one")
        return self


# --- resizing ------------------------------------------------------------------------------------


def target_size(height: int, width: int, cfg: DataConfig) -> tuple[int, int]:
    """(height, width) of the returned image of a stored (height, width) one under `cfg`."""
    if cfg.image_size is not None:
        return int(cfg.image_size[0]), int(cfg.image_size[1])
    if cfg.image_scale is not None:
        return max(1, round(height * cfg.image_scale)), max(1, round(width * cfg.image_scale))
    return int(height), int(width)


# --- one sample -----------------------------------------------------------------------------------


def _camera(im: CameraImage, to_chunk: np.ndarray, t0: float, cfg: DataConfig, where: str) -> dict:
    """One camera's tensors at its returned size (not yet padded)."""
    for what in ("depth", "semantic", "sky", "instance"):
        if getattr(im, what) is None:
            why = " (instance maps came with worlds layout version 2)" if what == "instance" else ""
            raise InputError(f"{where}: camera {im.name!r} has no {what} map{why}")
    intr = im.intrinsics
    size = (intr.height, intr.width)
    new = target_size(*size, cfg)
    rgb = torch.from_numpy(np.array(im.image, np.uint8)).permute(2, 0, 1).to(torch.float32) / 255.0
    return {
        "images": resize_bilinear(rgb, new).clamp(0.0, 1.0),
        "intrinsics": torch.from_numpy(scale_intrinsics(intr.K, size, new).astype(np.float32)),
        "distortion": torch.from_numpy(camera_distortion(im).astype(np.float32)),
        "image_size": torch.tensor(new, dtype=torch.int64),
        # float64 until the end: world coordinates are large, the chunk's are small
        "cam_to_chunk": torch.from_numpy((to_chunk @ im.cam_to_world).astype(np.float32)),
        "times": torch.tensor(im.timestamp - t0, dtype=torch.float32),
        "depth": torch.from_numpy(resize_nearest(im.depth.astype(np.float32), new)),
        "semantic": torch.from_numpy(resize_nearest(im.semantic, new).astype(np.int64)),
        "sky": torch.from_numpy(resize_nearest(im.sky.astype(bool), new)),
        "instance": torch.from_numpy(resize_nearest(im.instance, new).astype(np.int64)),
        "name": im.name,
    }


def _stack(cams: list[dict], index: list[int]) -> dict:
    """Per-camera dicts -> the item's per-camera keys, the maps padded to the largest size."""
    h = max(int(c["image_size"][0]) for c in cams)
    w = max(int(c["image_size"][1]) for c in cams)
    out: dict = {"camera_names": [c["name"] for c in cams], "camera_index": torch.tensor(index, dtype=torch.int64)}
    for k in CAMERA_KEYS:
        if k in out:
            continue
        if k not in PAD:
            out[k] = torch.stack([c[k] for c in cams])
            continue
        maps = []
        for c in cams:
            ch, cw = int(c["image_size"][0]), int(c["image_size"][1])
            v = torch.ones((ch, cw), dtype=torch.bool) if k == "valid" else c[k]
            full = torch.full((*v.shape[:-2], h, w), PAD[k], dtype=v.dtype)
            full[..., :ch, :cw] = v
            maps.append(full)
        out[k] = torch.stack(maps)
    return out


def _voxels(prefix: str, g) -> dict:
    return {f"{prefix}_ijk": torch.from_numpy(g.ijk.astype(np.int64)),
            f"{prefix}_labels": torch.from_numpy(g.labels.astype(np.int64)),
            f"{prefix}_visible": torch.from_numpy(g.visible.astype(bool)),
            f"{prefix}_voxel_size": float(g.voxel_size)}


def moving_instances(timeline) -> torch.Tensor:
    """(K,) int64 sorted instance ids of the boxes that move over the instants of `timeline` (a
    list of frames with ``boxes``, world frame): centre shift > MOVING_SHIFT_M between any two, or
    known speed > MOVING_SPEED_MPS."""
    first: dict[int, np.ndarray] = {}
    moving: set[int] = set()
    for f in timeline:
        for b in f.boxes:
            if b.instance <= 0:
                continue
            if np.all(np.isfinite(b.velocity)) and float(np.linalg.norm(b.velocity)) > MOVING_SPEED_MPS:
                moving.add(int(b.instance))
            c0 = first.setdefault(int(b.instance), b.center)
            if float(np.linalg.norm(b.center - c0)) > MOVING_SHIFT_M:
                moving.add(int(b.instance))
    return torch.tensor(sorted(moving), dtype=torch.int64)


def item_generator(seed: int, epoch: int, index: int) -> torch.Generator:
    """The torch.Generator of item `index` in `epoch`: seeded by (seed, epoch, index) through
    numpy's SeedSequence, so neighbouring seeds, epochs and indices give unrelated streams."""
    for name, v in (("seed", seed), ("epoch", epoch), ("index", index)):
        if int(v) < 0:
            raise InputError(f"{name}: expected an integer >= 0, got {v}")
    state = np.random.SeedSequence([int(seed), int(epoch), int(index)]).generate_state(1, np.uint64)[0]
    return torch.Generator().manual_seed(int(state))


class WorldsTorchDataset(Dataset):
    """Items (see the module docstring) of one split of a worlds dataset folder.

    root: the folder `scube-sim worlds generate -o` wrote; split: train, val or test; config: a
    `DataConfig`; train: rig randomisation and photometric augmentation on (refused for the test
    split). Call `set_epoch` before each epoch to draw new augmentations."""

    def __init__(self, root: str | Path, *, split: str = "train", config: DataConfig | None = None,
                 train: bool = False):
        if train and split == HELD_OUT_SPLIT:
            raise InputError(f"split {split!r}: the held-out test split is never trained on; use train=False to "
                             f"evaluate on it, or split 'train' (or 'val') to train")
        self.config = config if config is not None else DataConfig()
        self.train = bool(train)
        self.split = split
        self.epoch = 0
        self.worlds = open_dataset("worlds", root, split=split, eval_frames=self.config.eval_frames)

    def __len__(self) -> int:
        return len(self.worlds)

    def set_epoch(self, epoch: int) -> None:
        """Items after this draw their augmentation from (seed, epoch, index). With a DataLoader,
        call it before creating the epoch's iterator (workers copy the dataset when they start;
        persistent workers keep the epoch they started with)."""
        if int(epoch) < 0:
            raise InputError(f"epoch: expected an integer >= 0, got {epoch}")
        self.epoch = int(epoch)

    def __getitem__(self, index: int) -> dict:
        s = self.worlds[index]  # an IndexError naming the split past the end
        index %= len(self)
        cfg = self.config
        gt = s.ground_truth
        to_chunk = invert_pose(gt.chunk_to_world)
        t0 = float(s.reference.time)  # T: the first instant unless the dataset stores some before it
        where = str(s.metadata.get("sample_dir", s.name))
        images = s.frames.images
        keep = list(range(len(images)))
        gen = None
        if self.train:
            gen = item_generator(cfg.seed, self.epoch, index)
            keep = choose_cameras([im.name for im in images], gen, cfg.cameras)
        cams = [_camera(images[i], to_chunk, t0, cfg, where) for i in keep]
        if self.train:
            for c in cams:  # photometric changes images only: depth, labels and poses stay
                c["images"] = photometric(c["images"], gen, cfg.augment)
        item = _stack(cams, keep)
        item.update(_voxels("fine", gt.fine))
        item.update(_voxels("coarse", gt.coarse))
        item["chunk_to_world"] = torch.from_numpy(np.asarray(gt.chunk_to_world, np.float64).copy())
        item["sample"] = s.name
        item["moving_instances"] = moving_instances(s.timeline)
        if cfg.eval_frames:
            item["eval_frames"] = []
            for f in s.later():  # after T (instants before T are converter context, not evaluation)
                ev = _stack([_camera(im, to_chunk, t0, cfg, where) for im in f.frames.images],
                            list(range(len(f.frames.images))))
                ev["offset"] = int(f.offset)
                ev["time"] = float(f.time - t0)
                item["eval_frames"].append(ev)
        return item


def collate(items: list[dict]) -> dict:
    """A batch of B items: per-camera keys (and ``sample``, ``moving_instances``, ``eval_frames``) as lists of
    length B (camera counts and image sizes differ between rigs); ``camera_counts`` (B,) int64;
    ``chunk_to_world`` (B, 4, 4) float64;
    the voxels concatenated in the sparse tensors' layout: ``<level>_coords`` (sum V, 4) int64
    [b, i, j, k], ``<level>_labels`` (sum V,) int64, ``<level>_visible`` (sum V,) bool,
    ``<level>_counts`` (B,) int64 voxels per item, ``<level>_voxel_size`` (B,) float64."""
    if not items:
        raise InputError("collate: expected at least one item")
    batch: dict = {k: [it[k] for it in items] for k in (*CAMERA_KEYS, "sample", "moving_instances")}
    batch["camera_counts"] = torch.tensor([len(it["camera_names"]) for it in items], dtype=torch.int64)
    batch["chunk_to_world"] = torch.stack([it["chunk_to_world"] for it in items])
    for level in ("fine", "coarse"):
        ijk = [it[f"{level}_ijk"] for it in items]
        b = torch.cat([torch.full((len(a), 1), i, dtype=torch.int64) for i, a in enumerate(ijk)])
        batch[f"{level}_coords"] = torch.cat([b, torch.cat(ijk)], dim=1)
        batch[f"{level}_labels"] = torch.cat([it[f"{level}_labels"] for it in items])
        batch[f"{level}_visible"] = torch.cat([it[f"{level}_visible"] for it in items])
        batch[f"{level}_counts"] = torch.tensor([len(a) for a in ijk], dtype=torch.int64)
        batch[f"{level}_voxel_size"] = torch.tensor([it[f"{level}_voxel_size"] for it in items], dtype=torch.float64)
    if any("eval_frames" in it for it in items):
        batch["eval_frames"] = [it.get("eval_frames", []) for it in items]
    return batch


__all__ = ["CAMERA_KEYS", "DataConfig", "WorldsTorchDataset", "collate", "item_generator", "target_size"]
