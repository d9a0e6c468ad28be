"""nuScenes keyframes from an mmdetection3d v1.x info file (``*.pkl``) and the files it names.

    ds = NuScenesDataset("folder")          # the single *.pkl in the folder
    ds = NuScenesDataset("folder", info="nuscenes_infos_val.pkl", load_images=False)

One `Sample` per ``data_list`` entry, in time order. Frames:

- world = the nuScenes global (map) frame, metres; ego = the vehicle frame (x forward, y left,
  z up); ``Sample.ego_pose`` = ``ego2global`` at the LiDAR timestamp (the only ego pose stored).
- LIDAR_TOP sensor frame: x right, y forward, z up (nuScenes' own; ``lidar2ego`` rotates it by
  about -90 degrees about z into the ego frame).
- cameras: OpenCV (x right, y down, z forward); each image has its own timestamp and pose.

The info file is read with the restricted unpickler (`scube_sim.io.safe_pickle`): a stream that
names any class other than builtins and numpy arrays is refused, so a crafted pkl cannot run code.
Files named in it (``lidar_path``, ``img_path``) are looked up by basename in the folder, then in
``samples/<sensor>/`` and ``sweeps/<sensor>/`` below it (the full nuScenes layout).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from ..camera.frames import CameraImage, Frames
from ..camera.model import Intrinsics
from ..errors import NotFoundError
from ..io.images import read_rgb
from ..io.safe_pickle import load_pickle
from ..labels import LABEL_IDS
from ..lidar.config import load_lidar_config
from ..transforms import transform_points
from .base import Box, DatasetError, LidarSpec, LidarSweep, Sample, as_matrix, index_check, require_file

LIDAR = "LIDAR_TOP"
CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")

# nuScenes detection classes -> our label table (`scube_sim.labels`); others -> 0 (undefined).
LABEL_MAP = {
    "car": "car", "truck": "truck", "bus": "bus", "trailer": "other_vehicle",
    "construction_vehicle": "other_vehicle", "pedestrian": "pedestrian", "motorcycle": "motorcycle",
    "bicycle": "bicycle", "traffic_cone": "construction_cone", "barrier": "fence",
}

_POINT_FIELDS = 5  # float32 x, y, z, intensity, ring per point in a nuScenes .pcd.bin


def read_nuscenes_bin(path: Path) -> np.ndarray:
    """A nuScenes ``.pcd.bin`` -> (N, 5) float32: x, y, z (metres, LiDAR frame), intensity (0-255),
    ring (0-31). Raises DatasetError naming the file when its size is not whole points."""
    raw = require_file(Path(path), "LiDAR sweep").read_bytes()
    size = 4 * _POINT_FIELDS
    if len(raw) % size:
        raise DatasetError(f"{path}: truncated nuScenes sweep: {len(raw)} bytes is not a multiple of {size} "
                           f"(5 float32 per point: x y z intensity ring)")
    return np.frombuffer(raw, "<f4").reshape(-1, _POINT_FIELDS).copy()


def _rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class _Camera:
    name: str
    img_path: str
    timestamp: float
    k: np.ndarray  # (3, 3)
    cam2ego: np.ndarray  # (4, 4), camera at its own time -> ego at the camera time
    lidar2cam: np.ndarray  # (4, 4), LiDAR at the LiDAR time -> camera at the camera time
    token: str


@dataclass
class _Instance:
    bbox: np.ndarray  # (7,) x, y, z (box centre), l, w, h, yaw in the LiDAR frame
    velocity: np.ndarray  # (2,) vx, vy in the LiDAR frame, NaN if unknown
    label: int
    num_lidar_pts: int


@dataclass
class _Entry:
    index: int  # position in data_list
    token: str
    timestamp: float
    ego2global: np.ndarray
    lidar2ego: np.ndarray
    lidar_path: str
    cameras: list[_Camera]
    instances: list[_Instance]


class NuScenesDataset:
    """nuScenes samples from an mmdetection3d v1.x info pkl (see the module docstring).

    root: folder with the pkl and the files it names; info: the pkl (a path, or a name inside
    root; default: the single ``*.pkl`` in root); load_images: False leaves `Sample.frames` None
    and skips decoding the JPEGs (LiDAR-only use).

    Each sample has one sweep, ``LIDAR_TOP``: (N, 3) points in the sensor frame, intensity 0-255
    (``intensity_max`` 255), ring (int16, 0-31). nuScenes sweeps are ego-motion compensated to
    the sweep timestamp, so ``motion_compensated`` is True and ``sensor_to_world`` =
    ``ego2global @ lidar2ego``. The LiDAR model is the HDL-32E preset mounted at ``lidar2ego``.
    """

    name = "nuscenes"
    poses_from_icp = False

    def __init__(self, root: str | Path, info: str | Path | None = None, load_images: bool = True):
        self.root = Path(root)
        self.load_images = bool(load_images)
        self.info_path = self._find_info(info)
        self._lidar_config = None
        raw = self._load(self.info_path)
        src = str(self.info_path)
        if not isinstance(raw, dict):
            raise DatasetError(f"{src}: expected an mmdetection3d v1.x info dict, got {type(raw).__name__}")
        self.metainfo = raw.get("metainfo", {})
        if not isinstance(self.metainfo, dict):
            raise DatasetError(f"{src}: 'metainfo' is a {type(self.metainfo).__name__}, expected a dict")
        cats = self.metainfo.get("categories", {})
        if not isinstance(cats, dict):
            raise DatasetError(f"{src}: 'metainfo.categories' is a {type(cats).__name__}, expected a dict name -> id")
        self.categories = {int(i): str(n) for n, i in cats.items()}  # id -> class name
        data_list = _need(raw, "data_list", src, "")
        if not isinstance(data_list, list) or not data_list:
            raise DatasetError(f"{src}: 'data_list' must be a non-empty list of samples")
        entries = [self._parse_entry(i, e, src) for i, e in enumerate(data_list)]
        self._entries = sorted(entries, key=lambda e: e.timestamp)  # time order (stable for ties)
        self._logs = scene_logs(self._entries, [e.get("scene_token") if isinstance(e, dict) else None
                                                for e in data_list])

    # --- reading the info file ----------------------------------------------------------------
    def _find_info(self, info) -> Path:
        if info is not None:
            p = Path(info)
            if not p.is_absolute() and not p.exists():
                p = self.root / p
            return require_file(p, "mmdetection3d info file (info=)")
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: not a folder (expected a folder with an mmdetection3d info .pkl)")
        pkls = sorted(self.root.glob("*.pkl"))
        if not pkls:
            raise DatasetError(f"{self.root}: no *.pkl info file in the folder")
        if len(pkls) > 1:
            raise DatasetError(f"{self.root}: {len(pkls)} *.pkl files ({', '.join(p.name for p in pkls)}); "
                               f"choose one with info=")
        return pkls[0]

    @staticmethod
    def _load(path: Path):
        try:
            return load_pickle(path)
        except (OSError, ValueError) as exc:  # UnsafePickleError is a ValueError naming the file and class
            raise DatasetError(str(exc)) from None

    def _parse_entry(self, i: int, e, src: str) -> _Entry:
        at = f"data_list[{i}]"
        if not isinstance(e, dict):
            raise DatasetError(f"{src}: {at} is a {type(e).__name__}, expected a dict")
        lp = _need(e, "lidar_points", src, at)
        feats = lp.get("num_pts_feats", _POINT_FIELDS) if isinstance(lp, dict) else _POINT_FIELDS
        if feats != _POINT_FIELDS:
            raise DatasetError(f"{src}: {at}.lidar_points.num_pts_feats is {feats}, expected {_POINT_FIELDS} "
                               f"(x y z intensity ring)")
        cams = []
        images = e.get("images", {}) or {}
        if not isinstance(images, dict):
            raise DatasetError(f"{src}: {at}.images is a {type(images).__name__}, expected a dict camera -> info")
        for name, c in images.items():
            ca = f"{at}.images.{name}"
            cams.append(_Camera(
                name=str(name),
                img_path=str(_need(c, "img_path", src, ca)),
                timestamp=_number(_need(c, "timestamp", src, ca), src, f"{ca}.timestamp"),
                k=as_matrix(_need(c, "cam2img", src, ca), (3, 3), src, f"{ca}.cam2img"),
                cam2ego=as_matrix(_need(c, "cam2ego", src, ca), (4, 4), src, f"{ca}.cam2ego"),
                lidar2cam=as_matrix(_need(c, "lidar2cam", src, ca), (4, 4), src, f"{ca}.lidar2cam"),
                token=str(c.get("sample_data_token", "")),
            ))
        order = {n: k for k, n in enumerate(CAMERAS)}
        cams.sort(key=lambda c: order.get(c.name, len(order)))
        instances = []
        for j, ins in enumerate(e.get("instances", []) or []):
            ia = f"{at}.instances[{j}]"
            bbox = as_matrix(_need(ins, "bbox_3d", src, ia), (7,), src, f"{ia}.bbox_3d")
            vel = np.asarray(ins.get("velocity", [np.nan, np.nan]), np.float64).reshape(-1)
            if vel.shape != (2,):
                raise DatasetError(f"{src}: {ia}.velocity has shape {vel.shape}, expected (2,)")
            instances.append(_Instance(bbox, vel, int(_need(ins, "bbox_label_3d", src, ia)),
                                       int(ins.get("num_lidar_pts", -1))))
        return _Entry(
            index=i,
            token=str(e.get("token", f"data_list[{i}]")),
            timestamp=_number(_need(e, "timestamp", src, at), src, f"{at}.timestamp"),
            ego2global=as_matrix(_need(e, "ego2global", src, at), (4, 4), src, f"{at}.ego2global"),
            lidar2ego=as_matrix(_need(lp, "lidar2ego", src, f"{at}.lidar_points"), (4, 4), src,
                                f"{at}.lidar_points.lidar2ego"),
            lidar_path=str(_need(lp, "lidar_path", src, f"{at}.lidar_points")),
            cameras=cams,
            instances=instances,
        )

    # --- files ------------------------------------------------------------------------------
    def _resolve(self, name: str, sensor: str, what: str) -> Path:
        base = Path(name).name
        for p in (self.root / base, self.root / "samples" / sensor / base, self.root / "sweeps" / sensor / base):
            if p.is_file():
                return p
        raise DatasetError(f"{self.root / base}: missing {what} named in {self.info_path.name} ({name!r})")

    # --- Dataset protocol -------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._entries)

    def __iter__(self) -> Iterator[Sample]:
        for i in range(len(self)):
            yield self[i]

    def __getitem__(self, index: int) -> Sample:
        e = self._entries[index_check(index, len(self), f"{self.name} {self.info_path}")]
        lidar_to_world = e.ego2global @ e.lidar2ego

        pts = read_nuscenes_bin(self._resolve(e.lidar_path, LIDAR, "LiDAR sweep"))
        sweep = LidarSweep(LIDAR, pts[:, :3], lidar_to_world, e.timestamp, intensity=pts[:, 3].copy(),
                           intensity_max=255.0, ring=pts[:, 4].astype(np.int16), motion_compensated=True)

        if self._lidar_config is None:
            self._lidar_config = load_lidar_config("HDL-32E")
        lidars = {LIDAR: LidarSpec(LIDAR, self._lidar_config, e.lidar2ego)}

        boxes = [self._box(ins, lidar_to_world) for ins in e.instances]
        frames = self._frames(e, lidar_to_world) if self.load_images else None
        meta = {
            "dataset": self.name, "token": e.token, "info": str(self.info_path), "data_list_index": e.index,
            # per box, the nuScenes annotation's LiDAR point count (for checks against the sweep)
            "num_lidar_pts": [ins.num_lidar_pts for ins in e.instances],
        }
        return Sample(name=e.token, timestamp=e.timestamp, ego_pose=e.ego2global, frames=frames,
                      sweeps=[sweep], lidars=lidars, boxes=boxes, metadata=meta, log=self._logs[index % len(self)])

    def _frames(self, e: _Entry, lidar_to_world: np.ndarray) -> Frames:

        images = []
        for c in e.cameras:
            path = self._resolve(c.img_path, c.name, f"{c.name} image")
            rgb = read_rgb(path, error=DatasetError)
            # lidar2cam maps the LiDAR at the LiDAR time to the camera at *its* time (mmdet3d
            # composes lidar -> ego(t_lidar) -> global -> ego(t_cam) -> cam), so this is the camera
            # pose at its own timestamp; ego2global @ cam2ego would place it where the ego was at
            # the LiDAR time instead (off by the ego's motion between the two stamps).
            cam_to_world = lidar_to_world @ np.linalg.inv(c.lidar2cam)
            images.append(CameraImage(c.name, rgb, Intrinsics.from_k(c.k, rgb.shape[1], rgb.shape[0]),
                                      cam_to_world, c.timestamp))
        meta = {"dataset": self.name, "token": e.token,
                "sample_data_tokens": {c.name: c.token for c in e.cameras}}
        return Frames(images, e.ego2global, e.timestamp, meta)

    def _box(self, ins: _Instance, lidar_to_world: np.ndarray) -> Box:
        x, y, z, length, width, height, yaw = ins.bbox
        # In mmdet3d's nuScenes infos bbox_3d holds the box's *gravity* centre (nuScenes' own
        # box centre): mmdet3d's NuScenesDataset builds LiDARInstance3DBoxes from it with
        # origin=(0.5, 0.5, 0.5) and only then moves it to the bottom. (Read as a bottom centre,
        # the boxes sit h/2 too high and hold half the points that num_lidar_pts says.)
        # yaw turns the box's length axis from LiDAR +x towards +y.
        centre = transform_points(lidar_to_world, np.array([[x, y, z]]))[0]
        rot = lidar_to_world[:3, :3] @ _rz(yaw)
        vel = np.full(3, np.nan)
        if np.all(np.isfinite(ins.velocity)):
            vel = lidar_to_world[:3, :3] @ np.array([ins.velocity[0], ins.velocity[1], 0.0])
            # nuScenes velocities are horizontal in the global frame; mmdet3d dropped the small z
            # they get in the tilted LiDAR frame, so rotating back leaves a spurious vz: drop it.
            vel[2] = 0.0
        label = self.categories.get(ins.label, "unknown" if ins.label < 0 else f"class_{ins.label}")
        return Box(centre, np.array([length, width, height]), rot, label=LABEL_IDS.get(LABEL_MAP.get(label, ""), 0),
                   category=label, velocity=vel)

    def camera_pose_from_cam2ego(self, index: int, camera: str) -> np.ndarray:
        """(4, 4) ``ego2global @ cam2ego``: where `camera` would be if the ego had not moved
        since the LiDAR time. For comparison only; frames use the per-camera-time pose."""
        e = self._entries[index_check(index, len(self), self.name)]
        for c in e.cameras:
            if c.name == camera:
                return e.ego2global @ c.cam2ego
        raise NotFoundError(f"{self.info_path}: no camera {camera!r}; have {[c.name for c in e.cameras]}")


def _need(mapping, key: str, source: str, at: str):
    """mapping[key], or a DatasetError naming the file and the full key path (``at.key``)."""
    path = f"{at}.{key}" if at else key
    if not isinstance(mapping, dict):
        raise DatasetError(f"{source}: {at or 'top level'} is a {type(mapping).__name__}, expected a dict "
                           f"with key {key!r}")
    if key not in mapping:
        raise DatasetError(f"{source}: missing key {path}")
    return mapping[key]


def _number(value, source: str, key: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise DatasetError(f"{source}: {key} is not a number ({value!r})") from None
    if not np.isfinite(v):
        raise DatasetError(f"{source}: {key} is not finite")
    return v


# Consecutive keyframes (2 Hz) of one scene lie 0.5 s and a few metres apart; an info file that spans
# scenes and names none jumps between them by more.
SCENE_GAP_S = 1.0
SCENE_JUMP_M = 30.0


def scene_logs(entries: list, scene_tokens: list) -> list[str]:
    """The log (scene) of each time-ordered entry: its info's ``scene_token`` where the file has
    one (looked up by the entry's `index` into the data list), else a new scene wherever
    consecutive keyframes lie more than SCENE_GAP_S apart in time or SCENE_JUMP_M in space
    (mmdetection3d v1.x infos drop the scene token); such a scene is named after its first
    keyframe's token."""
    out: list[str] = []
    for i, e in enumerate(entries):
        token = scene_tokens[e.index] if e.index < len(scene_tokens) else None
        if token:
            out.append(f"scene-token:{token}")
            continue
        prev = entries[i - 1] if i else None
        same = (prev is not None and out[-1].startswith("scene@") and e.timestamp - prev.timestamp <= SCENE_GAP_S
                and float(np.linalg.norm(e.ego2global[:3, 3] - prev.ego2global[:3, 3])) <= SCENE_JUMP_M)
        out.append(out[-1] if same else f"scene@{e.token}")
    return out


__all__ = ["NuScenesDataset", "read_nuscenes_bin", "LABEL_MAP", "scene_logs"]
