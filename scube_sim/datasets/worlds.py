"""The procedural worlds' dataset (`scube_sim.worlds.dataset`, format ``scube_sim.worlds``) as an adapter.

    ds = open_dataset("worlds", "DIR")                 # DIR: what `scube-sim worlds generate -o DIR` wrote
    ds = WorldsDataset("DIR", split="test", eval_frames=False)
    s = ds[0]          # WorldsSample: Frames at T, the LiDAR sweep, boxes, plus the worlds' ground truth

DIR holds dataset.json and one folder per split; a split's samples are its complete sample folders
``DIR/<split>/<index:06d>/`` (hidden ``.tmp-*`` folders are unfinished writes and are skipped),
in index order. ``ds[i]`` is the i-th of them (indices may have gaps when a run used --start).

What a sample holds (see `WorldsSample`):

- ``frames``: the posed images at the reference instant T (frame offset 0), each `CameraImage`
  with its own timestamp and pose (the rig's firing offsets) and the renderer's ground truth:
  depth (H, W) float32 metres along the optical axis (inf: sky), semantic (H, W) int16 label ids,
  sky (H, W) bool, instance (H, W) int32 ids (0: ground and sky; each other object has its own
  id, and a boxed object's is its box's ``instance``); ``boxes``: every box at T (`Box`, world frame);
- ``timeline``: every stored instant in time order (T, then T+5 and T+10 frames at 10 Hz by
  default; instants before T first, since version 3) with its Frames and boxes; only T unless
  ``eval_frames`` (the default); ``reference`` is T's entry;
- ``log``: the sample's name (``<split>/<index:06d>``): a worlds sample is a log of its own, and
  the converter's context instants come from its own stored instants (`WorldsDataset.context_frames`,
  asked by `scube_sim.datasets.base.frames_with_context`), never from other samples;
- ``sweeps``: the one ground-truth LiDAR sweep over the first sweep period after T, as the sensor
  measured it (raw: each point in the sensor frame at its own fire time, with a pose per point by
  interpolating the stored start and end poses); ``lidars``: that sensor's model and mount;
- ``ground_truth``: fine and coarse voxel grids of the chunk with labels and visibility, the
  chunk-to-world pose, the LiDAR points with their labels and instances, the world's config.

Frames: world = the generated world's frame (z up, metres); ego = x forward, y left, z up; chunk
= the ego frame at T (`worlds.groundtruth`: voxel (i, j, k) spans CHUNK_CORNER + [ijk, ijk + 1) *
voxel_size in it). Errors are DatasetError naming the file and what was expected.
"""

from __future__ import annotations

import json
import re
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera.frames import CameraImage, Frames
from ..camera.model import Intrinsics
from ..config import ConfigError, json_loads
from ..errors import InputError
from ..io.images import read_rgb
from ..labels import label_id
from ..lidar.config import load_lidar_config
from ..run_manifest import read_manifest
from ..transforms import interpolate_poses
from ..worlds.dataset import (
    DATASET_FORMAT,
    DATASET_VERSION,
    EVAL_OFFSETS,
    SPLIT_SEED_BASE,
    DatasetConfig,
    frame_tag,
    read_dataset_config,
)
from ..worlds.generator import WorldConfig
from ..worlds.groundtruth import CHUNK_CORNER
from .base import Box, DatasetError, LidarSpec, LidarSweep, Sample, as_matrix, index_check, require_file, require_key

DATASET_FILE = "dataset.json"
META_FILE = "meta.json"
SAMPLE_DIR = re.compile(r"\d{6}")
SKY = label_id("sky")


@dataclass
class VoxelLabels:
    """One ground-truth voxel grid of the chunk: the voxels the scene's surface at T passes through.

    ijk (V, 3) int32: voxel (i, j, k) spans CHUNK_CORNER + [ijk, ijk + 1) * voxel_size in the chunk
    frame; labels (V,) int16 label ids (`scube_sim.labels`, the label with the most surface area);
    visible (V,) bool: holds a surface point one of the input cameras at T sees; voxel_size metres."""

    ijk: np.ndarray
    labels: np.ndarray
    visible: np.ndarray
    voxel_size: float

    def __len__(self) -> int:
        return int(self.ijk.shape[0])

    def centers(self) -> np.ndarray:
        """(V, 3) float64 voxel centres, chunk frame, metres."""
        return CHUNK_CORNER + (self.ijk + 0.5) * self.voxel_size


