"""TRI's DGP format (``TRI-ML/dgp``): scenes of posed cameras, a LiDAR and 3D boxes, as JSON.

    ds = TriDgpDataset("scene_02")              # a scene folder (one scene_*.json in it)
    ds = TriDgpDataset("scene_02/scene_fe9f....json")
    ds = TriDgpDataset("scenes")                 # a folder of scene folders: one log each

Layout of a scene folder (DGP's SceneProto written as JSON; the protobuf ``.bin`` form is not read)::

    scene_<sha1>.json                  samples[] (calibration_key, datum_keys), data[] (datums), ontologies
    calibration/<calibration_key>.json names[], intrinsics[] (fx fy cx cy skew ...), extrinsics[] (pose)
    ontology/<key>.json                items[] (id, name): the class table of one annotation type
    point_cloud/<SENSOR>/<us>.npz      key 'data': (N, F) float, columns per the datum's point_format
    rgb/<CAMERA>/<us>.jpg              images
    bounding_box_3d/<SENSOR>/<us>.json annotations[]: box (pose, length, width, height), class_id, instance_id

One `Sample` per entry of ``samples``, in time order; one log per scene, named after the scene's
``name`` or, where that is empty (the unit-test scenes), its folder: converter context never
crosses scenes.

Frames (DGP's ``dgp/utils/pose.py``, ``structures/bounding_box_3d.py`` and the test scene's README):

- Every datum carries its own sensor pose in the scene's world frame (``pose``: quaternion
  ``qw qx qy qz`` + translation, metres) at its own timestamp, so each camera is posed where it
  was when it fired (before the LiDAR in the test scene), not through the static calibration
  (the two differ by the ego's motion in between).
- ``extrinsics[k]`` = sensor k's pose in the vehicle frame (x forward, y left, z up; in the test
  scene its origin lies on the road: near returns on the road lie at z about 0, so no
  ``ego_height_m`` is set). ``Sample.ego_pose`` = the LiDAR datum's pose @ inv(its extrinsic)
  (the first camera's where a sample has no point cloud).
- Cameras: OpenCV (x right, y down, z forward); pinhole ``fx fy cx cy`` with OpenCV's pixel
  centres (`Intrinsics.from_k` moves them by half a pixel); a non-zero ``skew`` or distortion
  other than k1 k2 p1 p2 k3 is refused (DatasetError naming the file and key).
- Points: in the point-cloud datum's sensor frame, metres; INTENSITY as stored (0-0.93 in the
  test scene: ``intensity_max`` 1). The sweep is taken as motion-compensated (DGP gives no
  per-point times) with ``sensor_to_world`` = the datum's pose.
- 3D boxes: ``box.pose`` is the box centre in the LiDAR frame, ``length`` along the box x,
  ``width`` along y, ``height`` along z; labels by the class *name* of the bounding-box-3D
  ontology (``ontologies["1"]``: DGP's annotation type BOUNDING_BOX_3D) through `LABEL_MAP`.

Times: DGP stamps are UTC ISO strings (and the file names are microseconds); the test scene's are
shifted to the year 2464, so only differences mean anything. Sample and image timestamps are
seconds since the earliest datum of the dataset (exact to the microsecond; seconds since 1970 of
a year-2464 stamp would keep only ~2 us in float64); ``metadata["timestamp_us"]`` keeps the
stored stamp.

**The LiDAR cloud has no single origin.** The test scene's cloud is stored in the vehicle
frame, whose origin is on the road (the LIDAR extrinsic is identity), and the scene stores no
per-point sensor id (point_format X Y Z INTENSITY) nor the measuring units' mounts.
`origins.check_origin` fails on every sweep: far more returns lie behind another return, as seen
from the stated origin, than one sensor allows, and that origin lies below the ground. So the
sweep is left single-origin (its origins cannot be told from the data) and
`origins.require_single_origin` flags it (MergedCloudError): build and fidelity refuse it unless
``assume_single_origin``. (Restated at a roof unit's height above the vehicle origin it would
pass: a guess this adapter does not make.) The camera converter does not use the sweep. The
boxes' ``num_points`` exceed the returns inside them several times: the stored cloud is thinner
than the one annotated.

LiDAR model (`LIDAR_MODEL`): there is no preset for this sensor (a merged, non-spinning pattern;
the README likens the rig to DDAD's), so ``Sample.lidars`` holds the VLS-128 preset (the
longest-range preset, 1-245 m) with the range limits widened to 1.0-250 m (the test scene's returns reach
231 m from 1.3 m), the calibration's mount, and compensated output: a stand-in for a simulated
sensor of similar reach, not a model of the real scan pattern.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from ..camera.frames import CameraImage, Frames
from ..camera.model import Intrinsics
from ..config import json_loads
from ..errors import InputError
from ..io.images import read_rgb
from ..labels import LABEL_IDS
from ..lidar.config import ConfigError, LidarConfig, load_lidar_config
from ..transforms import invert_pose, make_pose, quat_to_rotmat, rotmat_to_euler
from .base import Box, DatasetError, LidarSpec, LidarSweep, Sample, index_check, require_file

SCENE_GLOB = "scene*.json"
IMAGE, POINT_CLOUD = "image", "point_cloud"
BOX3D = "1"  # DGP AnnotationType BOUNDING_BOX_3D (0 is BOUNDING_BOX_2D): key of datum annotations and ontologies
LIDAR_MODEL = "VLS-128"
RANGE_M = (1.0, 250.0)

# DGP ontology class names (case ignored) -> our label table (`scube_sim.labels`); others -> 0 (undefined).
LABEL_MAP = {
    "car": "car", "truck": "truck", "bus/rv/caravan": "bus", "bus": "bus", "person": "pedestrian",
    "pedestrian": "pedestrian", "motorcycle": "motorcycle", "bicycle": "bicycle", "bicyclist": "bicyclist",
    "cyclist": "bicyclist", "motorcyclist": "motorcyclist", "trailer": "other_vehicle",
    "towed object": "other_vehicle", "train": "other_vehicle", "van": "car",
    # "Wheeled Slow" (wheelchairs, strollers, scooters) has no class of ours: undefined.
}
_DISTORTION = ("k1", "k2", "p1", "p2", "k3")  # OpenCV's order, `Intrinsics` "opencv"
_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)


# --- reading helpers ---------------------------------------------------------------------------

def _read_json(path: Path, what: str):
    require_file(path, what)
    try:
        return json_loads(path.read_text(encoding="utf-8"), path, DatasetError)  # a key twice: refused
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from None


def _need(mapping, key: str, src: str, at: str = ""):
    """mapping[key], or a DatasetError naming the file and the key path (``at.key``)."""
    path = f"{at}.{key}" if at else key
    if not isinstance(mapping, dict):
        raise DatasetError(f"{src}: {at or 'top level'} is a {type(mapping).__name__}, expected an object with "
                           f"key {key!r}")
    if key not in mapping:
        raise DatasetError(f"{src}: missing key {path}")
    return mapping[key]


def _number(mapping, key: str, src: str, at: str) -> float:
    v = _need(mapping, key, src, at)
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise DatasetError(f"{src}: {at}.{key} is not a number ({v!r})") from None
    if not np.isfinite(f):
        raise DatasetError(f"{src}: {at}.{key} is not finite")
    return f


def _pose(p, src: str, at: str) -> np.ndarray:
    """A DGP Pose (``rotation`` qw qx qy qz, ``translation`` x y z) -> (4, 4) T_parent_child."""
    rot = _need(p, "rotation", src, at)
    tr = _need(p, "translation", src, at)
    # proto3 JSON leaves out zero fields: a missing component is 0.
    q = np.array([float(rot.get(k, 0.0)) if isinstance(rot, dict) else np.nan for k in ("qw", "qx", "qy", "qz")])
    t = np.array([float(tr.get(k, 0.0)) if isinstance(tr, dict) else np.nan for k in ("x", "y", "z")])
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
        raise DatasetError(f"{src}: {at}: expected rotation {{qw, qx, qy, qz}} and translation {{x, y, z}} numbers")
    if abs(np.linalg.norm(q) - 1.0) > 1e-3:
        raise DatasetError(f"{src}: {at}.rotation is not a unit quaternion (norm {np.linalg.norm(q):.6f})")
    return make_pose(quat_to_rotmat(q), t)


def _stamp_us(value, src: str, at: str) -> int:
    """A DGP timestamp (proto3 JSON: ISO 8601 UTC, 'Z') -> integer microseconds since 1970."""
    try:
        dt = datetime.fromisoformat(str(value).replace("Z", "+00:00"))
    except ValueError:
        raise DatasetError(f"{src}: {at} is not an ISO 8601 timestamp ({value!r})") from None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=timezone.utc)
    return (dt - _EPOCH) // timedelta(microseconds=1)


def _read_rgb(path: Path) -> np.ndarray:
    return read_rgb(path, error=DatasetError)


# --- the scene index -----------------------------------------------------------------------------

@dataclass
class _Datum:
    key: str
    sensor: str
    kind: str  # IMAGE or POINT_CLOUD
    stamp_us: int
    pose: np.ndarray  # (4, 4) sensor-to-world at stamp_us
    body: dict  # the datum's image / point_cloud message
    at: str  # where it sits in the scene JSON, for messages


@dataclass
class _Entry:
    scene: _Scene
    index: int  # position in the scene's samples[]
    stamp_us: int
    calibration_key: str
    data: list[_Datum]
    skipped: list[str] = field(default_factory=list)  # datum types not read (radar, files, ...)


@dataclass
class _Calibration:
    path: Path
    names: list[str]
    intrinsics: dict[str, dict]
    extrinsics: dict[str, np.ndarray]  # sensor -> (4, 4) sensor-to-vehicle


class _Scene:
    """One DGP scene JSON: its samples, datums, calibrations and box ontology."""

    def __init__(self, path: Path):
        self.path = path
        self.dir = path.parent
        src = str(path)
        raw = _read_json(path, "DGP scene JSON")
        if not isinstance(raw, dict):
            raise DatasetError(f"{src}: expected a DGP scene (JSON object), got {type(raw).__name__}")
        self.raw_name = str(raw.get("name", "") or "")
        self.log = self.raw_name or self.dir.name
        data = _need(raw, "data", src)
        samples = _need(raw, "samples", src)
        if not isinstance(data, list) or not isinstance(samples, list) or not samples:
            raise DatasetError(f"{src}: 'data' and 'samples' must be lists, 'samples' non-empty")
        by_key = {}
        for i, d in enumerate(data):
            key = str(_need(d, "key", src, f"data[{i}]"))
            by_key[key] = (i, d)
        self.calibrations: dict[str, _Calibration] = {}
        self.entries = []
        for j, s in enumerate(samples):
            at = f"samples[{j}]"
            sid = _need(s, "id", src, at)
            stamp = _stamp_us(_need(sid, "timestamp", src, f"{at}.id"), src, f"{at}.id.timestamp")
            ckey = str(_need(s, "calibration_key", src, at))
            if ckey not in self.calibrations:
                self.calibrations[ckey] = self._calibration(ckey, f"{at}.calibration_key")
            entry = _Entry(self, j, stamp, ckey, [])
            for k, dk in enumerate(_need(s, "datum_keys", src, at) or []):
                if str(dk) not in by_key:
                    raise DatasetError(f"{src}: {at}.datum_keys[{k}] {dk!r} is not the key of any entry of 'data'")
                i, d = by_key[str(dk)]
                datum = self._datum(i, d, src)
                if datum is None:
                    entry.skipped.append(str(d.get("id", {}).get("name", dk)))
                    continue
                if datum.sensor not in self.calibrations[ckey].extrinsics:
                    raise DatasetError(f"{self.calibrations[ckey].path}: no sensor {datum.sensor!r} in 'names' "
                                       f"(named by {src} {datum.at}.id.name)")
                entry.data.append(datum)
            self.entries.append(entry)
        self.entries.sort(key=lambda e: e.stamp_us)  # time order (stable for ties)
        self.labels = self._ontology(raw.get("ontologies") or {})

    def _datum(self, i: int, d, src: str) -> _Datum | None:
        at = f"data[{i}]"
        did = _need(d, "id", src, at)
        body = _need(d, "datum", src, at)
        kinds = [k for k in (IMAGE, POINT_CLOUD) if isinstance(body, dict) and k in body]
        if not kinds:
            return None
        kind = kinds[0]
        msg = body[kind]
        return _Datum(key=str(d["key"]), sensor=str(_need(did, "name", src, f"{at}.id")), kind=kind,
                      stamp_us=_stamp_us(_need(did, "timestamp", src, f"{at}.id"), src, f"{at}.id.timestamp"),
                      pose=_pose(_need(msg, "pose", src, f"{at}.datum.{kind}"), src, f"{at}.datum.{kind}.pose"),
                      body=msg, at=at)

    def _calibration(self, key: str, named_by: str) -> _Calibration:
        path = self.dir / "calibration" / f"{key}.json"
        raw = _read_json(path, f"calibration (the {named_by} of {self.path})")
        src = str(path)
        names = [str(n) for n in _need(raw, "names", src)]
        intr = _need(raw, "intrinsics", src)
        extr = _need(raw, "extrinsics", src)
        if not (isinstance(intr, list) and isinstance(extr, list) and len(intr) == len(extr) == len(names)):
            raise DatasetError(f"{src}: 'names', 'intrinsics' and 'extrinsics' must be lists of one length")
        return _Calibration(path, names, dict(zip(names, intr)),
                            {n: _pose(e, src, f"extrinsics[{k}]") for k, (n, e) in enumerate(zip(names, extr))})

    def _ontology(self, ontologies: dict) -> dict[int, str]:
        """class_id -> class name of the bounding-box-3D ontology ({} where the scene has none)."""
        key = ontologies.get(BOX3D) if isinstance(ontologies, dict) else None
        if key is None:
            return {}
        path = self.dir / "ontology" / f"{key}.json"
        raw = _read_json(path, f"ontology (ontologies.{BOX3D} of {self.path})")
        src = str(path)
        out = {}
        for k, item in enumerate(_need(raw, "items", src) or []):
            # proto3 JSON leaves out zero fields: a missing id is 0
            out[int(item.get("id", 0)) if isinstance(item, dict) else 0] = str(_need(item, "name", src, f"items[{k}]"))
        return out


def _find_scenes(root: Path) -> list[Path]:
    if root.is_file():
        return [root]
    if not root.is_dir():
        raise DatasetError(f"{root}: no such DGP scene folder or scene JSON")
    here = sorted(root.glob(SCENE_GLOB))
    if len(here) > 1:
        raise DatasetError(f"{root}: {len(here)} scene JSON files ({', '.join(p.name for p in here)}); open one "
                           f"of them as the path")
    if here:
        return here
    below = []
    for d in sorted(p for p in root.iterdir() if p.is_dir()):
        found = sorted(d.glob(SCENE_GLOB))
        if len(found) > 1:
            raise DatasetError(f"{d}: {len(found)} scene JSON files ({', '.join(p.name for p in found)})")
        below += found
    if not below:
        raise DatasetError(f"{root}: no DGP scene JSON ({SCENE_GLOB}) in the folder or its sub-folders")
    return below


def lidar_config(sensor: str, sensor_to_ego: np.ndarray) -> LidarConfig:
    """The stand-in model of a DGP LiDAR (module docstring): `LIDAR_MODEL` with the range limits
    widened to `RANGE_M`, the calibration's mount and compensated output."""
    base = load_lidar_config(LIDAR_MODEL)
    roll, pitch, yaw = rotmat_to_euler(sensor_to_ego[:3, :3])
    data = base.model_dump()
    data["name"] = f"DGP {sensor} ({base.name} stand-in)"
    data["range"] = {"min_m": RANGE_M[0], "max_m": RANGE_M[1]}
    data["mount"] = {"xyz": [float(v) for v in sensor_to_ego[:3, 3]],
                     "rpy_deg": [float(np.degrees(a)) for a in (roll, pitch, yaw)]}
    data["motion"] = {"output": "compensated", "reference": "start"}
    data["notes"] = (f"Stand-in for TRI DGP {sensor} (no preset: a merged, non-spinning pattern): the {base.name} "
                     f"preset with the range widened to {RANGE_M[0]:g}-{RANGE_M[1]:g} m (test scene returns: "
                     f"1.3-231 m), mount from the DGP calibration. {base.notes}").strip()
    try:
        return LidarConfig.model_validate(data)
    except ValueError as exc:  # pydantic's ValidationError
        raise ConfigError(f"tri_dgp: LiDAR stand-in for {sensor}: {exc}") from None


