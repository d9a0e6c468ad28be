"""KITTI-360: the front perspective camera (``image_00``, rectified) and the Velodyne HDL-64E.

    ds = Kitti360Dataset("KITTI-360")                      # layout (a): KITTI-360's own
    ds = Kitti360Dataset("kitti360-2013_05_28-seq")        # layout (b): a data/ folder, no poses

Two layouts are read; the root is the folder you open:

(a) KITTI-360's documented layout (root = the folder holding ``data_2d_raw/``)::

        data_2d_raw/<drive>/image_00/data_rect/NNNNNNNNNN.png     (+ image_00/timestamps.txt)
        data_3d_raw/<drive>/velodyne_points/data/NNNNNNNNNN.bin   (+ velodyne_points/timestamps.txt)
        calibration/perspective.txt, calib_cam_to_velo.txt, calib_cam_to_pose.txt
        data_poses/<drive>/poses.txt                               (optional)

    Every drive (``2013_05_28_drive_XXXX_sync``) with both folders is read, in name order, one
    log each; ``drive=`` picks one.

(b) the folder names of the 20-frame excerpt in ``../shared/data/kitti360-2013_05_28-seq``
    (root = the folder holding ``data/``, or ``data/`` itself)::

        data/image_00/good_data/NNNNNNNNNN.png, data/velodyne_points/good_data/NNNNNNNNNN.bin
        data/calibration/{perspective,calib_cam_to_velo,calib_cam_to_pose}.txt
        data/image_00/timestamps.txt, data/velodyne_points/timestamps.txt

    One log, named ``drive=`` or else after the folder holding ``data/`` (the excerpt does not
    say which drive number it is). This layout has no poses file.

Frames (KITTI-360's documentation and its ``kitti360scripts``):

- Velodyne frame: x forward, y left, z up, metres. The ego frame *is* the Velodyne frame (HDL-64E
  preset, identity mount), as in the KITTI raw adapter, ``ego_height_m`` 1.73 (see
  `VELODYNE_HEIGHT_M`).
- ``calib_cam_to_velo.txt``: 12 numbers, row-major (3, 4), *unrectified* camera 00 -> Velodyne.
- ``perspective.txt``: ``P_rect_00`` (3, 4) = K @ [I | 0] of the rectified camera 00,
  ``R_rect_00`` (3, 3) unrectified -> rectified (``x_rect = R_rect_00 @ x_cam0``), ``S_rect_00``
  its size. So the rectified camera's pose is ``T_world_velo @ T_velo_cam0 @ inv(R_rect_00)``.
- ``calib_cam_to_pose.txt``: ``image_0k:`` + 12 numbers, camera k -> the GPS/IMU "pose" frame
  (x forward, y right, z down). ``poses.txt``: per line a frame number and 12 numbers, the
  pose frame -> world (KITTI-360's map frame), only for the frames that have a pose. Then
  ``T_world_velo = pose @ T_pose_cam0 @ inv(T_velo_cam0)`` and the camera pose reduces to
  kitti360scripts' ``pose @ T_pose_cam0 @ inv(R_rect_00)``. Frames without a pose are left out
  (`unposed`).
- Without ``poses.txt`` (layout (b) always), poses are estimated from the sweeps, per log, once
  (`scube_sim.datasets.odometry`: our open3d ICP by default, kiss-icp with ``poses="kiss-icp"``;
  cached for every later command on the same files); world = the log's first Velodyne frame;
  ``metadata["poses"]`` starts with ``"estimated:"`` and ``poses_from_icp`` is True.
  ``experiments/kitti360_odometry.py`` measures the two estimators against each other.

Timestamps: line k of ``velodyne_points/timestamps.txt`` is taken as frame k's time (seconds
from line 0); where the file is missing or shorter than the frame numbers (the excerpt: 1 031
lines for frames 3000-3019, mapping undocumented), frame number x 0.1 s (10 Hz). The image and
the sweep share the sample's timestamp (image_00's own times differ by < 1 ms).

Sweeps are marked ``motion_compensated=True`` although KITTI-360 does not deskew them (its
scripts "curl" them with the poses): at ~10 m/s a return is off by up to ~0.5 m at the scan
seam behind the car, by nothing straight ahead, where the camera looks.

Not checked on a real copy of layout (a) (none is here): the folder names above, that line k of
timestamps.txt is frame k, and that poses.txt frame numbers match the file names; they follow
KITTI-360's documentation and scripts. The calibration texts and the .bin/.png files are the same
in both layouts and were checked on the excerpt (b).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera.frames import CameraImage, Frames
from ..errors import InputError
from ..lidar.config import load_lidar_config
from .base import DatasetError, LidarSpec, LidarSweep, Sample, index_check, require_file
from .kitti import camera_from_projection, read_image, read_velodyne
from .odometry import log_poses

LIDAR = "velodyne"
LIDAR_MODEL = "hdl64e"
CAMERA = "image_00"
# The Velodyne's height above the road: KITTI's documented 1.73 m on the same kind of rig (Geiger
# et al., IJRR 2013); the road plane fitted to the excerpt's sweeps agrees to a few centimetres
# (the road is cambered).
VELODYNE_HEIGHT_M = 1.73
FRAME_PERIOD_S = 0.1  # 10 Hz

POSE_MODES = ("auto", "file", "kiss-icp", "icp", "identity")


# --- calibration ---------------------------------------------------------------------------

def _numbers(text: str, path: Path, what: str) -> np.ndarray:
    try:
        values = np.array([float(v) for v in text.split()], np.float64)
    except ValueError:
        raise DatasetError(f"{path}: {what} has a value that is not a number") from None
    if not np.all(np.isfinite(values)):
        raise DatasetError(f"{path}: {what} holds NaN or Inf")
    return values


def _read_text(path: Path, what: str) -> str:
    require_file(path, what)
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not a readable {what} ({exc})") from None


def _keyed(path: Path, what: str) -> dict[str, str]:
    """A KITTI-360 ``key: v1 v2 ...`` text -> key -> the value text."""
    out = {}
    for line in _read_text(path, what).splitlines():
        key, sep, rest = line.partition(":")
        if sep:
            out[key.strip()] = rest
    return out


def _keyed_matrix(entries: dict, key: str, shape: tuple[int, int], path: Path) -> np.ndarray:
    if key not in entries:
        raise DatasetError(f"{path}: missing key {key!r} (expected {shape[0] * shape[1]} numbers)")
    v = _numbers(entries[key], path, f"key {key!r}")
    if v.size != shape[0] * shape[1]:
        raise DatasetError(f"{path}: key {key!r} has {v.size} numbers, expected {shape[0] * shape[1]}")
    return v.reshape(shape)


def _rigid(m34: np.ndarray, path: Path, what: str) -> np.ndarray:
    t = np.eye(4)
    t[:3] = m34
    r = t[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-4) or np.linalg.det(r) < 0:
        raise DatasetError(f"{path}: {what} is not a rigid transform (its 3x3 part is not a rotation)")
    return t


@dataclass
class Kitti360Calibration:
    """The calibration of camera 00 and the Velodyne. P_rect (3, 4), R_rect (3, 3);
    size: (width, height) of the rectified image or None; velo_cam0 (4, 4) T_velo_cam0
    (unrectified); pose_cam0 (4, 4) T_pose_cam0 or None (only needed with poses.txt)."""

    P_rect: np.ndarray
    R_rect: np.ndarray
    size: tuple[int, int] | None
    velo_cam0: np.ndarray
    pose_cam0: np.ndarray | None
    folder: Path

    @property
    def velo_rect(self) -> np.ndarray:
        """(4, 4) T_velo_rect: the rectified camera-00 frame in the Velodyne frame."""
        r = np.eye(4)
        r[:3, :3] = self.R_rect
        return self.velo_cam0 @ r.T  # inv(R_rect) of a rotation

    @property
    def pose_velo(self) -> np.ndarray:
        """(4, 4) T_pose_velo: the Velodyne in the GPS/IMU pose frame."""
        if self.pose_cam0 is None:
            raise DatasetError(f"{self.folder / 'calib_cam_to_pose.txt'}: missing calibration file "
                               f"(needed to use poses.txt)")
        return self.pose_cam0 @ np.linalg.inv(self.velo_cam0)


def read_calibration(folder: str | Path, *, need_pose: bool = False) -> Kitti360Calibration:
    """Read ``perspective.txt`` (P_rect_00, R_rect_00, S_rect_00), ``calib_cam_to_velo.txt``
    and ``calib_cam_to_pose.txt`` (image_00; required only if `need_pose`) from `folder`.
    Errors are DatasetError naming the file (and key)."""
    folder = Path(folder)
    persp = folder / "perspective.txt"
    entries = _keyed(persp, "KITTI-360 calibration file (P_rect_00, R_rect_00)")
    p_rect = _keyed_matrix(entries, "P_rect_00", (3, 4), persp)
    r_rect = _keyed_matrix(entries, "R_rect_00", (3, 3), persp)
    if not np.allclose(r_rect @ r_rect.T, np.eye(3), atol=1e-4):
        raise DatasetError(f"{persp}: R_rect_00 is not a rotation")
    size = None
    if "S_rect_00" in entries:
        s = _keyed_matrix(entries, "S_rect_00", (1, 2), persp)[0]
        size = (round(s[0]), round(s[1]))
    velo_path = folder / "calib_cam_to_velo.txt"
    v = _numbers(_read_text(velo_path, "KITTI-360 calibration file (camera 00 -> Velodyne, 12 numbers)"),
                 velo_path, "the transform")
    if v.size != 12:
        raise DatasetError(f"{velo_path}: {v.size} numbers, expected 12 (a 3x4 camera 00 -> Velodyne transform)")
    velo_cam0 = _rigid(v.reshape(3, 4), velo_path, "camera 00 -> Velodyne")
    pose_path = folder / "calib_cam_to_pose.txt"
    pose_cam0 = None
    if need_pose or pose_path.is_file():
        what = "KITTI-360 calibration file (cameras -> GPS/IMU pose frame)"
        entries = _keyed(pose_path, what)
        pose_cam0 = _rigid(_keyed_matrix(entries, CAMERA, (3, 4), pose_path), pose_path, "image_00 -> pose")
    return Kitti360Calibration(p_rect, r_rect, size, velo_cam0, pose_cam0, folder)


# --- poses and timestamps --------------------------------------------------------------------

def read_poses(path: str | Path) -> dict[int, np.ndarray]:
    """KITTI-360 ``poses.txt``: lines ``frame r00 r01 r02 t0 r10 ... t2`` -> frame -> (4, 4)
    pose-frame-to-world."""
    path = Path(path)
    out: dict[int, np.ndarray] = {}
    for lineno, line in enumerate(_read_text(path, "KITTI-360 poses file").splitlines(), 1):
        if not line.strip():
            continue
        v = _numbers(line, path, f"line {lineno}")
        if v.size != 13 or v[0] != int(v[0]) or v[0] < 0:
            raise DatasetError(f"{path}: line {lineno}: expected a frame number and 12 numbers (a 3x4 pose), "
                               f"got {v.size} values")
        frame = int(v[0])
        if frame in out:
            raise DatasetError(f"{path}: line {lineno}: frame {frame} appears twice")
        out[frame] = _rigid(v[1:].reshape(3, 4), path, f"line {lineno} (frame {frame})")
    if not out:
        raise DatasetError(f"{path}: no poses (expected lines of a frame number and 12 numbers)")
    return out


def read_timestamps(path: Path) -> np.ndarray | None:
    """``timestamps.txt`` (``YYYY-MM-DD hh:mm:ss.nnnnnnnnn`` per line) -> seconds from line 0;
    None if the file is absent."""
    if not path.is_file():
        return None
    lines = [ln.strip() for ln in _read_text(path, "timestamps file").splitlines() if ln.strip()]
    try:
        ns = np.array([np.datetime64(ln.replace(" ", "T"), "ns") for ln in lines], "datetime64[ns]")
    except ValueError:
        raise DatasetError(f"{path}: expected one 'YYYY-MM-DD hh:mm:ss.fffffffff' time per line") from None
    if ns.size == 0:
        return None
    return (ns - ns[0]).astype(np.int64) * 1e-9


# --- files -----------------------------------------------------------------------------------

@dataclass
class _Log:
    """One drive: its frames (number, image, sweep), where its poses and times come from."""

    name: str
    frames: list[tuple[int, Path, Path]]
    poses_file: Path | None
    times: np.ndarray | None  # seconds by frame number (None: 10 Hz)
    unmatched: list[str]


# --- the adapter -------------------------------------------------------------------------------

class Kitti360Dataset:
    """KITTI-360 drives (layout (a)) or the 20-frame excerpt's folders (layout (b)); see the module.

    root: the folder to open; drive: one drive (layout (a)) or the log name (layout (b));
    poses: "auto" (poses.txt where the drive has one, else estimated by our ICP), "file"
    (poses.txt required), "icp" or "kiss-icp" (always estimate, by our open3d ICP or kiss-icp:
    `datasets.odometry`) or "identity" (every sample at the origin);
    start, count: the frames of each drive to use (sorted by number), e.g. count=3.
    """

    name = "kitti360"

    def __init__(self, root: str | Path, drive: str | None = None, poses: str = "auto", start: int = 0,
                 count: int | None = None):
        self.root = Path(root)
        if poses not in POSE_MODES:
            raise InputError(f"kitti360: poses must be one of {', '.join(POSE_MODES)}, got {poses!r}")
        if start < 0 or (count is not None and count < 1):
            raise InputError(f"kitti360: start must be >= 0 and count >= 1, got start={start}, count={count}")
        self.poses_mode = poses
        self.layout, calib_dir, logs = self._find_logs(drive, start, count)
        if poses == "file":
            if self.layout == "excerpt":
                raise DatasetError(f"{self.root}: the excerpt layout (data/...) has no poses file; use poses='auto' "
                                   f"(estimated by ICP) or 'identity'")
            for log in logs:
                if log.poses_file is None:
                    raise DatasetError(f"{self._poses_path(log.name)}: missing KITTI-360 poses file (poses='file')")
        use_file = poses in ("auto", "file") and any(log.poses_file is not None for log in logs)
        self.calibration = read_calibration(calib_dir, need_pose=use_file)
        file_poses = {}
        self.file_poses: dict[str, np.ndarray] = {}  # per log: the poses.txt poses (GPS/IMU -> world) as read
        self.unposed: list[tuple[str, int]] = []  # frames left out: no line in poses.txt
        for log in logs:
            if poses in ("auto", "file") and log.poses_file is not None:
                table = read_poses(log.poses_file)
                self.unposed += [(log.name, n) for n, _, _ in log.frames if n not in table]
                log.frames = [f for f in log.frames if f[0] in table]
                if not log.frames:
                    raise DatasetError(f"{log.poses_file}: none of drive {log.name}'s frames has a pose")
                self.file_poses[log.name] = np.stack([table[n] for n, _, _ in log.frames])
                file_poses[log.name] = self.file_poses[log.name] @ self.calibration.pose_velo
        self._logs = logs
        self._index = [(k, j) for k, log in enumerate(logs) for j in range(len(log.frames))]
        self._poses: dict[str, np.ndarray] = file_poses  # Velodyne-to-world per log (filled on use)
        self._icp: dict[str, list] = {}
        self.poses_from_icp = poses in ("kiss-icp", "icp") or (poses == "auto" and any(log.poses_file is None
                                                                                      for log in logs))
        self.odometry = "kiss-icp" if poses == "kiss-icp" else "icp"  # where poses are estimated
        self.unmatched = [u for log in logs for u in log.unmatched]
        self._lidar_config = None

    # -- discovery ------------------------------------------------------------------------------

    def _poses_path(self, drive: str) -> Path:
        return self.root / "data_poses" / drive / "poses.txt"

    def _find_logs(self, drive, start, count):
        r = self.root
        if (r / "data_2d_raw").is_dir() or (r / "data_3d_raw").is_dir():
            img_root, velo_root = r / "data_2d_raw", r / "data_3d_raw"
            for d in (img_root, velo_root, r / "calibration"):
                if not d.is_dir():
                    raise DatasetError(f"{d}: missing folder (expected KITTI-360's data_2d_raw/, data_3d_raw/ "
                                       f"and calibration/)")
            names = sorted(p.name for p in velo_root.iterdir() if (p / "velodyne_points" / "data").is_dir())
            names = [n for n in names if (img_root / n / CAMERA / "data_rect").is_dir()]
            if drive is not None:
                if drive not in names:
                    raise DatasetError(f"{r}: no drive {drive!r} with data_2d_raw/{drive}/image_00/data_rect and "
                                       f"data_3d_raw/{drive}/velodyne_points/data (have: {', '.join(names) or 'none'})")
                names = [drive]
            if not names:
                raise DatasetError(f"{r}: no drive has both data_2d_raw/<drive>/image_00/data_rect and "
                                   f"data_3d_raw/<drive>/velodyne_points/data")
            logs = []
            for n in names:
                pf = self._poses_path(n)
                logs.append(self._log(n, img_root / n / CAMERA / "data_rect", velo_root / n / "velodyne_points" / "data",
                                      velo_root / n / "velodyne_points" / "timestamps.txt",
                                      pf if pf.is_file() else None, start, count))
            return "kitti360", r / "calibration", logs
        data = r / "data" if (r / "data" / CAMERA / "good_data").is_dir() else r
        img_dir, velo_dir = data / CAMERA / "good_data", data / "velodyne_points" / "good_data"
        if not img_dir.is_dir() or not velo_dir.is_dir():
            raise DatasetError(f"{r}: not a KITTI-360 folder: expected data_2d_raw/ + data_3d_raw/ + calibration/ "
                               f"(KITTI-360's layout) or data/image_00/good_data + data/velodyne_points/good_data + "
                               f"data/calibration/ (the sequence excerpt's)")
        name = drive if drive is not None else (data.parent.name if data.name == "data" else data.name)
        log = self._log(name, img_dir, velo_dir, data / "velodyne_points" / "timestamps.txt", None, start, count)
        return "excerpt", data / "calibration", [log]

    @staticmethod
    def _log(name, img_dir, velo_dir, times_path, poses_file, start, count) -> _Log:
        images = {p.stem: p for p in img_dir.glob("*.png")}
        sweeps = {p.stem: p for p in velo_dir.glob("*.bin")}
        stems = sorted(s for s in set(images) & set(sweeps) if s.isdigit())
        if not stems:
            raise DatasetError(f"{velo_dir}: no frame has both {img_dir.name}/NNNNNNNNNN.png and "
                               f"{velo_dir.name}/NNNNNNNNNN.bin ({img_dir})")
        stems = stems[start:] if count is None else stems[start:start + count]
        if not stems:
            raise DatasetError(f"{velo_dir}: start={start} is past the drive's frames")
        frames = [(int(s), images[s], sweeps[s]) for s in stems]
        times = read_timestamps(times_path)
        if times is not None and max(n for n, _, _ in frames) >= times.size:
            times = None  # the file does not reach these frame numbers: 10 Hz
        return _Log(name, frames, poses_file, times, sorted(set(images) ^ set(sweeps)))

    # -- poses ------------------------------------------------------------------------------------

    def _log_poses(self, k: int) -> np.ndarray:
        log = self._logs[k]
        if log.name not in self._poses:
            if self.poses_mode == "identity":
                poses, res = np.broadcast_to(np.eye(4), (len(log.frames), 4, 4)).copy(), []
            else:
                try:
                    est = log_poses([v for _, _, v in log.frames], lambda p: read_velodyne(p)[:, :3], self.odometry)
                except InputError as exc:
                    raise DatasetError(f"{log.frames[0][2].parent}: {self.odometry} registration of the sweeps "
                                       f"failed ({exc})") from None
                poses, res = est.poses, est.steps
            self._poses[log.name], self._icp[log.name] = poses, res
        return self._poses[log.name]

    @property
    def poses(self) -> np.ndarray:
        """(K, 4, 4) Velodyne-to-world (ego) poses of all samples (ICP runs on first use)."""
        return np.concatenate([self._log_poses(k) for k in range(len(self._logs))])

    def pose_source(self, k: int) -> str:
        log = self._logs[k]
        if log.poses_file is not None and self.poses_mode in ("auto", "file"):
            return f"file: {log.poses_file} (GPS/IMU pose @ calib_cam_to_pose @ inv(calib_cam_to_velo))"
        if self.poses_mode == "identity":
            return "identity: none (every sample at the origin)"
        how = ("kiss-icp (no deskew)" if self.odometry == "kiss-icp"
               else "open3d point-to-plane ICP of consecutive Velodyne sweeps")
        return f"estimated: {how} (scube_sim.datasets.odometry); world = the drive's first Velodyne frame"

    def icp_results(self, log: str | None = None) -> list:
        """The `IcpResult`s of a log's samples 1..K-1 ([] where poses are not estimated)."""
        k = 0 if log is None else [lg.name for lg in self._logs].index(log)
        self._log_poses(k)
        return self._icp.get(self._logs[k].name, [])

    @property
    def logs(self) -> list[str]:
        return [log.name for log in self._logs]

    # -- samples ----------------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._index)

    def __iter__(self) -> Iterator[Sample]:
        for i in range(len(self)):
            yield self[i]

    def __getitem__(self, index: int) -> Sample:
        k, j = self._index[index_check(index, len(self), f"{self.name} {self.root}")]
        log = self._logs[k]
        number, img_path, velo_path = log.frames[j]
        pose = self._log_poses(k)[j]
        if log.times is not None:
            t, t_note = float(log.times[number]), "velodyne_points/timestamps.txt line = frame number"
        else:
            t, t_note = number * FRAME_PERIOD_S, "frame number x 0.1 s (10 Hz): timestamps not mappable to frames"
        stem = velo_path.stem
        pts = read_velodyne(velo_path)
        rgb = read_image(img_path)
        cal = self.calibration
        persp = str(cal.folder / "perspective.txt")
        if cal.size is not None and cal.size != (rgb.shape[1], rgb.shape[0]):
            raise DatasetError(f"{img_path}: image is {rgb.shape[1]}x{rgb.shape[0]}, expected {cal.size[0]}x"
                               f"{cal.size[1]} (S_rect_00 of {persp})")
        intr, rect_to_cam = camera_from_projection(cal.P_rect, rgb.shape[1], rgb.shape[0], persp, "P_rect_00")
        sweep = LidarSweep(LIDAR, pts[:, :3], pose, t, intensity=pts[:, 3].copy(), intensity_max=1.0,
                           motion_compensated=True, source=str(velo_path))
        if self._lidar_config is None:
            self._lidar_config = load_lidar_config(LIDAR_MODEL)
        frames = Frames([CameraImage(CAMERA, rgb, intr, pose @ cal.velo_rect @ rect_to_cam, t)], pose, t,
                        {"dataset": self.name, "frame": stem, "root": str(self.root),
                         "ego_height_m": VELODYNE_HEIGHT_M})
        meta = {"dataset": self.name, "layout": self.layout, "drive": log.name, "frame": stem,
                "calibration": str(cal.folder), "poses": self.pose_source(k), "timestamps": t_note}
        res = self._icp.get(log.name)
        if res:  # ICP of this sweep (none for the first: it defines the world)
            meta["icp_fitness"] = res[j - 1].fitness if j > 0 else None
            meta["icp_rmse"] = res[j - 1].rmse if j > 0 else None
        return Sample(name=stem, timestamp=t, ego_pose=pose, frames=frames, sweeps=[sweep],
                      lidars={LIDAR: LidarSpec(LIDAR, self._lidar_config, np.eye(4))}, metadata=meta, log=log.name)


__all__ = ["VELODYNE_HEIGHT_M", "Kitti360Calibration", "Kitti360Dataset", "read_calibration", "read_poses",
           "read_timestamps"]
