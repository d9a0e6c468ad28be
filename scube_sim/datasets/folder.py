"""Our generic dataset folder (``scube-sim-folder`` version 2): what other datasets convert to.

    write_folder_dataset(open_dataset("argoverse2", "log"), "out")   # any samples -> folder
    ds = FolderDataset("out")                                        # or open_dataset("folder", "out")

Layout (full description with an example: docs/dataset-folder-format.md):

    ROOT/dataset.yaml                    format, version, lidars (model + mount), cameras (intrinsics)
    ROOT/lidars/<LIDAR>.yaml             LiDAR configs named by dataset.yaml (optional: or a preset)
    ROOT/samples/<NNNNNN>/sample.yaml    name, timestamp, ego_pose, images, sweeps, boxes, metadata
    ROOT/samples/<NNNNNN>/<CAM>.png|jpg  RGB image
    ROOT/samples/<NNNNNN>/<LIDAR>.npz|pcd|ply|bin   points: x y z [intensity ring time_offset sensor_id]
                                         (x y z float64 in .npz: exact; float32 in the others)

Frames are those of `scube_sim.datasets.base`: poses are (4, 4) ``T_parent_child`` written as
4 rows of 4 numbers, metres, seconds; points are in their sensor frame; cameras are OpenCV
(x right, y down, z forward). Every YAML file is validated by strict pydantic models (unknown keys
are errors); errors are DatasetError naming the file and the key path.

Version 2 adds clouds merged from several LiDARs: a sweep's ``origins`` (the measuring sensors,
by dataset.yaml name and/or pose in the sweep's frame) and a per-point ``sensor_id`` field
indexing them (`LidarSweep.origin_id`). The writer writes version 1 when no sweep is merged, so
older readers still read those folders.

Every version stores motion-compensated sweeps only (every point in the sensor frame at the sweep
timestamp): a raw sweep needs a pose per point, which the format has no place for, so
`write_folder_dataset` compensates raw sweeps (`LidarSweep.compensated`) and the sweeps read back
have no ``pose_fn``. Renderer ground truth on images (depth, semantic, sky) is not stored.
"""

from __future__ import annotations

import itertools
import os
import re
import shutil
from pathlib import Path
from typing import Annotated, Iterable, Iterator, Literal

import numpy as np
import yaml
from PIL import Image
from pydantic import AfterValidator, ConfigDict, Field, StringConstraints, field_validator, model_validator

from ..atomic import atomic_path
from ..camera.frames import CameraImage, Frames
from ..camera.model import Intrinsics
from ..config import ConfigError, StrictModel, load_yaml, repeated, validate_model
from ..errors import InputError
from ..io.images import read_rgb
from ..io.pointcloud import read_points, write_points
from ..labels import LABEL_IDS
from ..lidar.config import dump_config, load_config_file, load_lidar_config
from ..transforms import check_pose
from .base import Box, DatasetError, LidarSpec, LidarSweep, Sample, index_check

FORMAT = "scube-sim-folder"
VERSION = 2  # the newest version this module reads and writes
DATASET_FILE = "dataset.yaml"
SAMPLE_FILE = "sample.yaml"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
POINT_SUFFIXES = (".npz", ".pcd", ".ply", ".bin")

# --- schema ----------------------------------------------------------------------------------

# Sensor names become file names, and files live directly in the sample folder: letters, digits,
# '_', '-', '.', not starting with '.' (no folders, nothing hidden).
NAME_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$"
Name = Annotated[str, StringConstraints(pattern=NAME_PATTERN)]
FileName = Annotated[str, StringConstraints(pattern=NAME_PATTERN)]