@dataclass
class WorldsFrame:
    """One stored instant: offset (frames after T at the dataset's frame rate), time (s), the
    posed images with their depth, semantic and sky ground truth, and every box (world frame)."""

    offset: int
    time: float
    frames: Frames
    boxes: list[Box]


@dataclass
class WorldsGroundTruth:
    """What only a generated world can give, beyond the camera ground truth on each CameraImage.

    chunk_to_world (4, 4): the chunk frame (the ego frame at T) in the world; fine, coarse: the
    voxel grids; lidar_points (N,) `scube_sim.lidar.POINT_DTYPE`: the sweep as stored (sensor frame,
    with per-point label, instance, range, fire time); world: the WorldConfig that regenerates the
    scene (`generate_world(world)`); layout: its road layout kind; sun_dir (3,) unit vector towards
    the sun, world frame."""

    chunk_to_world: np.ndarray
    fine: VoxelLabels
    coarse: VoxelLabels
    lidar_points: np.ndarray
    world: WorldConfig
    layout: str
    sun_dir: np.ndarray


@dataclass
class WorldsSample(Sample):
    """A `Sample` of the worlds dataset: ``frames`` / ``boxes`` are the instant T; ``timeline``
    holds every loaded instant in time order (`reference` is T, the same Frames and boxes; it is
    ``timeline[0]`` unless the dataset stores instants before T, version 3)."""

    ground_truth: WorldsGroundTruth = field(kw_only=True)
    timeline: list[WorldsFrame] = field(kw_only=True)

    @property
    def reference(self) -> WorldsFrame:
        """The timeline's entry at offset 0: the input instant T."""
        return next(f for f in self.timeline if f.offset == 0)

    def later(self) -> list[WorldsFrame]:
        """The loaded instants after T (offset > 0), in time order: the evaluation instants and
        any later context instants."""
        return [f for f in self.timeline if f.offset > 0]


def _read_json(path: Path, what: str) -> dict:
    require_file(path, what)
    try:
        data = json_loads(path.read_text(), path, DatasetError)  # a key twice: refused
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


def _load_npz(path: Path, what: str, tags: set[str] | None = None) -> dict[str, np.ndarray]:
    """The arrays of an .npz; with `tags`, only the per-image maps ``<kind>_<tag>_<camera>`` of
    those frame tags (the others are not decompressed)."""
    require_file(path, what)
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files if tags is None or _map_tag(k) in tags}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        # truncated, corrupt or not a zip; pickled object arrays (never unpickled)
        raise DatasetError(f"{path}: not a readable .npz ({' '.join(str(exc).split()) or type(exc).__name__})") from None


def _map_tag(key: str) -> str | None:
    """The frame tag of a per-image map's key ``<kind>_<tag>_<camera>`` (None for another key)."""
    parts = key.split("_", 2)
    return parts[1] if len(parts) == 3 else None


def _array(arrays: dict, key: str, path: Path) -> np.ndarray:
    if key not in arrays:
        raise DatasetError(f"{path}: missing array {key!r}")
    return arrays[key]


def _being_written(folder: Path) -> bool:
    """A sample folder a batch is still writing (or was cut off writing): no meta.json yet (it is
    written last) and a run manifest that is not complete. It is not a sample yet; a folder that
    lost its meta.json otherwise is still listed, and reading it names what is missing."""
    if (folder / META_FILE).is_file():
        return False
    try:
        manifest = read_manifest(folder)
    except InputError:
        return False
    return manifest is not None and manifest.status != "complete"


def _context(frames_meta: list[dict], k: int) -> list[tuple[int, dict]]:
    """(index, frame) of the frames of a sample's meta that are context within k instants of T:
    offset in [-k, k], not 0 (T) and not an evaluation instant (EVAL_OFFSETS), in stored (time) order."""
    if k < 0:
        raise DatasetError(f"context: expected a number of instants >= 0, got {k}")
    return [(f, fm) for f, fm in enumerate(frames_meta)
            if -k <= int(fm["offset"]) <= k and int(fm["offset"]) != 0 and int(fm["offset"]) not in EVAL_OFFSETS]


