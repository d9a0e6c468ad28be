"""Camera frames for the converter: a sample's frames from a dataset (`open_frames`), the item a
stage's network reads from them (`network_inputs`), and the record of the instants used
(`context_record`). Frames: the chunk frame is the frames' ego frame at their reference instant
(x forward, y left, z up, metres).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..camera.frames import Frames, chunk_to_world
from ..camera.resize import camera_distortion, resize_bilinear, resize_nearest, scale_intrinsics
from ..datasets import adapter_name, open_dataset
from ..datasets.base import frames_with_context
from ..datasets.worlds import DATASET_FILE as WORLDS_HEADER
from ..datasets.worlds import META_FILE as WORLDS_SAMPLE_META
from ..errors import InputError
from ..transforms import invert_pose
from .profile import StageProfile


def open_frames(path: str | Path, dataset: str | None = None, sample: int = 0, context: int = 0) -> Frames:
    """The camera frames of one sample: `path` a worlds sample folder (DIR/<split>/NNNNNN) or, with
    `dataset`, any adapter's folder (`datasets.open_dataset`) and its sample index `sample`.
    context: with it, the frames of up to `context` instants before and after the sample in the
    same log (`datasets.frames_with_context`: the source's instants, never across a scene)."""
    if isinstance(context, bool) or not isinstance(context, (int, np.integer)) or context < 0:
        raise InputError(f"context: expected a number of instants >= 0, got {context!r}")
    path = Path(path)
    if dataset is None:
        if (path / WORLDS_SAMPLE_META).is_file() and (path.parent.parent / WORLDS_HEADER).is_file():
            ds = open_dataset("worlds", path.parent.parent, split=path.parent.name, eval_frames=False)
            names = [d.name for d in ds.sample_dirs]
            dataset, sample = "worlds", names.index(path.name)
        else:
            raise InputError(f"{path}: not a worlds sample folder (DIR/<split>/NNNNNN with {WORLDS_SAMPLE_META}); "
                             f"name the format of other folders with --dataset (nuscenes, kitti_raw, waymo, folder, "
                             f"worlds with DIR/<split> ...)")
    else:
        options = {}
        dataset = adapter_name(dataset)
        if dataset == "worlds":  # DIR/<split>
            options = {"split": path.name, "eval_frames": False}
            path = path.parent
        ds = open_dataset(dataset, path, **options)
    s = ds[sample]
    if s.frames is None or len(s.frames) == 0:
        raise InputError(f"{path}: sample {sample} ({s.name}) of the {ds.name} dataset has no camera images "
                         f"(Argoverse 2 here is LiDAR only); the converter needs posed camera frames")
    frames = frames_with_context(ds, sample, int(context)) if context else s.frames
    frames.metadata.setdefault("sample", s.name)
    frames.metadata.setdefault("dataset", ds.name)
    return frames


def context_record(frames: Frames) -> list[dict]:
    """What the converter was given over time, for a scene's metadata: one entry per instant
    (offset, timestamp, cameras), the reference's offset 0 among them."""
    return [{"offset": int(f.offset), "timestamp": float(f.timestamp), "cameras": list(f.names)}
            for f in frames.instants()]


def network_inputs(frames: Frames, stage: StageProfile, *, with_sky: bool = False) -> dict:
    """What a stage's network reads, from `frames` (module docstring), by name: ``images`` (N, 3, H, W)
    float32 in [0, 1], zero-padded to the largest; ``intrinsics`` (N, 3, 3) of the resized
    images; ``distortion`` (N, 5) OpenCV; ``image_size`` (N, 2) (rows, columns); ``valid`` (N, H, W)
    bool; ``cam_to_chunk`` (N, 4, 4) float32; ``chunk_to_world`` (4, 4) float64;
    ``camera_names``; and with_sky ``sky`` (N, H, W) bool from the frames' sky masks where every
    camera has one (otherwise the caller derives it)."""
    if not isinstance(frames, Frames):
        raise InputError(f"frames: expected a scube_sim.camera.Frames, got {type(frames).__name__}")
    if len(frames) == 0:
        raise InputError("frames: no images (the converter needs at least one posed camera image)")
    names = frames.names
    if len(set(names)) != len(names):
        raise InputError(f"frames: camera names must be unique, got {names}")
    to_chunk = invert_pose(chunk_to_world(frames))
    cams = []
    for im in frames.images:
        intr = im.intrinsics
        if im.image.ndim != 3 or im.image.shape[2] != 3 or im.image.dtype != np.uint8:
            raise InputError(f"camera {im.name!r}: image: expected (H, W, 3) uint8 RGB, got "
                             f"{im.image.shape} {im.image.dtype}")
        scale = stage.focal_px / float(intr.K[0, 0])
        scale = min(scale, stage.max_side / max(intr.width, intr.height))
        size = (intr.height, intr.width)
        new = (max(8, round(intr.height * scale)), max(8, round(intr.width * scale)))
        rgb = torch.from_numpy(np.array(im.image, np.uint8)).permute(2, 0, 1).to(torch.float32) / 255.0
        cam = {"images": resize_bilinear(rgb, new).clamp(0.0, 1.0),
               "intrinsics": torch.from_numpy(scale_intrinsics(intr.K, size, new).astype(np.float32)),
               "distortion": torch.from_numpy(camera_distortion(im).astype(np.float32)),
               "image_size": torch.tensor(new, dtype=torch.int64),
               # composed in float64: the world's coordinates may be large, the chunk's are small
               "cam_to_chunk": torch.from_numpy((to_chunk @ im.cam_to_world).astype(np.float32))}
        if with_sky and im.sky is not None:
            cam["sky"] = torch.from_numpy(resize_nearest(np.asarray(im.sky, bool), new))
        cams.append(cam)
    h = max(int(c["image_size"][0]) for c in cams)
    w = max(int(c["image_size"][1]) for c in cams)
    n = len(cams)
    item = {"images": torch.zeros(n, 3, h, w), "valid": torch.zeros(n, h, w, dtype=torch.bool),
            "camera_names": names, "chunk_to_world": torch.from_numpy(chunk_to_world(frames)),
            "sample": str(frames.metadata.get("sample", frames.metadata.get("name", "frames")))}
    for key in ("intrinsics", "distortion", "image_size", "cam_to_chunk"):
        item[key] = torch.stack([c[key] for c in cams])
    for i, c in enumerate(cams):
        ch, cw = (int(v) for v in c["image_size"])
        item["images"][i, :, :ch, :cw] = c["images"]
        item["valid"][i, :ch, :cw] = True
    if with_sky and all("sky" in c for c in cams):
        item["sky"] = torch.zeros(n, h, w, dtype=torch.bool)
        for i, c in enumerate(cams):
            ch, cw = (int(v) for v in c["image_size"])
            item["sky"][i, :ch, :cw] = c["sky"]
    return item
