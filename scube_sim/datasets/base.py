"""What every dataset adapter yields: `Sample`s of posed camera `Frames`, real LiDAR sweeps and 3D boxes.

Frames follow `scube_sim.camera.frames` (OpenCV cameras, camera-to-world poses, seconds). World frame:
the dataset's own global/map frame where it has one; otherwise the first sweep's sensor frame.
Poses are (4, 4) float64 `T_parent_child` (see `scube_sim.transforms`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterator, Protocol

import numpy as np

from ..boxes import Box
from ..camera.frames import Frames
from ..errors import InputError, NotFoundError, OutOfRangeError
from ..lidar.config import LidarConfig
from ..transforms import PoseFn, check_pose, invert_pose, transform_points


class DatasetError(InputError):
    """Bad or missing dataset content; the message names the file (and key) and what was expected."""


@dataclass
class LidarSpec:
    """A LiDAR of the rig: its model (a preset or a config built from the dataset's calibration)
    and its (4, 4) sensor-to-ego mount."""

    name: str
    config: LidarConfig
    sensor_to_ego: np.ndarray

    def __post_init__(self):
        self.sensor_to_ego = check_pose(self.sensor_to_ego, f"lidar {self.name!r}: sensor_to_ego")


@dataclass
class LidarSweep:
    """One real sweep of one sensor.

    points (N, 3) float64 metres, sensor frame. If `motion_compensated`, every point is expressed
    in the sensor frame at `timestamp`; otherwise each point is in the sensor frame at its own fire
    time `timestamp + time_offset` (raw, as the sensor measured it) and `pose_fn` must be given.
    sensor_to_world (4, 4): the sensor pose at `timestamp` (s). intensity (N,) float32 as stored
    by the dataset (its scale differs: see `intensity_max`); ring (N,) int16 laser index;
    time_offset (N,) float64 seconds relative to `timestamp`; pose_fn: absolute times ->
    sensor-to-world poses, where the dataset has a pose stream (for per-point timing).

    Clouds merged from several LiDARs (one cloud, no single origin): origin_id (N,) int16 says
    which measuring sensor each point came from, an index into origins (K, 4, 4) float64, each
    measuring sensor's pose in this sweep's frame (``T_sweep_origin``; rigid on the vehicle, so
    it holds at every fire time); origin_names (K,) optionally names them (keys of
    `Sample.lidars`, for their sensor models). None (the default): every ray starts at this
    frame's origin. `merge_sweeps` builds such a sweep; `by_origin` splits it back.
    source: the file the sweep was read from (for messages), '' if none.
    """

    sensor: str
    points: np.ndarray
    sensor_to_world: np.ndarray
    timestamp: float
    intensity: np.ndarray | None = None
    intensity_max: float = 1.0
    ring: np.ndarray | None = None
    time_offset: np.ndarray | None = None
    motion_compensated: bool = True
    pose_fn: PoseFn | None = None
    origin_id: np.ndarray | None = None
    origins: np.ndarray | None = None
    origin_names: tuple[str, ...] | None = None
    source: str = ""

    def __post_init__(self):
        self.points = np.asarray(self.points, np.float64).reshape(-1, 3)
        self.sensor_to_world = check_pose(self.sensor_to_world, f"sweep {self.sensor!r}: sensor_to_world")
        n = self.points.shape[0]
        for name in ("intensity", "ring", "time_offset", "origin_id"):
            v = getattr(self, name)
            if v is not None and np.shape(v) != (n,):
                raise InputError(f"sweep {self.sensor!r}: {name} has shape {np.shape(v)}, expected ({n},)")
        if not self.motion_compensated and (self.time_offset is None or self.pose_fn is None):
            raise InputError(f"sweep {self.sensor!r}: raw (not motion-compensated) points need time_offset and pose_fn")
        if (self.origin_id is None) != (self.origins is None):
            raise InputError(f"sweep {self.sensor!r}: give origin_id and origins together (or neither)")
        if self.origins is not None:
            o = np.asarray(self.origins, np.float64)
            if o.ndim != 3 or o.shape[1:] != (4, 4) or o.shape[0] == 0:
                raise InputError(f"sweep {self.sensor!r}: origins has shape {o.shape}, expected (K, 4, 4)")
            self.origins = np.stack([check_pose(t, f"sweep {self.sensor!r}: origins[{k}]") for k, t in enumerate(o)])
            ids = np.asarray(self.origin_id)
            if not np.issubdtype(ids.dtype, np.integer):
                raise InputError(f"sweep {self.sensor!r}: origin_id must be integers, got {ids.dtype}")
            if n and (ids.min() < 0 or ids.max() >= len(o)):
                raise InputError(f"sweep {self.sensor!r}: origin_id holds {int(ids.min())}..{int(ids.max())}, "
                                 f"expected 0..{len(o) - 1} (one per row of origins)")
            self.origin_id = ids.astype(np.int16)
            if self.origin_names is not None:
                self.origin_names = tuple(str(x) for x in self.origin_names)
                if len(self.origin_names) != len(o):
                    raise InputError(f"sweep {self.sensor!r}: {len(self.origin_names)} origin_names for "
                                     f"{len(o)} origins")
        elif self.origin_names is not None:
            raise InputError(f"sweep {self.sensor!r}: origin_names given without origins")

    def __len__(self) -> int:
        return self.points.shape[0]

    def point_poses(self) -> np.ndarray:
        """(N, 4, 4) sensor-to-world pose of each point's frame (the sweep pose when compensated)."""
        if self.motion_compensated:
            return np.broadcast_to(self.sensor_to_world, (len(self), 4, 4))
        return np.asarray(self.pose_fn(self.timestamp + self.time_offset), np.float64)

    def world_points(self) -> np.ndarray:
        """(N, 3) float64 metres, world frame (per-point poses for raw sweeps)."""
        if self.motion_compensated:
            return transform_points(self.sensor_to_world, self.points)
        return transform_points(self.point_poses(), self.points)

    @property
    def merged(self) -> bool:
        """True if the points carry their own origins (`origin_id`, `origins`)."""
        return self.origins is not None

    def point_origins(self) -> np.ndarray:
        """(N, 3) float64 metres: each ray's start in this sweep's frame (at the point's own fire
        time for raw sweeps, like the point): the frame origin unless the sweep is merged."""
        if self.origins is None:
            return np.zeros((len(self), 3))
        return self.origins[self.origin_id.astype(np.int64), :3, 3]

    def compensated(self) -> "LidarSweep":
        """The same sweep with every point moved into the sensor frame at `timestamp`."""
        if self.motion_compensated:
            return self
        local = transform_points(invert_pose(self.sensor_to_world), self.world_points())
        return replace(self, points=local, motion_compensated=True)

    def raw(self) -> "LidarSweep":
        """The same sweep as the sensor measured it: each point in the sensor frame at its own
        fire time (undoes motion compensation with `time_offset` and `pose_fn`)."""
        if not self.motion_compensated:
            return self
        if self.time_offset is None or self.pose_fn is None:
            raise InputError(f"sweep {self.sensor!r}: undoing motion compensation needs time_offset and pose_fn")
        poses = np.asarray(self.pose_fn(self.timestamp + self.time_offset), np.float64)
        local = transform_points(invert_pose(poses), self.world_points())
        return replace(self, points=local, motion_compensated=False)

    def subset(self, mask) -> "LidarSweep":
        pick = lambda a: None if a is None else a[mask]  # noqa: E731
        return replace(self, points=self.points[mask], intensity=pick(self.intensity), ring=pick(self.ring),
                       time_offset=pick(self.time_offset), origin_id=pick(self.origin_id))

    def origin_name(self, k: int) -> str:
        """The name of measuring sensor k: its `origin_names` entry, else '<sensor>#<k>'."""
        return self.origin_names[k] if self.origin_names is not None else f"{self.sensor}#{k}"

    def by_origin(self) -> list["LidarSweep"]:
        """Single-origin sweeps, one per measuring sensor that has points: each in that sensor's
        own frame (points, pose and pose function moved by `origins[k]`), named by
        `origin_name(k)`. A sweep that is not merged gives [self]."""
        if self.origins is None:
            return [self]
        out = []
        for k, t_so in enumerate(self.origins):
            sel = self.origin_id == k
            if not sel.any():
                continue
            part = self.subset(sel)
            fn = None if self.pose_fn is None else (lambda t, f=self.pose_fn, m=t_so: np.asarray(f(t)) @ m)
            out.append(replace(part, sensor=self.origin_name(k), points=transform_points(invert_pose(t_so), part.points),
                               sensor_to_world=self.sensor_to_world @ t_so, pose_fn=fn, origin_id=None, origins=None,
                               origin_names=None))
        return out


def merge_sweeps(sweeps: list[LidarSweep], sensor_to_world: np.ndarray, *, name: str = "merged") -> LidarSweep:
    """One merged cloud of several single-origin, motion-compensated sweeps taken at the same
    `timestamp` (the first one's), expressed in the frame `sensor_to_world` (4, 4): what a log
    that merges its LiDARs stores, with each point's origin kept (`origin_id`, `origins`,
    `origin_names` = the sweeps' sensor names). Intensity, ring and time_offset are kept where
    every sweep has them (intensity on the first sweep's `intensity_max` scale)."""
    if not sweeps:
        raise InputError("merge_sweeps: no sweeps")
    frame = check_pose(sensor_to_world, "merge_sweeps: sensor_to_world")
    to_frame = invert_pose(frame)
    for sw in sweeps:
        if not sw.motion_compensated or sw.merged:
            raise InputError(f"merge_sweeps: sweep {sw.sensor!r} is raw or already merged")
    origins = np.stack([to_frame @ sw.sensor_to_world for sw in sweeps])
    pts = np.concatenate([transform_points(o, sw.points) for o, sw in zip(origins, sweeps)])
    ids = np.concatenate([np.full(len(sw), k, np.int16) for k, sw in enumerate(sweeps)])
    imax = sweeps[0].intensity_max

    def cat(name, scale=False):
        vals = [getattr(sw, name) for sw in sweeps]
        if any(v is None for v in vals):
            return None
        if scale:
            vals = [np.asarray(v, np.float32) * np.float32(imax / sw.intensity_max) for v, sw in zip(vals, sweeps)]
        return np.concatenate(vals)

    return LidarSweep(name, pts, frame, sweeps[0].timestamp, cat("intensity", True), imax, cat("ring"),
                      cat("time_offset"), True, None, ids, origins, tuple(sw.sensor for sw in sweeps))


@dataclass
class Sample:
    """One instant of a log. frames: the camera images (None where the set has no images);
    sweeps: real LiDAR sweeps (empty where the set has none); lidars: the rig's LiDAR models by
    sensor name; boxes: labelled objects; ego_pose (4, 4) ego-to-world at `timestamp`; log: the
    log (drive, scene) it belongs to ('' where the whole set is one log): context instants never
    cross it (`frames_with_context`)."""

    name: str
    timestamp: float
    ego_pose: np.ndarray
    frames: Frames | None = None
    sweeps: list[LidarSweep] = field(default_factory=list)
    lidars: dict[str, LidarSpec] = field(default_factory=dict)
    boxes: list[Box] = field(default_factory=list)
    metadata: dict = field(default_factory=dict)
    log: str = ""

    def __post_init__(self):
        self.ego_pose = check_pose(self.ego_pose, f"sample {self.name!r}: ego_pose")
        if self.frames is not None:  # the frames know their instant's log and objects
            self.frames.log = self.log
            if not self.frames.boxes:
                self.frames.boxes = list(self.boxes)

    def sweep(self, sensor: str | None = None) -> LidarSweep:
        """The sweep of `sensor` (default: the only or first sweep)."""
        if not self.sweeps:
            raise DatasetError(f"sample {self.name!r} has no LiDAR sweep")
        if sensor is None:
            return self.sweeps[0]
        for s in self.sweeps:
            if s.sensor == sensor:
                return s
        raise NotFoundError(f"sample {self.name!r}: no sweep of sensor {sensor!r}; have {[s.sensor for s in self.sweeps]}")


class Dataset(Protocol):
    """An adapter: `len(ds)` samples, `ds[i]` -> Sample (loaded on access), in time order within
    each log. An adapter whose samples hold several instants of their own (the worlds) may define
    `context_frames(index, k) -> list[Frames]`; `frames_with_context` then asks it instead of
    taking neighbouring samples."""

    name: str
    root: Path
    poses_from_icp: bool  # True when the set has no poses and they were registered by ICP

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> Sample: ...

    def __iter__(self) -> Iterator[Sample]: ...


def require_file(path: Path, what: str) -> Path:
    """`path` if it is a file, else a DatasetError saying which file of the set is missing."""
    if not path.is_file():
        raise DatasetError(f"{path}: missing {what}")
    return path


def require_key(mapping, key, source: str, what: str = "key"):
    """mapping[key] or a DatasetError naming the file and the key."""
    try:
        return mapping[key]
    except (KeyError, IndexError, TypeError):
        raise DatasetError(f"{source}: missing {what} {key!r}") from None


def as_matrix(value, shape: tuple[int, ...], source: str, key: str) -> np.ndarray:
    """value as a finite float64 array of `shape`, or a DatasetError naming the file and key."""
    try:
        a = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{source}: {key} is not numeric") from None
    if a.shape != shape:
        raise DatasetError(f"{source}: {key} has shape {a.shape}, expected {shape}")
    if not np.all(np.isfinite(a)):
        raise DatasetError(f"{source}: {key} holds NaN or Inf")
    return a


def index_check(index: int, n: int, name: str) -> int:
    if not -n <= index < n:
        raise OutOfRangeError(f"{name}: sample {index} out of range (have {n})")
    return index % n


def frames_with_context(ds: Dataset, index: int, k: int) -> Frames:
    """The camera frames of sample `index` with `context`: the frames of up to `k` instants before
    and `k` after it in the same log (`Sample.log`; never across a scene boundary), each with its
    `offset` in the source's instants, its own ego pose, time and boxes. k = 0: the sample's
    frames as they are. An adapter with `context_frames(index, k)` gives its own."""
    if k < 0:
        raise InputError(f"context: expected a number of instants >= 0, got {k}")
    sample = ds[index]
    if sample.frames is None:
        raise DatasetError(f"{ds.root}: sample {index} ({sample.name}) has no camera images")
    if k == 0:
        return sample.frames
    if hasattr(ds, "context_frames"):
        context = list(ds.context_frames(index, k))
    else:
        context = []
        for step in (-1, 1):  # walk out from the reference, loading only the neighbours needed
            j = index + step
            while 0 <= j < len(ds) and abs(j - index) <= k:
                s = ds[j]
                if s.log != sample.log:
                    break
                if s.frames is not None and len(s.frames):
                    context.append(replace(s.frames, offset=j - index))
                j += step
    # replace() checks the context again: same log, distinct offsets, ordered
    return replace(sample.frames, context=context)