class WorldsDataset:
    """The samples of one split of a worlds dataset folder (see the module docstring).

    root: the folder `worlds generate -o` wrote (it holds dataset.json); split: train, val or test;
    eval_frames: also load the other stored instants (T+5, T+10 ..., and those before T) into each
    sample's ``timeline``. `context_frames` gives a sample's context instants whatever eval_frames.
    Reads versions 2, 3 and 4 (`scube_sim.worlds.dataset.READABLE_VERSIONS`)."""

    name = "worlds"
    poses_from_icp = False

    def __init__(self, root: str | Path, *, split: str = "train", eval_frames: bool = True):
        self.root = Path(root)
        head = require_file(self.root / DATASET_FILE, "worlds dataset header (`scube-sim worlds generate -o DIR` "
                                                      "writes DIR/dataset.json)")
        try:
            self.config: DatasetConfig = read_dataset_config(self.root)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise DatasetError(f"{head}: not valid JSON ({exc})") from None
        except KeyError as exc:
            raise DatasetError(f"{head}: missing key {exc.args[0]!r}") from None
        except ValueError as exc:  # another format or version; a config pydantic refuses
            msg = str(exc)
            raise DatasetError(msg if msg.startswith(str(head)) else f"{head}: config: {msg}") from None
        if split not in SPLIT_SEED_BASE:
            raise DatasetError(f"split: expected one of {', '.join(SPLIT_SEED_BASE)}, got {split!r}")
        self.split = split
        self.eval_frames = eval_frames
        sdir = self.root / split
        if not sdir.is_dir():
            have = [s for s in SPLIT_SEED_BASE if (self.root / s).is_dir()]
            raise DatasetError(f"{sdir}: no {split!r} split in this dataset (splits here: {', '.join(have) or 'none'})")
        self.sample_dirs = sorted((d for d in sdir.iterdir()
                                   if d.is_dir() and SAMPLE_DIR.fullmatch(d.name) and not _being_written(d)),
                                  key=lambda d: int(d.name))
        try:
            lidar_cfg = load_lidar_config(self.config.lidar)
        except ConfigError as exc:
            raise DatasetError(f"{head}: config.lidar: {exc}") from None
        self.lidars = {self.config.lidar: LidarSpec(self.config.lidar, lidar_cfg, lidar_cfg.mount.matrix())}

    def __len__(self) -> int:
        return len(self.sample_dirs)

    def __iter__(self) -> Iterator[WorldsSample]:
        for i in range(len(self)):
            yield self[i]

    def _meta(self, index: int) -> tuple[Path, Path, dict, list]:
        """The sample folder of `index`, its meta.json path, the parsed meta and its frames list."""
        d = self.sample_dirs[index_check(index, len(self), f"{self.name} {self.root / self.split}")]
        meta_path = d / META_FILE
        meta = _read_json(meta_path, f"sample metadata {META_FILE} (not a complete worlds sample)")
        if meta.get("format") != DATASET_FORMAT or not isinstance(meta.get("version"), int) \
                or meta["version"] > DATASET_VERSION:
            raise DatasetError(f"{meta_path}: format {meta.get('format')!r} version {meta.get('version')!r}: expected "
                               f"{DATASET_FORMAT!r} version {DATASET_VERSION} or older")
        frames_meta = require_key(meta, "frames", str(meta_path))
        if not isinstance(frames_meta, list) or not frames_meta:
            raise DatasetError(f"{meta_path}: frames: expected a non-empty list")
        offsets = []
        for f, fm in enumerate(frames_meta):
            if not isinstance(fm, dict):
                raise DatasetError(f"{meta_path}: frames[{f}]: expected an object")
            k = require_key(fm, "offset", f"{meta_path}: frames[{f}]")
            if not isinstance(k, int) or isinstance(k, bool):
                raise DatasetError(f"{meta_path}: frames[{f}].offset: expected an integer, got {k!r}")
            offsets.append(k)
        if 0 not in offsets or any(b <= a for a, b in zip(offsets, offsets[1:])):
            raise DatasetError(f"{meta_path}: frames: expected offsets in increasing order that include 0 (the "
                               f"input instant T), got {offsets}")
        return d, meta_path, meta, frames_meta

    def _name(self, d: Path) -> str:
        return f"{self.split}/{d.name}"

    def __getitem__(self, index: int) -> WorldsSample:
        d, meta_path, meta, frames_meta = self._meta(index)
        load = [(f, fm) for f, fm in enumerate(frames_meta) if self.eval_frames or int(fm["offset"]) == 0]
        maps_path = d / "frames.npz"
        maps = _load_npz(maps_path, "per-camera depth and semantic maps", {frame_tag(fm["offset"]) for _, fm in load})
        timeline = [self._frame(d, meta_path, f, fm, maps, maps_path) for f, fm in load]
        t0 = next(f for f in timeline if f.offset == 0)
        chunk_to_world = as_matrix(require_key(meta, "chunk_to_world", str(meta_path)), (4, 4), str(meta_path),
                                   "chunk_to_world")
        points, sweep = self._sweep(d, meta_path, meta)
        try:
            world = WorldConfig.model_validate(require_key(meta, "world", str(meta_path)))
        except ValueError as exc:
            raise DatasetError(f"{meta_path}: world: {exc}") from None
        fine, coarse = self._voxels(d / "voxels.npz")
        gt = WorldsGroundTruth(chunk_to_world, fine, coarse, points, world, str(meta.get("layout", "")),
                               as_matrix(require_key(meta, "sun_dir", str(meta_path)), (3,), str(meta_path), "sun_dir"))
        index = int(meta.get("index", int(d.name)))
        return WorldsSample(name=self._name(d), timestamp=t0.time, ego_pose=t0.frames.ego_pose, log=self._name(d),
                            frames=t0.frames, sweeps=[sweep], lidars=dict(self.lidars), boxes=t0.boxes,
                            metadata={"dataset": self.name, "split": self.split, "index": index,
                                      "sample_dir": str(d), "world": meta.get("world"),
                                      "layout": meta.get("layout"), "rig": meta.get("rig")},
                            ground_truth=gt, timeline=timeline)

    def context_offsets(self, index: int, k: int) -> list[int]:
        """The frame offsets `context_frames(index, k)` gives: the sample's stored offsets in
        [-k, k], less 0 (T itself) and the evaluation instants (EVAL_OFFSETS), in time order."""
        _, _, _, frames_meta = self._meta(index)
        return [int(fm["offset"]) for _, fm in _context(frames_meta, k)]

    def context_frames(self, index: int, k: int) -> list[Frames]:
        """The converter's context of sample `index`: its own stored instants within k frames (at
        the dataset's frame rate) of T, before and after, less T and the evaluation instants
        (EVAL_OFFSETS: never converter inputs), in time order. Each a `Frames` with its `offset`,
        its own ego pose and time (seconds after T), its cameras' poses and timestamps, the boxes
        at that instant and the sample's name as its `log`. A worlds sample never takes context
        from other samples (each is a world of its own)."""
        d, meta_path, _, frames_meta = self._meta(index)
        want = _context(frames_meta, k)
        if not want:
            return []
        maps_path = d / "frames.npz"
        maps = _load_npz(maps_path, "per-camera depth and semantic maps", {frame_tag(fm["offset"]) for _, fm in want})
        return [self._frame(d, meta_path, f, fm, maps, maps_path).frames for f, fm in want]

    def _frame(self, d: Path, meta_path: Path, f: int, fm, maps: dict, maps_path: Path) -> WorldsFrame:
        where = f"{meta_path}: frames[{f}]"
        if not isinstance(fm, dict):
            raise DatasetError(f"{where}: expected an object")
        k = int(require_key(fm, "offset", where))
        tag = frame_tag(k)
        t_ref = float(require_key(fm, "time", where))
        images = []
        for c, cam in enumerate(require_key(fm, "cameras", where)):
            cwhere = f"{where}.cameras[{c}]"
            name = require_key(cam, "name", cwhere)
            intr_d = require_key(cam, "intrinsics", cwhere)
            try:
                intr = Intrinsics(intr_d["width"], intr_d["height"], intr_d["fx"], intr_d["fy"], intr_d["cx"],
                                  intr_d["cy"], intr_d["model"], tuple(intr_d["dist"]))
            except (KeyError, TypeError, ValueError) as exc:
                raise DatasetError(f"{cwhere}.intrinsics: {exc}") from None
            rgb_path = d / f"rgb_{tag}_{name}.png"
            require_file(rgb_path, f"image of camera {name!r} at frame offset {k}")
            rgb = read_rgb(rgb_path, error=DatasetError)
            depth = _array(maps, f"depth_{tag}_{name}", maps_path).astype(np.float32)
            sem = _array(maps, f"semantic_{tag}_{name}", maps_path).astype(np.int16)
            inst = _array(maps, f"instance_{tag}_{name}", maps_path).astype(np.int32)
            for what, a in (("depth", depth), ("semantic", sem), ("instance", inst)):
                if a.shape != (intr.height, intr.width):
                    raise DatasetError(f"{maps_path}: {what}_{tag}_{name} has shape {a.shape}, expected "
                                       f"{(intr.height, intr.width)} (the camera's intrinsics in {meta_path})")
            pose = as_matrix(require_key(cam, "cam_to_world", cwhere), (4, 4), cwhere, "cam_to_world")
            try:
                images.append(CameraImage(name, rgb, intr, pose, float(require_key(cam, "timestamp", cwhere)),
                                          depth=depth, semantic=sem, sky=sem == SKY, instance=inst))
            except ValueError as exc:
                raise DatasetError(f"{rgb_path}: {exc}") from None
        ego = as_matrix(require_key(fm, "ego_pose", where), (4, 4), where, "ego_pose")
        try:
            boxes = [Box.from_json(b) for b in require_key(fm, "boxes", where)]
        except (KeyError, TypeError, ValueError) as exc:
            raise DatasetError(f"{where}.boxes: not a box ({type(exc).__name__}: {exc})") from None
        meta_f = {"dataset": self.name, "split": self.split, "sample_dir": str(d), "frame_offset": k}
        return WorldsFrame(k, t_ref, Frames(images, ego, t_ref, meta_f, log=self._name(d), offset=k, boxes=list(boxes)),
                           boxes)

    def _sweep(self, d: Path, meta_path: Path, meta: dict) -> tuple[np.ndarray, LidarSweep]:
        lm = require_key(meta, "lidar", str(meta_path))
        where = f"{meta_path}: lidar"
        sensor = str(require_key(lm, "sensor", where))
        if sensor not in self.lidars:
            raise DatasetError(f"{where}.sensor: {sensor!r}, but {self.root / DATASET_FILE} names "
                               f"{self.config.lidar!r}")
        spec = self.lidars[sensor]
        pose_start = as_matrix(require_key(lm, "pose_start", where), (4, 4), where, "pose_start")
        pose_end = as_matrix(require_key(lm, "pose_end", where), (4, 4), where, "pose_end")
        t_start, t_end = float(require_key(lm, "t_start", where)), float(require_key(lm, "t_end", where))
        path = d / "lidar.npz"
        pts = _array(_load_npz(path, "LiDAR sweep"), "points", path)
        fields = pts.dtype.names or ()
        for f in ("x", "y", "z", "intensity", "ring", "time"):
            if f not in fields:
                raise DatasetError(f"{path}: points has no field {f!r} (fields: {', '.join(fields) or 'none'})")
        xyz = np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float64)
        period = t_end - t_start

        def pose_fn(t):
            """Sensor-to-world at absolute times t: the interpolation the simulator moved the sensor by."""
            return interpolate_poses(pose_start, pose_end, (np.asarray(t, np.float64) - t_start) / period)

        # The simulator writes raw points unless the sensor's config asks for compensated ones
        # (then in the frame of the start or end pose); a static sensor's points are the same.
        motion = spec.config.motion
        compensated = motion.output == "compensated"
        at_end = compensated and motion.reference == "end"
        t_ref = t_end if at_end else t_start
        sweep = LidarSweep(sensor, xyz, pose_end if at_end else pose_start, t_ref,
                           intensity=pts["intensity"].astype(np.float32),
                           intensity_max=float(spec.config.intensity.output_scale),
                           ring=pts["ring"].astype(np.int16),
                           time_offset=t_start + pts["time"].astype(np.float64) - t_ref,
                           motion_compensated=compensated, pose_fn=pose_fn)
        return pts, sweep

    @staticmethod
    def _voxels(path: Path) -> tuple[VoxelLabels, VoxelLabels]:
        z = _load_npz(path, "ground-truth voxels")
        grids = []
        for level in ("fine", "coarse"):
            ijk = _array(z, f"{level}_ijk", path)
            labels = _array(z, f"{level}_labels", path)
            visible = _array(z, f"{level}_visible", path)
            size = _array(z, f"{level}_voxel_size", path)
            n = ijk.shape[0] if ijk.ndim == 2 else -1
            if ijk.shape != (n, 3) or labels.shape != (n,) or visible.shape != (n,) or size.shape != ():
                raise DatasetError(f"{path}: {level}_* arrays have shapes ijk {ijk.shape}, labels {labels.shape}, "
                                   f"visible {visible.shape}, voxel_size {size.shape}; expected (V, 3), (V,), (V,), ()")
            grids.append(VoxelLabels(ijk.astype(np.int32), labels.astype(np.int16), visible.astype(bool),
                                     float(size)))
        return grids[0], grids[1]


__all__ = ["VoxelLabels", "WorldsDataset", "WorldsFrame", "WorldsGroundTruth", "WorldsSample"]
