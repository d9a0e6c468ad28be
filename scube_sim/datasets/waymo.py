"""One Waymo Open Dataset frame from its extracted calibration/pose/label JSON and camera JPEGs.

    ds = WaymoFrameDataset("waymo-open-dataset-frame")   # frame_metadata.json + camera_images/
    sample = ds[0]                                       # 5 posed images, 64-beam TOP model, boxes

``frame_metadata.json`` is our extract of a ``waymo.open_dataset.Frame`` (keys as in Waymo's
``dataset.proto``: ``vehicle_pose_vehicle_to_global_4x4``, ``camera_calibrations[]``,
``laser_calibrations[]``, ``images[]`` with ``file`` relative to the folder, or null when the
record held no image, and ``laser_labels[]``). The folder may also be given as the JSON file.

Frames:

- world = Waymo's global frame (metres); ego = the vehicle frame, x forward, y left, z up;
  ``Sample.ego_pose`` = ``vehicle_pose_vehicle_to_global_4x4`` at ``timestamp_micros``.
- Waymo's camera frame is x forward (optical axis), y left, z up (the body convention), so
  ``cam_to_world = pose_vehicle_to_global_4x4_at_image @ extrinsic_camera_to_vehicle_4x4 @
  BODY_FROM_OPTICAL`` gives our OpenCV camera; each image is stamped ``pose_timestamp_s``.
- Intrinsics ``f_u f_v c_u c_v k1 k2 p1 p2 k3``: OpenCV's distortion order (Waymo's
  camera_model.cc: "k3 same as p1 in OpenCV", "k4 same as p2", "k5 same as k3"). Its image
  coordinates run over [0, width) (``CameraModel::InImage``), as ours do, so c_u, c_v are used
  as given. Rolling shutter (readout ~47 ms, left to right) is not modelled.

No LiDAR returns: the frames this adapter was written for carry calibrations only (the range
images are not in the extract), so ``sweeps`` is empty. ``lidars`` holds the lasers whose beam
inclinations are published (TOP, via `from_waymo_frame`); the short-range lasers only publish a
min/max inclination and are left out.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterator

import numpy as np

from ..camera.frames import CameraImage, Frames
from ..camera.model import Intrinsics
from ..camera.rig import BODY_FROM_OPTICAL
from ..config import json_loads, listed_twice
from ..io.images import read_rgb
from ..labels import LABEL_IDS
from ..lidar.config import ConfigError
from ..lidar.importers import from_waymo_frame
from ..transforms import transform_points
from .base import Box, DatasetError, LidarSpec, Sample, as_matrix, index_check, require_file, require_key

METADATA = "frame_metadata.json"

# Waymo label.proto Label.Type (name, or its enum number) -> our label table (`scube_sim.labels`).
TYPE_TO_LABEL = {"TYPE_UNKNOWN": "undefined", "TYPE_VEHICLE": "car", "TYPE_PEDESTRIAN": "pedestrian",
                 "TYPE_SIGN": "sign", "TYPE_CYCLIST": "bicyclist"}
TYPE_NUMBERS = {0: "TYPE_UNKNOWN", 1: "TYPE_VEHICLE", 2: "TYPE_PEDESTRIAN", 3: "TYPE_SIGN", 4: "TYPE_CYCLIST"}


def _rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _read_rgb(path: Path) -> np.ndarray:
    return read_rgb(path, error=DatasetError)


def _names_once(entries, src: str, key: str) -> None:
    """A camera or laser that `entries` (a list of mappings with `name`) lists twice: DatasetError."""
    names = [str(e["name"]) for e in entries if isinstance(e, dict) and "name" in e] if isinstance(entries, list) else []
    msg = listed_twice(names)
    if msg:
        raise DatasetError(f"{src}: {key}: name {msg}")


class WaymoFrameDataset:
    """The single frame of an extracted Waymo record folder (see the module docstring).

    root: the folder holding ``frame_metadata.json`` (or that file); load_images: False leaves
    ``Sample.frames`` None without decoding the JPEGs.
    """

    name = "waymo"
    poses_from_icp = False

    def __init__(self, root: str | Path, load_images: bool = True):
        root = Path(root)
        self.meta_path = require_file(root if root.is_file() else root / METADATA, "Waymo frame metadata")
        self.root = self.meta_path.parent
        self.load_images = bool(load_images)
        try:
            self.meta = json_loads(self.meta_path.read_text(encoding="utf-8"), self.meta_path, DatasetError)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise DatasetError(f"{self.meta_path}: not valid JSON ({exc})") from None
        if not isinstance(self.meta, dict):
            raise DatasetError(f"{self.meta_path}: expected a JSON object, got {type(self.meta).__name__}")

    def __len__(self) -> int:
        return 1

    def __iter__(self) -> Iterator[Sample]:
        yield self[0]

    def __getitem__(self, index: int) -> Sample:
        index_check(index, 1, f"{self.name} {self.root}")
        src = str(self.meta_path)
        m = self.meta
        timestamp = float(require_key(m, "timestamp_micros", src)) * 1e-6
        ego_pose = as_matrix(require_key(m, "vehicle_pose_vehicle_to_global_4x4", src), (4, 4), src,
                             "vehicle_pose_vehicle_to_global_4x4")
        context = str(m.get("context_name", self.root.name))
        return Sample(
            name=f"{context}_{int(m['timestamp_micros'])}",
            timestamp=timestamp,
            ego_pose=ego_pose,
            frames=self._frames(ego_pose, timestamp) if self.load_images else None,
            sweeps=[],  # the extract holds no range images
            lidars=self._lidars(),
            boxes=self._boxes(ego_pose),
            log=context,
            metadata={"dataset": self.name, "context_name": context, "timestamp_micros": int(m["timestamp_micros"]),
                      "stats": m.get("stats", {}), "metadata_file": src},
        )

    def _frames(self, ego_pose: np.ndarray, timestamp: float) -> Frames | None:
        src = str(self.meta_path)
        calibs = {}
        _names_once(require_key(self.meta, "camera_calibrations", src), src, "camera_calibrations")
        _names_once([im for im in self.meta.get("images") or [] if im.get("file") is not None], src, "images")
        for i, c in enumerate(require_key(self.meta, "camera_calibrations", src)):
            calibs[str(require_key(c, "name", src, f"camera_calibrations[{i}] key"))] = c
        images = []
        for i, im in enumerate(self.meta.get("images") or []):
            where = f"images[{i}]"
            if im.get("file") is None:
                continue  # the record held no JPEG for this camera
            cam = str(require_key(im, "name", src, f"{where} key"))
            c = require_key(calibs, cam, src, "camera_calibrations entry for camera")
            key = f"camera_calibrations[{cam}]"
            vals = as_matrix(require_key(c, "intrinsic_fu_fv_cu_cv_k1_k2_p1_p2_k3", src, f"{key} key"), (9,), src,
                             f"{key}.intrinsic_fu_fv_cu_cv_k1_k2_p1_p2_k3")
            fu, fv, cu, cv = vals[:4]
            try:
                intr = Intrinsics(int(require_key(c, "width", src, f"{key} key")),
                                  int(require_key(c, "height", src, f"{key} key")),
                                  fu, fv, cu, cv, "opencv", vals[4:])
            except ValueError as exc:
                raise DatasetError(f"{src}: {key}: {exc}") from None
            ext = as_matrix(require_key(c, "extrinsic_camera_to_vehicle_4x4", src, f"{key} key"), (4, 4), src,
                            f"{key}.extrinsic_camera_to_vehicle_4x4")
            pose = as_matrix(require_key(im, "pose_vehicle_to_global_4x4_at_image", src, f"{where} key"), (4, 4),
                             src, f"{where}.pose_vehicle_to_global_4x4_at_image")
            t = float(require_key(im, "pose_timestamp_s", src, f"{where} key"))
            path = require_file(self.root / str(im["file"]), f"image of camera {cam} ({src} {where}.file)")
            rgb = _read_rgb(path)
            try:
                images.append(CameraImage(cam, rgb, intr, pose @ ext @ BODY_FROM_OPTICAL, t))
            except ValueError as exc:
                raise DatasetError(f"{path}: {exc}") from None
        if not images:
            return None
        return Frames(images, ego_pose, timestamp, metadata={"dataset": self.name, "metadata_file": src})

    def _lidars(self) -> dict[str, LidarSpec]:
        src = str(self.meta_path)
        out = {}
        _names_once(require_key(self.meta, "laser_calibrations", src), src, "laser_calibrations")
        for i, laser in enumerate(require_key(self.meta, "laser_calibrations", src)):
            name = str(require_key(laser, "name", src, f"laser_calibrations[{i}] key"))
            if not laser.get("beam_inclinations_rad"):
                continue  # only min/max inclination published: no per-beam table to build a model from
            mount = as_matrix(require_key(laser, "extrinsic_laser_to_vehicle_4x4", src, f"laser_calibrations[{i}] key"),
                              (4, 4), src, f"laser_calibrations[{i}].extrinsic_laser_to_vehicle_4x4")
            try:
                cfg = from_waymo_frame(self.meta_path, name, name=f"Waymo {name}")
            except ConfigError as exc:
                raise DatasetError(str(exc)) from None
            out[name] = LidarSpec(name, cfg, mount)
        return out

    def _boxes(self, ego_pose: np.ndarray) -> list[Box]:
        """laser_labels (vehicle frame at the frame time) -> world boxes. heading is the yaw
        about the vehicle z axis; length/width/height along the box x/y/z."""
        src = str(self.meta_path)
        boxes = []
        for i, lab in enumerate(self.meta.get("laser_labels") or []):
            where = f"laser_labels[{i}]"
            kind = require_key(lab, "type", src, f"{where} key")
            kind = TYPE_NUMBERS.get(kind, kind) if isinstance(kind, int) else str(kind)
            if kind not in TYPE_TO_LABEL:
                raise DatasetError(f"{src}: {where}.type is {kind!r}, expected one of {', '.join(TYPE_TO_LABEL)}")
            center = as_matrix(require_key(lab, "center_xyz_vehicle_m", src, f"{where} key"), (3,), src,
                               f"{where}.center_xyz_vehicle_m")
            size = as_matrix(require_key(lab, "length_width_height_m", src, f"{where} key"), (3,), src,
                             f"{where}.length_width_height_m")
            heading = float(as_matrix(require_key(lab, "heading_rad", src, f"{where} key"), (), src,
                                      f"{where}.heading_rad"))
            boxes.append(Box(center=transform_points(ego_pose, center[None])[0], size=size,
                             rotation=ego_pose[:3, :3] @ _rz(heading), category=kind,
                             label=LABEL_IDS[TYPE_TO_LABEL[kind]], track_id=str(lab.get("id", ""))))
        return boxes
