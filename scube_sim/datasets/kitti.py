"""KITTI: raw recordings (synced+rectified image_02 + Velodyne) and 3D-object frames (mmdetection3d).

    ds = KittiRawDataset("2011_09_26_drive_xxxx_sync")          # poses by ICP
    ds = KittiObjectDataset("folder with NNNNNN.bin/.png/.pkl")

Frames (both):

- Velodyne frame: x forward, y left, z up, metres; the ego frame *is* the Velodyne frame (the
  LiDAR models are the HDL-64E preset with an identity mount).
- rectified camera frame ("rect"): OpenCV axes (x right, y down, z forward), the common frame of
  KITTI's four rectified cameras, which is camera 0's after rotation by ``R0_rect``:
  ``x_rect = R0_rect @ Tr_velo_to_cam @ x_velo``.
- camera 2 (left colour): ``P2 = K @ [I | t]`` with ``t = inv(K) @ P2[:, 3]`` (mostly the 0.06 m
  baseline: ``P2[0, 3]`` = 44.857 px), i.e. ``x_cam2 = x_rect + t``; so the camera-2 pose is
  ``T_world_rect @ translate(-t)`` and its intrinsics are K (pixel centres moved to our +0.5
  convention, see `scube_sim.camera.model.Intrinsics.from_k`).

KITTI Velodyne sweeps are *not* deskewed by KITTI; the adapters still mark them
``motion_compensated=True`` (see each class for why that is a small error).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from ..camera.frames import CameraImage, Frames
from ..camera.model import Intrinsics
from ..errors import InputError
from ..io.images import read_rgb
from ..io.safe_pickle import load_pickle
from ..labels import LABEL_IDS
from ..lidar.config import load_lidar_config
from ..transforms import make_pose, transform_points
from .base import Box, DatasetError, LidarSpec, LidarSweep, Sample, as_matrix, index_check, require_file
from .odometry import log_poses

LIDAR = "velodyne"
LIDAR_MODEL = "HDL-64E"
# The Velodyne's height above the road on the KITTI car (Geiger et al., "Vision meets Robotics: The
# KITTI Dataset", IJRR 2013, the sensor setup figure: 1.73 m). The ego frame here is the Velodyne
# frame, so Frames carry it as ``ego_height_m`` (the converter's chunk starts at road level).
VELODYNE_HEIGHT_M = 1.73

# KITTI calib text (object-benchmark format): key -> count of numbers. Shapes after reading:
# P0..P3 (3, 4) projection matrices of the rectified cameras, R0_rect (3, 3), Tr_* (3, 4).
CALIB_KEYS = {"P0": 12, "P1": 12, "P2": 12, "P3": 12, "R0_rect": 9, "Tr_velo_to_cam": 12, "Tr_imu_to_velo": 12}
# The same matrices under the names of the KITTI tracking benchmark's calib files.
_CALIB_ALIASES = {"R_rect": "R0_rect", "Tr_velo_cam": "Tr_velo_to_cam", "Tr_imu_velo": "Tr_imu_to_velo"}

# mmdetection3d v1.x KITTI class ids (its KittiDataset METAINFO; DontCare is -1).
MMDET3D_KITTI_CLASSES = ("Pedestrian", "Cyclist", "Car", "Van", "Truck", "Person_sitting", "Tram", "Misc")

# KITTI classes -> our label table (`scube_sim.labels`); others (Misc, DontCare) -> 0.
LABEL_MAP = {
    "Car": "car", "Van": "truck", "Truck": "truck", "Pedestrian": "pedestrian", "Person_sitting": "pedestrian",
    "Cyclist": "bicyclist", "Tram": "other_vehicle",
}


# --- calibration ---------------------------------------------------------------------------

def read_kitti_calib(path: str | Path) -> dict[str, np.ndarray]:
    """Read a KITTI-object calib text (lines ``name: v1 v2 ...``) -> name -> float64 array.

    The seven keys of `CALIB_KEYS` are required, each with its count of numbers; they come back
    shaped: ``P0..P3`` (3, 4), ``R0_rect`` (3, 3), ``Tr_velo_to_cam`` / ``Tr_imu_to_velo`` (3, 4).
    Other keys are returned flat. Tracking-style names (``R_rect``, ``Tr_velo_cam``,
    ``Tr_imu_velo``, without the colon) are accepted too. Errors are DatasetError naming the file
    (and line and key)."""
    path = require_file(Path(path), "KITTI calibration file")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not a readable calib text ({exc})") from None
    out: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if ":" in line:
            key, _, rest = line.partition(":")
        else:
            key, _, rest = line.partition(" ")
        key = _CALIB_ALIASES.get(key.strip(), key.strip())
        try:
            values = np.array([float(v) for v in rest.split()], np.float64)
        except ValueError:
            raise DatasetError(f"{path}: line {lineno}: key {key!r} has a value that is not a number") from None
        if not np.all(np.isfinite(values)):
            raise DatasetError(f"{path}: line {lineno}: key {key!r} holds NaN or Inf")
        if key in out:
            raise DatasetError(f"{path}: line {lineno}: key {key!r} appears twice")
        out[key] = values
    for key, count in CALIB_KEYS.items():
        if key not in out:
            raise DatasetError(f"{path}: missing calibration key {key!r} (expected {count} numbers)")
        if out[key].size != count:
            raise DatasetError(f"{path}: key {key!r} has {out[key].size} numbers, expected {count}")
        out[key] = out[key].reshape((3, 3) if count == 9 else (3, 4))
    return out


def _homogeneous(m: np.ndarray) -> np.ndarray:
    """(3, 3) or (3, 4) -> (4, 4) with [0, 0, 0, 1] as the last row."""
    t = np.eye(4)
    t[:3, : m.shape[1]] = m
    return t


def camera_from_projection(p: np.ndarray, width: int, height: int, source: str, key: str):
    """A rectified KITTI camera's (3, 4) projection P = K @ [I | t] -> (Intrinsics, T_rect_cam (4, 4)).

    T_rect_cam = translate(-t): the camera sits at -t in the rectified frame, with its axes."""
    p = np.asarray(p, np.float64)
    k = p[:, :3]
    if abs(k[0, 1]) > 1e-9 or np.any(np.abs(k[2, :2]) > 1e-9) or abs(k[1, 0]) > 1e-9 or abs(k[2, 2] - 1) > 1e-9:
        raise DatasetError(f"{source}: {key} is not a rectified projection K @ [I | t] "
                           f"(K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]); got {p.tolist()}")
    t = np.linalg.solve(k, p[:, 3])
    intr = Intrinsics.from_k(k, width, height)
    return intr, make_pose(None, -t)


def read_velodyne(path: Path) -> np.ndarray:
    """A KITTI or KITTI-360 Velodyne .bin -> (N, 4) float32 x, y, z (metres, Velodyne frame),
    reflectance (0-1)."""
    raw = require_file(path, "Velodyne sweep").read_bytes()
    if len(raw) % 16:
        raise DatasetError(f"{path}: truncated KITTI Velodyne .bin: {len(raw)} bytes is not a multiple of 16 "
                           f"(4 float32 per point: x y z reflectance)")
    return np.frombuffer(raw, "<f4").reshape(-1, 4).copy()


def read_image(path: Path) -> np.ndarray:
    """A camera image file -> (H, W, 3) uint8 (`scube_sim.io.images.read_rgb`: any mode and bit depth)."""
    require_file(path, "camera image")
    return read_rgb(path, error=DatasetError)


def _label_id(name: str) -> int:
    return LABEL_IDS.get(LABEL_MAP.get(name, ""), 0)


# --- KITTI raw -----------------------------------------------------------------------------

class KittiRawDataset:
    """A KITTI raw drive: ``image_02/data/*.png`` + ``velodyne_points/data/*.bin`` (matched by
    file stem) and a calib text in KITTI-object format (`read_kitti_calib`).

    root: the drive folder; calib: the calib text (default: the single ``calib*.txt`` in root);
    poses: "icp" (the default) or "kiss-icp" (register all sweeps once, on first use, by our
    open3d ICP or kiss-icp: `datasets.odometry`, cached for later commands) or "identity" (every
    sample at the origin).

    This set has no poses and no timestamps. World = the first sample's Velodyne frame (ICP);
    ego = the Velodyne frame; sample k's timestamp = frame number k x 0.1 s (the 10 Hz rate).
    The camera is triggered when the scanner faces forward, so the image and the sweep share
    the timestamp. Sweeps are marked ``motion_compensated=True`` although KITTI does not deskew
    them: at this drive's low speed a point is off by at most half a turn's motion,
    and by nothing straight ahead where the timestamp is taken. Reflectance 0-1
    (``intensity_max`` 1); no ring index in the files.
    """

    name = "kitti_raw"

    def __init__(self, root: str | Path, calib: str | Path | None = None, poses: str = "icp"):
        self.root = Path(root)
        if poses not in ("kiss-icp", "icp", "identity"):
            raise InputError(f"kitti_raw: poses must be 'icp', 'kiss-icp' or 'identity', got {poses!r}")
        self.poses_mode = poses
        self.poses_from_icp = poses != "identity"
        img_dir, velo_dir = self.root / "image_02" / "data", self.root / "velodyne_points" / "data"
        for d in (img_dir, velo_dir):
            if not d.is_dir():
                raise DatasetError(f"{d}: missing folder (expected a KITTI raw drive with image_02/data and "
                                   f"velodyne_points/data)")
        images = {p.stem: p for p in img_dir.glob("*.png")}
        sweeps = {p.stem: p for p in velo_dir.glob("*.bin")}
        stems = sorted(set(images) & set(sweeps))
        if not stems:
            raise DatasetError(f"{self.root}: no frame has both image_02/data/<n>.png and velodyne_points/data/<n>.bin")
        self._frames = [(s, images[s], sweeps[s]) for s in stems]
        self.unmatched = sorted(set(images) ^ set(sweeps))  # frames with only one of the two files
        self.calib_path = self._find_calib(calib)
        self.calib = read_kitti_calib(self.calib_path)
        # Velodyne -> rectified camera frame, and camera 2 in the rectified frame.
        self.velo_to_rect = _homogeneous(self.calib["R0_rect"]) @ _homogeneous(self.calib["Tr_velo_to_cam"])
        self._lidar_config = None
        self._poses: np.ndarray | None = None
        self._icp: list | None = None

    def _find_calib(self, calib) -> Path:
        if calib is not None:
            p = Path(calib)
            if not p.is_absolute() and not p.exists():
                p = self.root / p
            return require_file(p, "KITTI calibration file (calib=)")
        found = sorted(self.root.glob("calib*.txt"))
        if len(found) != 1:
            what = "no calib*.txt" if not found else f"{len(found)} calib*.txt files ({', '.join(p.name for p in found)})"
            raise DatasetError(f"{self.root}: {what}; pass calib= a KITTI-object-format calib text "
                               f"(P0..P3, R0_rect, Tr_velo_to_cam, Tr_imu_to_velo)")
        return found[0]

    def _times(self) -> np.ndarray:
        stems = [s for s, _, _ in self._frames]
        if all(s.isdigit() for s in stems):
            return np.array([int(s) for s in stems], np.float64) * 0.1
        return np.arange(len(stems)) * 0.1

    @property
    def poses(self) -> np.ndarray:
        """(K, 4, 4) Velodyne-to-world poses of all samples (ICP on first use, then cached)."""
        if self._poses is None:
            if self.poses_mode == "identity":
                self._poses = np.broadcast_to(np.eye(4), (len(self), 4, 4)).copy()
                self._icp = []
            else:
                try:
                    est = log_poses([v for _, _, v in self._frames], lambda p: read_velodyne(p)[:, :3],
                                    self.poses_mode)
                except ValueError as exc:
                    raise DatasetError(f"{self.root}: {self.poses_mode} registration of the sweeps failed "
                                       f"({exc})") from None
                self._poses, self._icp = est.poses, est.steps
        return self._poses

    @property
    def icp_results(self) -> list:
        """The K - 1 `IcpResult`s of samples 1..K-1 (see `register_sequence`); [] for identity poses."""
        _ = self.poses  # runs the registration if it has not run yet
        return self._icp

    def __len__(self) -> int:
        return len(self._frames)

    def __iter__(self) -> Iterator[Sample]:
        for i in range(len(self)):
            yield self[i]

    def __getitem__(self, index: int) -> Sample:
        i = index_check(index, len(self), f"{self.name} {self.root}")
        stem, img_path, velo_path = self._frames[i]
        pose = self.poses[i]
        t = float(self._times()[i])
        pts = read_velodyne(velo_path)
        sweep = LidarSweep(LIDAR, pts[:, :3], pose, t, intensity=pts[:, 3].copy(), intensity_max=1.0,
                           motion_compensated=True)
        if self._lidar_config is None:
            self._lidar_config = load_lidar_config(LIDAR_MODEL)
        rgb = read_image(img_path)
        intr, rect_to_cam2 = camera_from_projection(self.calib["P2"], rgb.shape[1], rgb.shape[0],
                                                    str(self.calib_path), "P2")
        cam_to_world = pose @ np.linalg.inv(self.velo_to_rect) @ rect_to_cam2
        frames = Frames([CameraImage("image_02", rgb, intr, cam_to_world, t)], pose, t,
                        {"dataset": self.name, "frame": stem, "root": str(self.root),
                         "ego_height_m": VELODYNE_HEIGHT_M})
        meta = {"dataset": self.name, "frame": stem, "calib": str(self.calib_path), "poses": self.poses_mode,
                "timestamps": "frame number x 0.1 s (10 Hz); the set has none"}
        if self.poses_mode == "icp":
            # ICP of this sweep onto the previous one (none for the first: it defines the world)
            res = self._icp[i - 1] if i > 0 else None
            meta["icp_fitness"] = None if res is None else res.fitness
            meta["icp_rmse"] = None if res is None else res.rmse
        return Sample(name=stem, timestamp=t, ego_pose=pose, frames=frames, sweeps=[sweep], log=self.root.name,
                      lidars={LIDAR: LidarSpec(LIDAR, self._lidar_config, np.eye(4))}, metadata=meta)


# --- KITTI object (mmdetection3d infos) ----------------------------------------------------

class KittiObjectDataset:
    """KITTI 3D-object frames as mmdetection3d ships them: ``NNNNNN.bin`` (Velodyne points),
    ``NNNNNN.png`` (image_2) and ``NNNNNN.pkl`` (a v1.x info dict, read with the restricted
    unpickler). Samples: the .bin files that have a .pkl of the same stem, sorted by name.

    The benchmark has no poses and no times: world = ego = Velodyne frame, every pose is the
    identity and every timestamp 0. The points are mmdetection3d's "velodyne_reduced": cropped to
    the camera's field of view (every point projects into the image), not a full 360-degree
    sweep. Marked ``motion_compensated=True`` like KITTI raw (not deskewed; small at city speed).

    Boxes: ``instances[].bbox_3d = [x, y, z, l, h, w, ry]`` in the rectified camera frame, z the
    bottom centre, ry about camera y; converted to Velodyne-frame `Box`es (size l, w, h along the
    box's x forward, y left, z up). DontCare entries (label -1, no 3D box) are left out.
    """

    name = "kitti_object"
    poses_from_icp = False

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: not a folder (expected NNNNNN.bin, .png and .pkl files)")
        bins = sorted(self.root.glob("*.bin"))
        self._stems = [b.stem for b in bins if (self.root / f"{b.stem}.pkl").is_file()]
        if not self._stems:
            raise DatasetError(f"{self.root}: no NNNNNN.bin with a matching NNNNNN.pkl info file")
        self._lidar_config = None

    def __len__(self) -> int:
        return len(self._stems)

    def __iter__(self) -> Iterator[Sample]:
        for i in range(len(self)):
            yield self[i]

    def _entry(self, stem: str):
        path = self.root / f"{stem}.pkl"
        src = str(path)
        try:
            raw = load_pickle(path)
        except (OSError, ValueError) as exc:  # UnsafePickleError names the file and the class
            raise DatasetError(str(exc)) from None
        if not isinstance(raw, dict) or "data_list" not in raw:
            raise DatasetError(f"{src}: missing key data_list (expected an mmdetection3d v1.x info dict)")
        data_list = raw["data_list"]
        if not isinstance(data_list, list) or not data_list:
            raise DatasetError(f"{src}: 'data_list' must be a non-empty list")
        # the entry that names this .bin (a per-frame pkl holds just that one)
        for i, e in enumerate(data_list):
            lp = e.get("lidar_points", {}) if isinstance(e, dict) else {}
            if isinstance(lp, dict) and Path(str(lp.get("lidar_path", ""))).name == f"{stem}.bin":
                return raw, e, f"data_list[{i}]", src
        if len(data_list) == 1:
            return raw, data_list[0], "data_list[0]", src
        raise DatasetError(f"{src}: no data_list entry has lidar_points.lidar_path {stem}.bin")

    def __getitem__(self, index: int) -> Sample:
        stem = self._stems[index_check(index, len(self), f"{self.name} {self.root}")]
        raw, e, at, src = self._entry(stem)
        cam = _get(e, ("images", "CAM2"), src, at)
        cam2img = as_matrix(_get(cam, ("cam2img",), src, f"{at}.images.CAM2"), (4, 4), src,
                            f"{at}.images.CAM2.cam2img")
        lidar2cam = as_matrix(_get(cam, ("lidar2cam",), src, f"{at}.images.CAM2"), (4, 4), src,
                              f"{at}.images.CAM2.lidar2cam")  # = R0_rect @ Tr_velo_to_cam: Velodyne -> rect
        img_name = Path(str(cam.get("img_path", f"{stem}.png"))).name

        pts = read_velodyne(self.root / f"{stem}.bin")
        sweep = LidarSweep(LIDAR, pts[:, :3], np.eye(4), 0.0, intensity=pts[:, 3].copy(), intensity_max=1.0,
                           motion_compensated=True)
        rgb = read_image(self.root / img_name)
        intr, rect_to_cam2 = camera_from_projection(cam2img[:3], rgb.shape[1], rgb.shape[0], src,
                                                    f"{at}.images.CAM2.cam2img")
        rect_to_velo = np.linalg.inv(lidar2cam)
        frames = Frames([CameraImage("CAM2", rgb, intr, rect_to_velo @ rect_to_cam2, 0.0)], np.eye(4), 0.0,
                        {"dataset": self.name, "frame": stem, "fov_cropped": True,
                         "ego_height_m": VELODYNE_HEIGHT_M})

        classes = _class_names(raw.get("metainfo"))
        boxes, nlp = [], []
        for j, ins in enumerate(e.get("instances", []) or []):
            ia = f"{at}.instances[{j}]"
            label = int(_get(ins, ("bbox_label_3d",), src, ia))
            if label < 0:
                continue  # DontCare: a 2D region only (bbox_3d is a -1000 placeholder)
            bbox = as_matrix(_get(ins, ("bbox_3d",), src, ia), (7,), src, f"{ia}.bbox_3d")
            name = classes.get(label, f"class_{label}")
            boxes.append(_box_from_camera(bbox, rect_to_velo, name))
            nlp.append(int(ins.get("num_lidar_pts", -1)))

        if self._lidar_config is None:
            self._lidar_config = load_lidar_config(LIDAR_MODEL)
        meta = {"dataset": self.name, "frame": stem, "info": src, "fov_cropped": True,
                "sample_id": e.get("sample_id", e.get("sample_idx")),
                "num_lidar_pts": nlp}  # per box, KITTI's point count (for checks against the sweep)
        # each object frame is its own log: the set's frames are unrelated instants
        return Sample(name=stem, timestamp=0.0, ego_pose=np.eye(4), frames=frames, sweeps=[sweep], log=stem,
                      lidars={LIDAR: LidarSpec(LIDAR, self._lidar_config, np.eye(4))}, boxes=boxes, metadata=meta)


def _class_names(metainfo) -> dict[int, str]:
    """id -> class name: the info's own table (``categories`` name -> id, or ``classes``), else
    mmdetection3d's KITTI default (this demo pkl's metainfo holds only the dataset name)."""
    if isinstance(metainfo, dict):
        if isinstance(metainfo.get("categories"), dict):
            return {int(i): str(n) for n, i in metainfo["categories"].items()}
        if isinstance(metainfo.get("classes"), (list, tuple)):
            return dict(enumerate(map(str, metainfo["classes"])))
    return dict(enumerate(MMDET3D_KITTI_CLASSES))


def _box_from_camera(bbox: np.ndarray, rect_to_world: np.ndarray, label: str) -> Box:
    """KITTI camera box [x, y, z, l, h, w, ry] (rect frame, bottom centre, y down) -> world Box.

    In the camera frame the box's length axis is Ry(ry) @ x = (cos ry, 0, -sin ry), its up axis
    -y, and its width axis (sin ry, 0, cos ry) = up x length, so the box-to-rect rotation has these
    three as columns (x forward, y left, z up, as `Box` wants)."""
    x, y, z, length, height, width, ry = bbox
    c, s = np.cos(ry), np.sin(ry)
    box_to_rect = np.array([[c, s, 0.0], [0.0, 0.0, -1.0], [-s, c, 0.0]])
    centre_rect = np.array([x, y - 0.5 * height, z])  # y points down: the centre is h/2 above the bottom
    centre = transform_points(rect_to_world, centre_rect[None])[0]
    rot = rect_to_world[:3, :3] @ box_to_rect
    return Box(centre, np.array([length, width, height]), rot, label=_label_id(label), category=label)


def _get(mapping, keys: tuple, source: str, at: str):
    """mapping[k0][k1]..., or a DatasetError naming the file and the key path."""
    cur, path = mapping, at
    for k in keys:
        nxt = f"{path}.{k}" if path else str(k)
        if not isinstance(cur, dict) or k not in cur:
            raise DatasetError(f"{source}: missing key {nxt}")
        cur, path = cur[k], nxt
    return cur


__all__ = ["KittiRawDataset", "KittiObjectDataset", "read_kitti_calib", "camera_from_projection", "CALIB_KEYS",
           "LABEL_MAP"]