# --- the adapter ---------------------------------------------------------------------------------

class TriDgpDataset:
    """DGP scenes (see the module docstring): `root` a scene folder, a scene JSON, or a folder of
    scene folders (one log each). load_images: False leaves `Sample.frames` None without decoding
    the JPEGs (LiDAR-only use). Images are decoded when a sample is read, not at opening."""

    name = "tri_dgp"
    poses_from_icp = False

    def __init__(self, root: str | Path, load_images: bool = True):
        self.root = Path(root)
        self.load_images = bool(load_images)
        self.scenes = [_Scene(p) for p in _find_scenes(self.root)]
        logs = [s.log for s in self.scenes]
        if len(set(logs)) != len(logs):
            twice = next(n for n in logs if logs.count(n) > 1)
            raise DatasetError(f"{self.root}: two scenes share the name {twice!r}; logs must be distinct")
        self._entries = [e for s in self.scenes for e in s.entries]
        stamps = [d.stamp_us for e in self._entries for d in e.data] + [e.stamp_us for e in self._entries]
        self.time_origin_us = min(stamps)  # seconds are counted from here (module docstring: Times)
        self._lidar_configs: dict[tuple, LidarConfig] = {}

    def __len__(self) -> int:
        return len(self._entries)

    def __iter__(self) -> Iterator[Sample]:
        for i in range(len(self)):
            yield self[i]

    def _seconds(self, stamp_us: int) -> float:
        return (stamp_us - self.time_origin_us) * 1e-6

    def __getitem__(self, index: int) -> Sample:
        e = self._entries[index_check(index, len(self), f"{self.name} {self.root}")]
        scene, calib = e.scene, e.scene.calibrations[e.calibration_key]
        order = {n: k for k, n in enumerate(calib.names)}
        clouds = sorted((d for d in e.data if d.kind == POINT_CLOUD), key=lambda d: order[d.sensor])
        cams = sorted((d for d in e.data if d.kind == IMAGE), key=lambda d: order[d.sensor])
        ref = clouds[0] if clouds else (cams[0] if cams else None)
        if ref is None:
            raise DatasetError(f"{scene.path}: samples[{e.index}] has no image or point_cloud datum")
        ego_pose = ref.pose @ invert_pose(calib.extrinsics[ref.sensor])
        name = f"{scene.log}_{e.stamp_us}"
        timestamp = self._seconds(e.stamp_us)
        sweeps = [self._sweep(d, scene) for d in clouds]
        lidars = {d.sensor: LidarSpec(d.sensor, self._lidar_config(d.sensor, calib.extrinsics[d.sensor]),
                                      calib.extrinsics[d.sensor]) for d in clouds}
        boxes, counts = self._boxes(clouds[0], scene) if clouds else ([], [])
        frames = None
        if self.load_images and cams:
            images = [self._image(d, scene, calib) for d in cams]
            frames = Frames(images, ego_pose, timestamp, metadata={"dataset": self.name, "sample": name,
                                                                   "scene": str(scene.path)})
        meta = {"dataset": self.name, "scene": str(scene.path), "scene_sample_index": e.index,
                "timestamp_us": e.stamp_us, "time_origin_us": self.time_origin_us,
                "calibration": str(calib.path), "num_lidar_pts": counts}
        if e.skipped:
            meta["skipped_datums"] = list(e.skipped)
        return Sample(name=name, timestamp=timestamp, ego_pose=ego_pose, frames=frames, sweeps=sweeps,
                      lidars=lidars, boxes=boxes, metadata=meta, log=scene.log)

    def _lidar_config(self, sensor: str, mount: np.ndarray) -> LidarConfig:
        key = (sensor, mount.tobytes())
        if key not in self._lidar_configs:
            self._lidar_configs[key] = lidar_config(sensor, mount)
        return self._lidar_configs[key]

    def _sweep(self, d: _Datum, scene: _Scene) -> LidarSweep:
        src = str(scene.path)
        at = f"{d.at}.datum.point_cloud"
        path = require_file(scene.dir / str(_need(d.body, "filename", src, at)),
                            f"point cloud of {d.sensor} ({src} {at}.filename)")
        fmt = [str(f) for f in _need(d.body, "point_format", src, at)]
        for f in ("X", "Y", "Z"):
            if f not in fmt:
                raise DatasetError(f"{src}: {at}.point_format {fmt} has no {f!r}")
        try:
            with np.load(path, allow_pickle=False) as z:
                if "data" not in z.files:
                    raise DatasetError(f"{path}: missing key 'data' (has {', '.join(z.files) or 'none'})")
                pts = np.asarray(z["data"], np.float64)
        except (OSError, ValueError) as exc:
            raise DatasetError(f"{path}: not a readable npz ({exc})") from None
        if pts.ndim != 2 or pts.shape[1] != len(fmt):
            raise DatasetError(f"{path}: 'data' has shape {pts.shape}, expected (N, {len(fmt)}) for point_format {fmt}")
        if not np.all(np.isfinite(pts)):
            raise DatasetError(f"{path}: 'data' holds NaN or Inf")
        col = {f: k for k, f in enumerate(fmt)}
        xyz = pts[:, [col["X"], col["Y"], col["Z"]]]
        intensity = pts[:, col["INTENSITY"]].astype(np.float32) if "INTENSITY" in col else None
        ring = pts[:, col["RING_ID"]].astype(np.int16) if "RING_ID" in col else None
        return LidarSweep(d.sensor, xyz, d.pose, self._seconds(d.stamp_us), intensity=intensity, intensity_max=1.0,
                          ring=ring, motion_compensated=True, source=str(path))

    def _image(self, d: _Datum, scene: _Scene, calib: _Calibration) -> CameraImage:
        src, csrc = str(scene.path), str(calib.path)
        at = f"{d.at}.datum.image"
        path = require_file(scene.dir / str(_need(d.body, "filename", src, at)),
                            f"image of {d.sensor} ({src} {at}.filename)")
        k = calib.names.index(d.sensor)
        c = calib.intrinsics[d.sensor]
        where = f"intrinsics[{k}] ({d.sensor})"
        fx, fy = _number(c, "fx", csrc, where), _number(c, "fy", csrc, where)
        cx, cy = _number(c, "cx", csrc, where), _number(c, "cy", csrc, where)
        if float(c.get("skew", 0.0) or 0.0) != 0.0:
            raise DatasetError(f"{csrc}: {where}.skew is {c['skew']}: skewed pixels are not supported")
        if c.get("fisheye"):
            raise DatasetError(f"{csrc}: {where}.fisheye is set: DGP's fisheye model is not supported")
        extra = [key for key, v in c.items() if key not in ("fx", "fy", "cx", "cy", "skew", "fov", "fisheye",
                                                              *_DISTORTION) and isinstance(v, (int, float)) and v]
        if extra:
            raise DatasetError(f"{csrc}: {where} has distortion terms {extra}: only k1 k2 p1 p2 k3 are supported")
        dist = [float(c.get(key, 0.0) or 0.0) for key in _DISTORTION]
        model, dist = ("opencv", dist) if any(dist) else ("pinhole", [])
        rgb = _read_rgb(path)
        h, w = rgb.shape[:2]
        want = (int(d.body.get("width", w)), int(d.body.get("height", h)))
        if want != (w, h):
            raise DatasetError(f"{path}: image is {w}x{h} but {src} {at} says {want[0]}x{want[1]}")
        try:
            intr = Intrinsics.from_k([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], w, h, model, dist)
            return CameraImage(d.sensor, rgb, intr, d.pose, self._seconds(d.stamp_us))
        except InputError as exc:
            raise DatasetError(f"{csrc}: {where}: {exc}") from None

    def _boxes(self, d: _Datum, scene: _Scene) -> tuple[list[Box], list[int]]:
        """The 3D boxes annotated on the LiDAR datum -> world boxes (and each box's num_points)."""
        ann = d.body.get("annotations") or {}
        rel = ann.get(BOX3D) if isinstance(ann, dict) else None
        if rel is None:
            return [], []
        path = scene.dir / str(rel)
        raw = _read_json(path, f"3D boxes of {d.sensor} ({scene.path} {d.at}.datum.point_cloud.annotations.{BOX3D})")
        src = str(path)
        boxes, counts = [], []
        for i, a in enumerate(_need(raw, "annotations", src) or []):
            at = f"annotations[{i}]"
            b = _need(a, "box", src, at)
            pose = d.pose @ _pose(_need(b, "pose", src, f"{at}.box"), src, f"{at}.box.pose")
            size = [_number(b, k, src, f"{at}.box") for k in ("length", "width", "height")]
            if not all(s > 0 for s in size):
                raise DatasetError(f"{src}: {at}.box: length, width and height must be positive, got {size}")
            cid = int(a.get("class_id", 0))  # proto3 JSON leaves out a zero id
            if scene.labels and cid not in scene.labels:
                raise DatasetError(f"{src}: {at}.class_id {cid} is not in the scene's 3D box ontology "
                                   f"(ids {sorted(scene.labels)})")
            category = scene.labels.get(cid, f"class_{cid}")
            label = LABEL_IDS.get(LABEL_MAP.get(category.lower(), ""), 0)
            boxes.append(Box(pose[:3, 3].copy(), np.array(size), pose[:3, :3].copy(),
                             label=label, category=category, track_id=str(a.get("instance_id", ""))))
            counts.append(int(a.get("num_points", -1)))
        return boxes, counts


__all__ = ["LABEL_MAP", "LIDAR_MODEL", "RANGE_M", "TriDgpDataset", "lidar_config"]
