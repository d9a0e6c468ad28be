"""`Frames`: the camera input of the converter, shared by the worlds and the dataset adapters.

A set of posed images: real rigs fire their cameras tens of milliseconds apart, so each image has
its own camera-to-world pose and timestamp; the set has one reference ego pose and time. A
reference set may carry `context`: the frame sets of other instants of the same log (each with its
own ego pose, time and `offset` in the source's instants), which define nothing of the chunk.
Frames: cameras are OpenCV (x right, y down, z forward); poses are (4, 4) float64 camera-to-world
(``T_world_cam``); times are seconds (float64). The chunk frame of a set (`chunk_to_world`: its
ego frame moved down to the road) and the ego's poses in it at each instant (`ego_poses_in_chunk`)
are defined here, once, for every route of the converter and its training data.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..boxes import Box
from ..errors import InputError, NotFoundError
from ..transforms import check_pose, invert_pose
from .model import Intrinsics


@dataclass
class CameraImage:
    """One image. image (H, W, 3) uint8 RGB; optional ground truth from renderers: depth (H, W)
    float32 metres along the optical axis (inf where nothing was hit), semantic (H, W) int16 label
    ids, sky (H, W) bool, instance (H, W) int32 instance ids of the surface seen (renderer-defined;
    the worlds: 0 for ground and sky, a boxed object's id equals its `Box.instance`)."""

    name: str
    image: np.ndarray
    intrinsics: Intrinsics
    cam_to_world: np.ndarray
    timestamp: float
    depth: np.ndarray | None = None
    semantic: np.ndarray | None = None
    sky: np.ndarray | None = None
    instance: np.ndarray | None = None

    def __post_init__(self):
        self.cam_to_world = check_pose(self.cam_to_world, f"camera {self.name!r}: cam_to_world")
        h, w = self.image.shape[:2]
        if (w, h) != (self.intrinsics.width, self.intrinsics.height):
            raise InputError(f"camera {self.name!r}: image is {w}x{h} but intrinsics say "
                             f"{self.intrinsics.width}x{self.intrinsics.height}")
        if not np.isfinite(self.timestamp):
            raise InputError(f"camera {self.name!r}: timestamp is not finite")


@dataclass
class Frames:
    """Posed camera images around one reference instant.

    images: list of CameraImage; ego_pose (4, 4) float64 ego-to-world at `timestamp`;
    metadata: free-form provenance (dataset, sample id, ...); ``ego_height_m``, where an adapter
    knows it, is the ego frame's origin height above the road in metres (0 where the ego frame
    sits on the road, as in nuScenes and the worlds; KITTI's is its Velodyne, 1.73 m up).
    log: the log (drive, scene) the instant belongs to ('' where the source is one log); offset:
    this instant's place among the source's instants, relative to the reference (0: the
    reference; -1: the instant before); boxes: labelled objects at this instant, world frame,
    where the source has them (moving actors break the static-scene assumption); context: other
    instants of the same log, ordered by offset, none at 0 and none with a context of its own."""

    images: list[CameraImage]
    ego_pose: np.ndarray
    timestamp: float
    metadata: dict = field(default_factory=dict)
    log: str = ""
    offset: int = 0
    boxes: list[Box] = field(default_factory=list)
    context: list["Frames"] = field(default_factory=list)

    def __post_init__(self):
        self.ego_pose = check_pose(self.ego_pose, "Frames.ego_pose")
        if not np.isfinite(self.timestamp):
            raise InputError("Frames.timestamp is not finite")
        offsets = []
        for c in self.context:
            where = f"context frames at offset {c.offset}"
            if c.context:
                raise InputError(f"{where}: a context instant cannot carry a context of its own")
            if c.log != self.log:
                raise InputError(f"{where}: from log {c.log!r}, not the reference's {self.log!r}: context "
                                 f"never crosses a log or scene boundary")
            if c.offset == 0 or c.offset in offsets:
                raise InputError(f"{where}: offsets must be non-zero and distinct (have {offsets})")
            offsets.append(c.offset)
        if offsets != sorted(offsets):
            self.context = sorted(self.context, key=lambda c: c.offset)

    def __len__(self) -> int:
        return len(self.images)

    @property
    def names(self) -> list[str]:
        return [im.name for im in self.images]

    def instants(self) -> list["Frames"]:
        """The reference (without its context) and every context instant, ordered by offset."""
        ref = Frames(self.images, self.ego_pose, self.timestamp, self.metadata, self.log, self.offset, self.boxes)
        return sorted([ref, *self.context], key=lambda f: f.offset)

    def around(self, offset: int) -> Frames:
        """The same instants with the one at `offset` (relative to this reference) as the
        reference: offsets counted from it, the others its context. NotFoundError names the
        offsets there are."""
        if offset == 0:
            return self
        instants = self.instants()
        have = [f.offset - self.offset for f in instants]
        if offset not in have:
            raise NotFoundError(f"no instant at offset {offset}; have {have}")
        base = self.offset + offset
        moved = [Frames(f.images, f.ego_pose, f.timestamp, f.metadata, f.log, f.offset - base, f.boxes)
                 for f in instants]
        ref = next(f for f in moved if f.offset == 0)
        return Frames(ref.images, ref.ego_pose, ref.timestamp, ref.metadata, ref.log, 0, ref.boxes,
                      [f for f in moved if f.offset != 0])

    def __getitem__(self, name: str) -> CameraImage:
        for im in self.images:
            if im.name == name:
                return im
        raise NotFoundError(f"no camera {name!r}; have {', '.join(self.names)}")


def chunk_to_world(frames: Frames) -> np.ndarray:
    """(4, 4) float64 the chunk frame of `frames`: their ego frame moved down to the road by the
    metadata's ``ego_height_m`` (0 where absent), so the box's z range sits where it was trained."""
    h = frames.metadata.get("ego_height_m", 0.0)
    try:
        h = float(h)
    except (TypeError, ValueError):
        h = float("nan")
    if not np.isfinite(h):
        raise InputError(f"frames.metadata ego_height_m: expected a finite number of metres, got {frames.metadata.get('ego_height_m')!r}")
    down = np.eye(4)
    down[2, 3] = -h
    return np.asarray(frames.ego_pose, np.float64) @ down


def ego_poses_in_chunk(frames: Frames) -> np.ndarray:
    """(K, 4, 4) float64 the ego's pose on the road in the chunk frame at each instant of `frames`:
    the reference first (identity), then its context in offset order (each instant's ego frame
    moved down by the reference's ``ego_height_m``: one car, one height)."""
    c2w = chunk_to_world(frames)
    down = invert_pose(np.asarray(frames.ego_pose, np.float64)) @ c2w
    to_chunk = invert_pose(c2w)
    return np.stack([to_chunk @ np.asarray(f.ego_pose, np.float64) @ down for f in [frames, *frames.context]])
