"""Argoverse 2 Sensor Dataset logs: LiDAR sweeps of the two stacked VLP-32C, 200 Hz ego poses,
camera calibration.

    ds = Argoverse2Dataset("path/to/<log_id>")      # or open_dataset("argoverse2", ...)
    sample = ds[0]                                   # sweeps "up_lidar" and "down_lidar"

Layout of a log folder (all tables are Apache Feather, read with pyarrow):

    sensors/lidar/<t_ns>.feather                 x y z (float16, m, ego frame), intensity (uint8),
                                                 laser_number (uint8, 0-63), offset_ns (int32)
    city_SE3_egovehicle.feather                  timestamp_ns, qw qx qy qz, tx_m ty_m tz_m (ego -> city)
    calibration/egovehicle_SE3_sensor.feather    sensor_name, qw qx qy qz, tx_m ty_m tz_m (sensor -> ego)
    calibration/intrinsics.feather               sensor_name, fx_px fy_px cx_px cy_px, k1 k2 k3, height_px width_px

Frames:

- world = the city frame (metres); ego = the vehicle frame, x forward, y left, z up.
- One `Sample` per sweep file, in time order; ``Sample.timestamp`` = the file name (ns) in
  seconds; ``Sample.ego_pose`` = ``city_SE3_egovehicle`` at that time (the stream holds the
  sweep times exactly; otherwise it is interpolated).
- Each feather holds both LiDARs. ``laser_number`` 0-31 is ``up_lidar``, 32-63 ``down_lidar``.
  av2-api's ``Sweep`` keeps the 64 numbers together and does not document the split; the data do: in
  its own sensor frame every laser's points lie on one cone at the VLP-32C table's elevation,
  while in the other sensor's frame they smear. av2 users split the same way (av2-api
  issue #82, following #77: "laser number [0, 31] -> top lidar, [32, 63] -> bottom lidar").
- AV2 numbers the 32 lasers of each sensor in its own order, not Velodyne's. ``LidarSweep.ring``
  is the channel index of our VLP-32C preset (Velodyne's laser id, the order of
  ``LidarSpec.config``'s elevation table), through `AV2_LASER_TO_VLP32C_CHANNEL`, found by
  matching each laser's measured elevation to the table (same map for both sensors and sweeps).

Motion compensation: AV2 sweep points are ego-motion compensated, every point expressed in the
ego frame at the sweep timestamp. av2-api says so in ``src/av2/structures/sweep.py`` (class
``Sweep``: "We have egomotion-compensated the lidar sensor data to the egovehicle reference
timestamp (`timestamp_ns`)"), and its Rust loader (``rust/src/io.rs``, ``read_accumulate_lidar``)
moves whole sweeps with the single pose at each sweep timestamp. The data agree: two sweeps'
static points align best when each sweep uses the pose at its timestamp, not when each point
uses the pose at its own time. So ``motion_compensated`` is True; ``pose_fn`` is still given
(sensor-to-world from the 200 Hz pose stream) for per-point timing.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from ..camera.model import Intrinsics
from ..lidar.config import LidarConfig, load_lidar_config
from ..transforms import interpolate_poses, invert_pose, quat_to_rotmat, rotmat_to_euler, transform_points
from .base import DatasetError, LidarSpec, LidarSweep, Sample, index_check, require_file

LIDARS = ("up_lidar", "down_lidar")
LASERS_PER_SENSOR = 32  # laser_number // 32: 0 -> up_lidar, 1 -> down_lidar
INTENSITY_MAX = 255.0  # uint8 intensity

# AV2 laser index within a sensor (laser_number % 32) -> channel of the VLP-32C preset
# (sensors/lidar/vlp32c.yaml, Velodyne's laser id order). Measured on log 7fab2350: the median
# elevation of each AV2 laser, in its sensor frame, is within 0.04 degrees of that channel's.
AV2_LASER_TO_VLP32C_CHANNEL = np.array(
    [25, 2, 17, 6, 29, 10, 21, 14, 13, 5, 18, 22, 9, 1, 26, 30,
     11, 3, 24, 28, 15, 7, 16, 20, 23, 12, 31, 8, 19, 4, 27, 0], np.int16)

# AV2's K is OpenCV's (pixel centres at integers: av2's PinholeCamera.cull_to_view_frustum
# accepts u in [0, width - 1]); `Intrinsics.from_k` moves it to ours.

_POSE_COLUMNS = ("qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
_SWEEP_COLUMNS = ("x", "y", "z", "intensity", "laser_number", "offset_ns")


def read_feather_columns(path: Path, columns, what: str) -> dict[str, np.ndarray]:
    """The named columns of a Feather table as numpy arrays (dtypes as stored). DatasetError
    naming the file when it is missing or unreadable, and the column when one is absent or has
    nulls."""
    import pyarrow as pa
    import pyarrow.feather as feather

    path = require_file(Path(path), what)
    try:
        table = feather.read_table(path, memory_map=False)
    except (pa.ArrowInvalid, OSError) as exc:
        raise DatasetError(f"{path}: not a readable Feather file ({what}): {exc}") from None
    out = {}
    for col in columns:
        if col not in table.column_names:
            raise DatasetError(f"{path}: missing column {col!r} ({what}); have {', '.join(table.column_names)}")
        if table[col].null_count:
            raise DatasetError(f"{path}: column {col!r} has {table[col].null_count} null values")
        out[col] = table[col].to_numpy()
    return out


def read_lidar_feather(path: Path) -> dict[str, np.ndarray]:
    """One AV2 sweep file as stored: x, y, z (N,) float16 metres in the ego frame at the sweep
    timestamp; intensity (N,) uint8; laser_number (N,) uint8 0-63; offset_ns (N,) int32."""
    cols = read_feather_columns(path, _SWEEP_COLUMNS, "LiDAR sweep")
    bad = cols["laser_number"] >= 2 * LASERS_PER_SENSOR
    if np.any(bad):
        raise DatasetError(f"{path}: column 'laser_number' holds {int(cols['laser_number'][bad][0])}, expected 0-63")
    return cols


def _poses(cols: dict[str, np.ndarray]) -> np.ndarray:
    """(K, 4, 4) float64 poses from qw qx qy qz (wxyz) and tx_m ty_m tz_m columns."""
    q = np.stack([cols[c] for c in ("qw", "qx", "qy", "qz")], axis=1).astype(np.float64)
    t = np.zeros((q.shape[0], 4, 4))
    t[:, :3, :3] = quat_to_rotmat(q)
    t[:, :3, 3] = np.stack([cols[c] for c in ("tx_m", "ty_m", "tz_m")], axis=1)
    t[:, 3, 3] = 1.0
    return t


def _mounted(base: LidarConfig, name: str, sensor_to_ego: np.ndarray) -> LidarConfig:
    """The preset with the calibrated mount, and compensated output like the AV2 sweeps."""
    roll, pitch, yaw = rotmat_to_euler(sensor_to_ego[:3, :3])
    data = base.model_dump()
    data["mount"] = {"xyz": [float(v) for v in sensor_to_ego[:3, 3]],
                     "rpy_deg": [float(np.degrees(a)) for a in (roll, pitch, yaw)]}
    data["motion"] = {"output": "compensated", "reference": "start"}
    data["notes"] = (f"{base.notes} Argoverse 2 {name}: mount from calibration/egovehicle_SE3_sensor.feather; "
                     f"output compensated to the sweep start, as AV2 distributes its sweeps.").strip()
    return LidarConfig.model_validate(data)


class Argoverse2Dataset:
    """One Argoverse 2 sensor log (see the module docstring for files and frames).

    Each sample has two sweeps, ``up_lidar`` and ``down_lidar``: points (N, 3) float64 in that
    sensor's frame (compensated, at the sweep timestamp); intensity float32 0-255
    (``intensity_max`` 255); ring int16 VLP-32C channel; time_offset float64 s after the sweep
    timestamp (offset_ns * 1e-9). ``frames`` is None (the images are not part of the sensor
    log folder as read here); camera calibration is in `cameras()`. ``boxes`` is empty.
    """

    name = "argoverse2"
    poses_from_icp = False

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: not a folder (expected an Argoverse 2 log folder)")
        lidar_dir = self.root / "sensors" / "lidar"
        files = sorted(lidar_dir.glob("*.feather")) if lidar_dir.is_dir() else []
        if not files:
            raise DatasetError(f"{lidar_dir}: no sweep files <t_ns>.feather")
        stamps = []
        for f in files:
            if not f.stem.isdigit():
                raise DatasetError(f"{f}: sweep file name must be its timestamp in ns (<t_ns>.feather)")
            stamps.append(int(f.stem))
        order = np.argsort(stamps, kind="stable")
        self.sweep_files = [files[i] for i in order]
        self.sweep_times_ns = np.asarray(stamps, np.int64)[order]
        self._load_poses()
        self._load_calibration()

    # --- tables -------------------------------------------------------------------------------
    def _load_poses(self) -> None:
        self.pose_file = self.root / "city_SE3_egovehicle.feather"
        cols = read_feather_columns(self.pose_file, ("timestamp_ns",) + _POSE_COLUMNS, "ego poses")
        t_ns = cols["timestamp_ns"].astype(np.int64)
        if t_ns.size < 2:
            raise DatasetError(f"{self.pose_file}: {t_ns.size} pose rows, need at least 2 to interpolate")
        # Sort, and keep the first of rows with equal timestamps (AV2 logs hold a few duplicates).
        order = np.argsort(t_ns, kind="stable")
        t_ns = t_ns[order]
        keep = np.concatenate([[True], np.diff(t_ns) > 0])
        self.pose_times_ns = t_ns[keep]
        self._pose_times_s = self.pose_times_ns * 1e-9
        self._pose_mats = _poses({k: v[order][keep] for k, v in cols.items()})

    def _load_calibration(self) -> None:
        self.extrinsics_file = self.root / "calibration" / "egovehicle_SE3_sensor.feather"
        cols = read_feather_columns(self.extrinsics_file, ("sensor_name",) + _POSE_COLUMNS, "sensor extrinsics")
        mats = _poses(cols)
        self.sensor_to_ego = {str(n): mats[i] for i, n in enumerate(cols["sensor_name"])}
        for name in LIDARS:
            if name not in self.sensor_to_ego:
                raise DatasetError(f"{self.extrinsics_file}: no row with sensor_name {name!r}; "
                                   f"have {', '.join(self.sensor_to_ego)}")
        base = load_lidar_config("VLP-32C")
        self.lidars = {n: LidarSpec(n, _mounted(base, n, self.sensor_to_ego[n]), self.sensor_to_ego[n])
                       for n in LIDARS}
        self.intrinsics_file = self.root / "calibration" / "intrinsics.feather"

    def cameras(self) -> dict[str, tuple[Intrinsics, np.ndarray]]:
        """Camera name -> (Intrinsics, cam_to_ego (4, 4) float64).

        AV2 camera frames are OpenCV's (x right, y down, z forward: av2-api's
        ``PinholeCamera.project_ego_to_img`` applies ``K`` directly to ``inv(ego_SE3_cam)`` times
        the point, and ``compute_pixel_ray_directions`` says "+z points out of the camera, +y is
        downwards"), so ``egovehicle_SE3_sensor`` is already our cam_to_ego. Distortion: AV2's
        radial k1, k2, k3 as OpenCV ``[k1, k2, 0, 0, k3]``; cx, cy moved by half a pixel (see
        `Intrinsics.from_k`)."""
        cols = read_feather_columns(self.intrinsics_file, ("sensor_name", "fx_px", "fy_px", "cx_px", "cy_px",
                                                           "k1", "k2", "k3", "height_px", "width_px"),
                                    "camera intrinsics")
        out = {}
        for i, name in enumerate(cols["sensor_name"]):
            name = str(name)
            if name not in self.sensor_to_ego:
                raise DatasetError(f"{self.extrinsics_file}: no row with sensor_name {name!r} "
                                   f"(named in {self.intrinsics_file})")
            try:
                k = np.array([[cols["fx_px"][i], 0, cols["cx_px"][i]], [0, cols["fy_px"][i], cols["cy_px"][i]],
                              [0, 0, 1]], np.float64)
                intr = Intrinsics.from_k(k, int(cols["width_px"][i]), int(cols["height_px"][i]), "opencv",
                                         (cols["k1"][i], cols["k2"][i], 0.0, 0.0, cols["k3"][i]))
            except ValueError as exc:
                raise DatasetError(f"{self.intrinsics_file}: camera {name!r}: {exc}") from None
            out[name] = (intr, self.sensor_to_ego[name].copy())
        return out

    # --- poses --------------------------------------------------------------------------------
    @property
    def pose_span(self) -> tuple[float, float]:
        """(first, last) time of the pose stream, seconds."""
        return float(self._pose_times_s[0]), float(self._pose_times_s[-1])

    def ego_poses(self, times) -> np.ndarray:
        """Absolute times (K,) s -> (K, 4, 4) float64 ego-to-city poses, interpolated in the pose
        stream (SLERP rotation, linear translation). DatasetError for a time outside the stream."""
        t = np.atleast_1d(np.asarray(times, np.float64))
        lo, hi = self.pose_span
        outside = ~((t >= lo) & (t <= hi))  # also catches NaN
        if np.any(outside):
            bad = float(t[outside][0])
            raise DatasetError(f"{self.pose_file}: no ego pose at t={bad!r} s; the pose stream covers "
                               f"[{lo!r}, {hi!r}] s")
        ts = self._pose_times_s
        seg = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, ts.size - 2)
        out = np.empty((t.size, 4, 4))
        for k in np.unique(seg):  # a sweep spans ~20 segments of the 200 Hz stream
            m = seg == k
            s = (t[m] - ts[k]) / (ts[k + 1] - ts[k])
            out[m] = interpolate_poses(self._pose_mats[k], self._pose_mats[k + 1], s)
        return out

    def ego_pose_ns(self, t_ns: int) -> np.ndarray:
        """(4, 4) ego-to-city at an integer ns time: the stream's row when it has this exact time
        (the AV2 sweep times), else interpolated."""
        i = int(np.searchsorted(self.pose_times_ns, t_ns))
        if i < self.pose_times_ns.size and self.pose_times_ns[i] == t_ns:
            return self._pose_mats[i].copy()
        return self.ego_poses([t_ns * 1e-9])[0]

    def sensor_pose_fn(self, sensor: str):
        """Absolute times (K,) s -> (K, 4, 4) sensor-to-city poses of `sensor`."""
        mount = self.sensor_to_ego[sensor]
        return lambda times: self.ego_poses(times) @ mount

    # --- samples ------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.sweep_files)

    def __iter__(self) -> Iterator[Sample]:
        for i in range(len(self)):
            yield self[i]

    def __getitem__(self, index: int) -> Sample:
        i = index_check(index, len(self), f"{self.name} {self.root}")
        path = self.sweep_files[i]
        t_ns = int(self.sweep_times_ns[i])
        timestamp = t_ns * 1e-9
        ego_pose = self.ego_pose_ns(t_ns)
        cols = read_lidar_feather(path)
        xyz_ego = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float64)  # float16 is exact in float64
        sensor_index = cols["laser_number"] // LASERS_PER_SENSOR
        sweeps = []
        for k, name in enumerate(LIDARS):
            m = sensor_index == k
            mount = self.sensor_to_ego[name]
            sweeps.append(LidarSweep(
                sensor=name,
                points=transform_points(invert_pose(mount), xyz_ego[m]),
                sensor_to_world=ego_pose @ mount,
                timestamp=timestamp,
                intensity=cols["intensity"][m].astype(np.float32),
                intensity_max=INTENSITY_MAX,
                ring=AV2_LASER_TO_VLP32C_CHANNEL[cols["laser_number"][m] % LASERS_PER_SENSOR],
                time_offset=cols["offset_ns"][m].astype(np.float64) * 1e-9,
                motion_compensated=True,
                pose_fn=self.sensor_pose_fn(name),
            ))
        return Sample(name=path.stem, timestamp=timestamp, ego_pose=ego_pose, frames=None, sweeps=sweeps,
                      lidars=dict(self.lidars), boxes=[], log=self.root.name,
                      metadata={"dataset": self.name, "log_id": self.root.name, "sweep_file": str(path),
                                "timestamp_ns": t_ns})