def _matrix(shape: tuple[int, ...]):
    def check(v):
        try:
            a = np.asarray(v, np.float64)
        except ValueError:  # ragged rows
            raise ValueError(f"expected a {'x'.join(map(str, shape))} matrix, got rows of different lengths") from None
        if a.shape != shape:
            raise ValueError(f"expected a {'x'.join(map(str, shape))} matrix, got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError("holds NaN or Inf")
        return v
    return check


def _pose(v):
    check_pose(v, "pose")  # rigid: orthonormal rotation with det +1, last row 0 0 0 1
    return v


def _rotation(v):
    check_pose(np.block([[np.asarray(v), np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]), "rotation")
    return v


Pose = Annotated[list[list[float]], AfterValidator(_matrix((4, 4))), AfterValidator(_pose)]
Rotation = Annotated[list[list[float]], AfterValidator(_matrix((3, 3))), AfterValidator(_rotation)]
Vec3 = Annotated[list[float], AfterValidator(_matrix((3,)))]


class _Strict(StrictModel):
    """Dataset files are data, not hand-written settings: no type coercion either."""
    model_config = ConfigDict(strict=True)


class LidarEntry(_Strict):
    """A LiDAR of the rig: its model (exactly one of a preset name or a config YAML path relative
    to ROOT) and its sensor-to-ego mount."""

    preset: str | None = None
    config: str | None = None
    sensor_to_ego: Pose

    @model_validator(mode="after")
    def _one_model(self):
        if (self.preset is None) == (self.config is None):
            raise ValueError("give exactly one of 'preset' and 'config'")
        return self


class CameraEntry(_Strict):
    """Intrinsics as `scube_sim.camera.model.Intrinsics` (pixel centres at integer + 0.5)."""

    width: int = Field(gt=0)
    height: int = Field(gt=0)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    model: Literal["pinhole", "opencv", "fisheye"] = "pinhole"
    dist: list[float] = []


class DatasetFile(_Strict):
    format: Literal["scube-sim-folder"]
    version: Literal[1, 2]
    name: str = ""
    poses_from_icp: bool = False
    lidars: dict[Name, LidarEntry] = {}
    cameras: dict[Name, CameraEntry] = {}
    metadata: dict = {}


class ImageEntry(_Strict):
    file: FileName
    timestamp: float
    cam_to_world: Pose


class OriginEntry(_Strict):
    """One sensor of a merged cloud (version 2): `sensor`, its name (a LiDAR of dataset.yaml gives
    its model, and its mount when `pose` is absent), and/or `pose`, the sensor's pose in the
    sweep's frame (T_sweep_sensor)."""

    sensor: Name | None = None
    pose: Pose | None = None

    @model_validator(mode="after")
    def _something(self):
        if self.sensor is None and self.pose is None:
            raise ValueError("give 'sensor' (a LiDAR of dataset.yaml), 'pose' (T_sweep_sensor), or both")
        return self


class SweepEntry(_Strict):
    """Points in the sensor frame at `timestamp` (compensated: the format has no per-point poses).
    origins (version 2): the sensors of a merged cloud, indexed by the points' `sensor_id` field."""

    file: FileName
    timestamp: float
    sensor_to_world: Pose
    motion_compensated: Literal[True] = True
    intensity_max: float = Field(default=1.0, gt=0)
    origins: list[OriginEntry] | None = Field(default=None, min_length=1)

    @field_validator("origins")
    @classmethod
    def _sensors_once(cls, v):
        named = [(k, o.sensor) for k, o in enumerate(v or []) if o.sensor is not None]
        hit = repeated([s for _, s in named])
        if hit is not None:  # each measuring sensor once: its points are one sensor_id
            (i, s), (j, _) = named[hit[0]], named[hit[1]]
            raise ValueError(f"sensor {s!r} is listed twice (at [{i}] and [{j}])")
        return v


class BoxEntry(_Strict):
    """center (world, m), size (length, width, height along the box x, y, z), and exactly one of
    rotation (3x3 box-to-world) or yaw (radians about world z)."""

    center: Vec3
    size: Vec3
    rotation: Rotation | None = None
    yaw: float | None = None
    label: str
    label_id: int | None = Field(default=None, ge=0)
    velocity: list[float] | None = Field(default=None, min_length=3, max_length=3)  # m/s world; null or NaN: unknown
    track_id: str = ""

    @model_validator(mode="after")
    def _one_orientation(self):
        if (self.rotation is None) == (self.yaw is None):
            raise ValueError("give exactly one of 'rotation' and 'yaw'")
        if not all(s > 0 for s in self.size):
            raise ValueError(f"size must be positive, got {self.size}")
        return self


class SampleFile(_Strict):
    name: str
    timestamp: float
    log: str = ""  # the log (drive, scene) of the instant: converter context never crosses it
    ego_pose: Pose
    images: dict[Name, ImageEntry] = {}
    sweeps: dict[Name, SweepEntry] = {}
    boxes: list[BoxEntry] = []
    metadata: dict = {}

    @field_validator("images", "sweeps")
    @classmethod
    def _files_once(cls, v):
        files = [e.file for e in v.values()]  # two sensors' data in one file: one of them is wrong
        hit = repeated(files)
        if hit is not None:
            names = list(v)
            raise ValueError(f"file {files[hit[1]]!r} is listed twice ({names[hit[0]]}.file and {names[hit[1]]}.file)")
        return v


# --- reading ---------------------------------------------------------------------------------

def _load_yaml(path: Path) -> object:
    return load_yaml(path, error=DatasetError)


def _validate(model_cls, data, path: Path, what: str):
    return validate_model(model_cls, data, str(path), what, error=DatasetError)


def _rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class FolderDataset:
    """A ``scube-sim-folder`` dataset (see the module docstring). Samples are the folders under
    ``samples/`` in natural name order (the writer uses zero-padded indices); each is read on
    access."""

    name = "folder"

    def __init__(self, root: str | Path):
        self.root = Path(root)
        path = self.root / DATASET_FILE
        data = _load_yaml(path)
        if isinstance(data, dict):  # say "newer version" rather than "input should be 1"
            if data.get("format") != FORMAT:
                raise DatasetError(f"{path}: format: expected {FORMAT!r}, got {data.get('format')!r}")
            v = data.get("version")
            if isinstance(v, int) and not isinstance(v, bool) and v > VERSION:
                raise DatasetError(f"{path}: version: {v} is newer than this reader (reads version {VERSION})")
        spec = _validate(DatasetFile, data, path, "dataset settings")
        self.spec = spec
        self.version = spec.version
        self.dataset_name = spec.name
        self.poses_from_icp = spec.poses_from_icp
        self.lidars = {n: self._lidar(path, n, e) for n, e in spec.lidars.items()}
        self.cameras = {}
        for n, c in spec.cameras.items():
            try:
                self.cameras[n] = Intrinsics(c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.model, c.dist)
            except ValueError as exc:
                raise DatasetError(f"{path}: cameras.{n}: {exc}") from None
        sdir = self.root / "samples"
        if not sdir.is_dir():
            raise DatasetError(f"{sdir}: missing samples folder")
        # Hidden folders are the writer's temporaries (a sample being written). Natural order, so
        # 1000000 follows 999999 and hand-named folders like frame_2, frame_10 sort as numbers.
        self.sample_dirs = sorted((d for d in sdir.iterdir() if d.is_dir() and not d.name.startswith(".")),
                                  key=lambda d: [(0, int(t), "") if t.isdigit() else (1, 0, t)
                                                 for t in re.split(r"(\d+)", d.name) if t])

    def _lidar(self, path: Path, name: str, e: LidarEntry) -> LidarSpec:
        key = f"lidars.{name}"
        try:
            if e.preset is not None:
                cfg = load_lidar_config(e.preset)
            else:
                cfg_path = self.root / e.config
                if not cfg_path.is_file():
                    raise DatasetError(f"{path}: {key}.config: no such file {cfg_path}")
                cfg = load_config_file(cfg_path)
        except ConfigError as exc:
            raise DatasetError(f"{path}: {key}: {exc}") from None
        return LidarSpec(name, cfg, np.asarray(e.sensor_to_ego, np.float64))

    def __len__(self) -> int:
        return len(self.sample_dirs)

    def __iter__(self) -> Iterator[Sample]:
        for i in range(len(self)):
            yield self[i]

    def __getitem__(self, index: int) -> Sample:
        d = self.sample_dirs[index_check(index, len(self), f"{self.name} {self.root}")]
        path = d / SAMPLE_FILE
        s = _validate(SampleFile, _load_yaml(path), path, "sample")
        ego_pose = np.asarray(s.ego_pose, np.float64)
        images = []
        for cam, e in s.images.items():
            if cam not in self.cameras:
                raise DatasetError(f"{path}: images.{cam}: camera not listed under 'cameras' in "
                                   f"{self.root / DATASET_FILE}")
            images.append(self._image(d / e.file, cam, e, path))
        frames = Frames(images, ego_pose, s.timestamp, metadata={"dataset": self.name, "sample_dir": str(d)}) \
            if images else None
        sweeps = [self._sweep(d / e.file, name, e, path, ego_pose) for name, e in s.sweeps.items()]
        boxes = [self._box(b) for b in s.boxes]
        return Sample(name=s.name, timestamp=s.timestamp, ego_pose=ego_pose, frames=frames, sweeps=sweeps,
                      lidars=dict(self.lidars), boxes=boxes, metadata=dict(s.metadata), log=s.log)

    def _image(self, file: Path, cam: str, e: ImageEntry, src: Path) -> CameraImage:

        if file.suffix.lower() not in IMAGE_SUFFIXES:
            raise DatasetError(f"{src}: images.{cam}.file: {file.name!r} is not one of {', '.join(IMAGE_SUFFIXES)}")
        if not file.is_file():
            raise DatasetError(f"{src}: images.{cam}.file: missing file {file}")
        rgb = read_rgb(file, error=DatasetError)
        try:
            return CameraImage(cam, rgb, self.cameras[cam], np.asarray(e.cam_to_world, np.float64), e.timestamp)
        except ValueError as exc:
            raise DatasetError(f"{file}: {exc}") from None

    def _origins(self, name: str, e: SweepEntry, src: Path, ego_pose: np.ndarray):
        """(K, 4, 4) T_sweep_sensor and the names of a merged sweep's sensors (see OriginEntry)."""
        key = f"sweeps.{name}.origins"
        if self.version < 2:
            raise DatasetError(f"{src}: {key}: merged sweeps need version 2 in {self.root / DATASET_FILE} "
                               f"(it says {self.version})")
        poses, names = [], []
        to_sweep = np.linalg.inv(np.asarray(e.sensor_to_world, np.float64))
        for k, o in enumerate(e.origins):
            if o.pose is None and o.sensor not in self.lidars:
                raise DatasetError(f"{src}: {key}[{k}].sensor: {o.sensor!r} is not a LiDAR of "
                                   f"{self.root / DATASET_FILE} (have {', '.join(self.lidars) or 'none'}), "
                                   f"so its mount is unknown: give its 'pose'")
            if o.pose is not None:
                poses.append(np.asarray(o.pose, np.float64))
            else:  # the mount, through the sample's ego pose
                poses.append(to_sweep @ ego_pose @ self.lidars[o.sensor].sensor_to_ego)
            names.append(o.sensor if o.sensor is not None else f"{name}#{k}")
        return np.stack(poses), tuple(names)

    def _sweep(self, file: Path, name: str, e: SweepEntry, src: Path, ego_pose: np.ndarray) -> LidarSweep:
        if file.suffix.lower() not in POINT_SUFFIXES:
            raise DatasetError(f"{src}: sweeps.{name}.file: {file.name!r} is not one of {', '.join(POINT_SUFFIXES)}")
        if not file.is_file():
            raise DatasetError(f"{src}: sweeps.{name}.file: missing file {file}")
        try:
            pts = read_points(file)
        except ValueError as exc:
            raise DatasetError(str(exc)) from None
        fields = pts.dtype.names or ()
        for f in ("x", "y", "z"):
            if f not in fields:
                raise DatasetError(f"{file}: no field {f!r} (fields: {', '.join(fields)})")
        xyz = np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float64)
        get = lambda f, dt: pts[f].astype(dt) if f in fields else None  # noqa: E731
        origin_id = origins = names = None
        if e.origins is not None:
            origins, names = self._origins(name, e, src, ego_pose)
            if "sensor_id" not in fields:
                raise DatasetError(f"{file}: no field 'sensor_id' (fields: {', '.join(fields)}); "
                                   f"{src}: sweeps.{name}.origins needs it (index into origins per point)")
            ids = pts["sensor_id"]
            if ids.dtype.kind not in "iu" or (len(ids) and (ids.min() < 0 or ids.max() >= len(origins))):
                raise DatasetError(f"{file}: field 'sensor_id' must hold integers 0..{len(origins) - 1} (one per "
                                   f"entry of {src}: sweeps.{name}.origins), got {ids.dtype} "
                                   f"{ids.min() if len(ids) else ''}..{ids.max() if len(ids) else ''}")
            origin_id = ids.astype(np.int16)
        elif "sensor_id" in fields:
            raise DatasetError(f"{file}: has a 'sensor_id' field but {src}: sweeps.{name} has no 'origins' "
                               f"saying which sensors the ids mean")
        return LidarSweep(name, xyz, np.asarray(e.sensor_to_world, np.float64), e.timestamp,
                          intensity=get("intensity", np.float32), intensity_max=e.intensity_max,
                          ring=get("ring", np.int16), time_offset=get("time_offset", np.float64),
                          motion_compensated=True, origin_id=origin_id, origins=origins, origin_names=names,
                          source=str(file))

    @staticmethod
    def _box(b: BoxEntry) -> Box:
        rot = np.asarray(b.rotation, np.float64) if b.rotation is not None else _rz(b.yaw)
        vel = np.full(3, np.nan) if b.velocity is None else np.asarray(b.velocity, np.float64)
        label_id = b.label_id if b.label_id is not None else LABEL_IDS.get(b.label, 0)
        return Box(np.asarray(b.center, np.float64), np.asarray(b.size, np.float64), rot, label=label_id,
                   category=b.label, velocity=vel, track_id=b.track_id)


# --- writing ---------------------------------------------------------------------------------

def _rows(m) -> list[list[float]]:
    return np.asarray(m, np.float64).tolist()  # Python floats: YAML writes their repr (exact)


def _plain(v):
    """A value YAML can write safely: numpy scalars/arrays -> Python, paths -> str, others -> str."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    return str(v)


def _dump_yaml(path: Path, data: dict) -> None:
    text = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")


def _check_name(name: str, what: str) -> str:
    if not re.match(NAME_PATTERN, name):
        raise InputError(f"write_folder_dataset: {what} name {name!r} cannot be a file name "
                         f"(letters, digits, '_', '-', '.'; not starting with '.')")
    return name


def _points_array(sweep: LidarSweep, suffix: str) -> np.ndarray:
    """Structured points in the sensor frame: x y z float64 in .npz (exact), float32 in .pcd,
    .ply and .bin (what PCL, Open3D and KITTI tools expect: Open3D's legacy PCD reader misreads
    float64 x y z); intensity float32, ring int16, time_offset float64, sensor_id int16 (the
    fields the sweep has; sensor_id = `origin_id` of a merged sweep)."""
    xyz_dt = np.float64 if suffix == ".npz" else np.float32
    fields = [("x", xyz_dt), ("y", xyz_dt), ("z", xyz_dt)]
    if sweep.intensity is not None:
        fields.append(("intensity", np.float32))
    if sweep.ring is not None:
        fields.append(("ring", np.int16))
    if sweep.time_offset is not None:
        fields.append(("time_offset", np.float64))
    if sweep.origin_id is not None:
        fields.append(("sensor_id", np.int16))
    out = np.empty(len(sweep), fields)
    out["x"], out["y"], out["z"] = sweep.points[:, 0], sweep.points[:, 1], sweep.points[:, 2]
    for f in ("intensity", "ring", "time_offset"):
        if f in out.dtype.names:
            out[f] = getattr(sweep, f)
    if sweep.origin_id is not None:
        out["sensor_id"] = sweep.origin_id
    return out


def _sample_entry(sample: Sample, out_dir: Path, points_suffix: str, image_suffix: str) -> dict:
    """Write one sample's files into `out_dir` and return its sample.yaml mapping."""
    entry = {"name": str(sample.name), "timestamp": float(sample.timestamp), "ego_pose": _rows(sample.ego_pose)}
    if sample.log:  # only where the source has logs: files of single-log sources stay as they were
        entry["log"] = str(sample.log)
    for what, names in (("camera", sample.frames.names if sample.frames is not None else []),
                        ("LiDAR sweep", [sw.sensor for sw in sample.sweeps])):
        if len(set(names)) != len(names):
            raise InputError(f"write_folder_dataset: sample {sample.name!r}: two of its {what}s share a name "
                             f"({', '.join(names)}); files are named after them")
    images = {}
    for im in (sample.frames.images if sample.frames is not None else []):
        file = _check_name(im.name, "camera") + image_suffix
        # JPEG at quality 95 without chroma subsampling (PIL's default 75 and 4:2:0 visibly blur
        # fine texture and colour edges); PNG ignores both and is lossless.
        Image.fromarray(np.ascontiguousarray(im.image, np.uint8)).save(out_dir / file, quality=95, subsampling=0)
        images[im.name] = {"file": file, "timestamp": float(im.timestamp), "cam_to_world": _rows(im.cam_to_world)}
    sweeps = {}
    for sw in sample.sweeps:
        sw = sw.compensated()  # the format stores compensated sweeps only (no per-point poses)
        file = _check_name(sw.sensor, "LiDAR") + points_suffix
        if sw.merged and points_suffix == ".bin":
            raise InputError(f"write_folder_dataset: sample {sample.name!r}: sweep {sw.sensor!r} is merged from "
                             f"several LiDARs and KITTI .bin cannot store its sensor_id field: use npz, pcd or ply")
        write_points(out_dir / file, _points_array(sw, points_suffix))
        sweeps[sw.sensor] = {"file": file, "timestamp": float(sw.timestamp),
                             "sensor_to_world": _rows(sw.sensor_to_world), "motion_compensated": True,
                             "intensity_max": float(sw.intensity_max)}
        if sw.merged:
            # A name that cannot be a sensor name (the reader's '<sweep>#<k>' for unnamed ones) is left out.
            named = lambda k: sw.origin_names is not None and re.match(NAME_PATTERN, sw.origin_names[k])  # noqa: E731
            sweeps[sw.sensor]["origins"] = [{**({"sensor": sw.origin_names[k]} if named(k) else {}), "pose": _rows(t)}
                                            for k, t in enumerate(sw.origins)]
    boxes = []
    for b in sample.boxes:
        vel = np.asarray(b.velocity, np.float64)
        boxes.append({"center": _rows(b.center), "size": _rows(b.size), "rotation": _rows(b.rotation),
                      "label": str(b.category), "label_id": int(b.label),
                      "velocity": None if np.all(np.isnan(vel)) else _rows(vel), "track_id": str(b.track_id)})
    if images:
        entry["images"] = images
    if sweeps:
        entry["sweeps"] = sweeps
    if boxes:
        entry["boxes"] = boxes
    if sample.metadata:
        entry["metadata"] = _plain(sample.metadata)
    return entry


def write_folder_dataset(samples: Iterable[Sample], root: str | Path, *, points_format: str = "npz",
                         image_format: str = "png", name: str = "", overwrite: bool = False) -> Path:
    """Write `samples` (any iterable of Sample, e.g. a dataset adapter) as a scube-sim-folder.

    points_format: npz (x y z float64: exact), pcd or ply (x y z float32) or bin (KITTI: float32
    x y z intensity only); image_format: png (lossless) or jpg. Each sample is written into a hidden
    temporary folder and renamed into place when complete; dataset.yaml is written last, so a
    folder without it is an interrupted write. Raw sweeps are motion-compensated first. All
    samples must agree on each LiDAR's model and mount and each camera's intrinsics (ValueError
    naming the sensor otherwise). overwrite: replace an existing dataset at `root`.
    Returns `root`.
    """
    root = Path(root)
    points_suffix = "." + points_format.lower().lstrip(".")
    image_suffix = "." + image_format.lower().lstrip(".")
    if points_suffix not in POINT_SUFFIXES:
        raise InputError(f"write_folder_dataset: points_format {points_format!r}: expected one of "
                         f"{', '.join(s[1:] for s in POINT_SUFFIXES)}")
    if image_suffix not in (".png", ".jpg"):
        raise InputError(f"write_folder_dataset: image_format {image_format!r}: expected png or jpg")
    # the first sample is read before any folder is made: one that cannot be read leaves nothing behind
    source, samples = samples, iter(samples)
    first = next(samples, None)
    samples = itertools.chain([first], samples) if first is not None else samples
    sdir = root / "samples"
    if (root / DATASET_FILE).exists() or (sdir.is_dir() and any(sdir.iterdir())):
        if not overwrite:
            raise FileExistsError(f"{root}: already holds a dataset (pass overwrite=True, or --overwrite on the command line, to replace it)")
        (root / DATASET_FILE).unlink(missing_ok=True)  # first: an interrupted rewrite is then visibly incomplete
        shutil.rmtree(sdir, ignore_errors=True)
        shutil.rmtree(root / "lidars", ignore_errors=True)
    sdir.mkdir(parents=True, exist_ok=True)

    lidars: dict[str, LidarSpec] = {}
    cameras: dict[str, Intrinsics] = {}
    count = 0
    merged = False
    for sample in samples:
        merged |= any(sw.merged for sw in sample.sweeps)
        for n, spec in sample.lidars.items():
            _check_name(n, "LiDAR")
            have = lidars.setdefault(n, spec)
            if not (np.array_equal(have.sensor_to_ego, spec.sensor_to_ego) and have.config == spec.config):
                raise InputError(f"write_folder_dataset: sample {sample.name!r}: LiDAR {n!r} has another model or "
                                 f"mount than earlier samples; the folder format keeps one per sensor")
        for im in (sample.frames.images if sample.frames is not None else []):
            have = cameras.setdefault(_check_name(im.name, "camera"), im.intrinsics)
            if have != im.intrinsics:
                raise InputError(f"write_folder_dataset: sample {sample.name!r}: camera {im.name!r} has other "
                                 f"intrinsics than earlier samples; the folder format keeps one per camera")
        final = sdir / f"{count:06d}"
        tmp = sdir / f".{final.name}.tmp-{os.getpid()}"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        try:
            _dump_yaml(tmp / SAMPLE_FILE, _sample_entry(sample, tmp, points_suffix, image_suffix))
            os.replace(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        count += 1

    lidar_entries = {}
    for n, spec in lidars.items():
        rel = f"lidars/{n}.yaml"
        (root / "lidars").mkdir(exist_ok=True)
        dump_config(spec.config, root / rel)
        lidar_entries[n] = {"config": rel, "sensor_to_ego": _rows(spec.sensor_to_ego)}
    data = {"format": FORMAT, "version": VERSION if merged else 1, "name": str(name or getattr(source, "name", "")),
            "poses_from_icp": bool(getattr(source, "poses_from_icp", False)),
            "lidars": lidar_entries,
            "cameras": {n: _plain(c.to_dict()) for n, c in cameras.items()}}
    _dump_yaml(root / DATASET_FILE, data)
    return root


__all__ = ["FolderDataset", "write_folder_dataset", "FORMAT", "VERSION"]
