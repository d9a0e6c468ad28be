"""Poses for logs that have none, estimated once per log from its LiDAR sweeps and cached.

Two estimators behind one interface (`Odometry.estimate(sweeps) -> LogPoses`):

- `Icp`, the default: our open3d point-to-plane ICP (`datasets.icp.register_sequence`), coarse to
  fine from a constant-velocity guess; the more accurate on short and slow logs, where kiss-icp's
  map of a few sweeps under-estimates the first steps (experiments/kitti360_odometry.py).
- `KissIcp`: kiss-icp (PyPI, MIT), its KITTI settings without deskewing (the sweeps the adapters
  read are one instant each), on one thread so the poses are the same bytes on every machine; tens
  of times faster, for long logs.

`log_poses` caches each log's result under the user's cache folder (SCUBE_SIM_CACHE, else
$XDG_CACHE_HOME/scube-sim, else ~/.cache/scube-sim), keyed by the estimator, its settings and each
sweep file's path, size and modification time: every later command on the same log (`convert`,
`fidelity`, `build`, a batch task) reads the poses instead of estimating them again. The cache
is written under a temporary name and renamed, read without pickles, and a damaged entry is
estimated again.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from ..atomic import atomic_path
from ..errors import InputError
from .icp import IcpResult, register_sequence, step_quality

CACHE_ENV = "SCUBE_SIM_CACHE"
CACHE_VERSION = 1


@dataclass
class LogPoses:
    """A log's estimated poses: poses (K, 4, 4) sensor-to-world, world = the first sweep's sensor
    frame; steps: K - 1 `IcpResult`s (the relative pose of sweep k onto k - 1, with the inlier
    share and residual in metres of the registration that placed sweep k); method: the
    estimator's name."""

    poses: np.ndarray
    steps: list[IcpResult]
    method: str


class Odometry(Protocol):
    name: str

    def settings(self) -> dict:
        """What, besides the sweeps, decides the poses (part of the cache key)."""
        ...

    def estimate(self, sweeps: list[np.ndarray]) -> LogPoses:
        """(N_k, 3) float64 points per sweep, metres, sensor frame, in time order -> `LogPoses`."""
        ...


class KissIcp:
    """kiss-icp with its KITTI defaults (max range 100 m, voxel = max range / 100), no deskew, one thread."""

    name = "kiss-icp"

    def __init__(self, max_range_m: float = 100.0, min_range_m: float = 0.0):
        self.max_range_m, self.min_range_m = float(max_range_m), float(min_range_m)

    def settings(self) -> dict:
        from importlib.metadata import PackageNotFoundError, version

        try:
            release = version("kiss-icp")
        except PackageNotFoundError:
            release = "not installed"
        return {"max_range_m": self.max_range_m, "min_range_m": self.min_range_m, "deskew": False, "threads": 1,
                "version": release}

    def estimate(self, sweeps: list[np.ndarray]) -> LogPoses:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP

        cfg = KISSConfig()
        cfg.data.deskew = False
        cfg.data.max_range, cfg.data.min_range = self.max_range_m, self.min_range_m
        cfg.mapping.voxel_size = cfg.data.max_range / 100.0  # what kiss-icp's config loader sets
        cfg.registration.max_num_threads = 1  # its parallel sums would make the last bits vary
        odo = KissICP(cfg)
        poses = []
        for k, pts in enumerate(sweeps):
            pts = np.ascontiguousarray(pts, np.float64)
            if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 100:
                raise InputError(f"kiss-icp: sweep {k} has {pts.shape[0] if pts.ndim == 2 else 0} points; "
                                 f"at least 100 are needed to register it")
            odo.register_frame(pts, np.zeros(0))
            # rounded far below the method's accuracy: the same sweeps, the same poses, bit for bit
            poses.append(np.round(np.asarray(odo.last_pose, np.float64), 10))
        poses = np.stack(poses) if poses else np.zeros((0, 4, 4))
        if len(poses):
            poses = np.round(np.linalg.inv(poses[0]) @ poses, 10)  # world = the first sweep's frame
        return LogPoses(poses, step_quality(sweeps, poses), self.name)


class Icp:
    """Our open3d point-to-plane ICP, frame to frame, the first `refine_to_first` sweeps refined onto the first."""

    name = "icp"

    def __init__(self, refine_to_first: int = 10):
        self.refine_to_first = int(refine_to_first)

    def settings(self) -> dict:
        return {"refine_to_first": self.refine_to_first}

    def estimate(self, sweeps: list[np.ndarray]) -> LogPoses:
        poses, fits = register_sequence(sweeps, refine_to_first=self.refine_to_first)
        # each step as sweep k onto k - 1, with the quality of the registration that placed sweep k
        steps = [IcpResult(np.round(np.linalg.inv(poses[k - 1]) @ poses[k], 10), f.fitness, f.rmse)
                 for k, f in enumerate(fits, 1)]
        return LogPoses(poses, steps, self.name)


ODOMETRY: dict[str, type] = {"icp": Icp, "kiss-icp": KissIcp}
DEFAULT_ODOMETRY = "icp"


def odometry(name: str) -> Odometry:
    """An estimator by name (ODOMETRY)."""
    if name not in ODOMETRY:
        raise InputError(f"odometry: expected one of {', '.join(ODOMETRY)}, got {name!r}")
    return ODOMETRY[name]()


def cache_dir() -> Path:
    """Where estimated poses are kept: SCUBE_SIM_CACHE, else $XDG_CACHE_HOME/scube-sim, else ~/.cache/scube-sim."""
    env = os.environ.get(CACHE_ENV, "").strip()
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
    return (Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "scube-sim"


def _key(files: list[Path], method: Odometry) -> str:
    h = hashlib.sha256(json.dumps({"version": CACHE_VERSION, "method": method.name,
                                   "settings": method.settings()}, sort_keys=True).encode())
    for f in files:
        st = f.stat()
        h.update(f"{f.resolve()}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def _read_cache(path: Path, count: int, method: str) -> LogPoses | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            poses, rel, fit, rmse = z["poses"], z["steps"], z["fitness"], z["rmse"]
            name = str(z["method"])
    except (OSError, ValueError, KeyError):
        return None
    if poses.shape != (count, 4, 4) or rel.shape != (max(count - 1, 0), 4, 4) or name != method \
            or not np.all(np.isfinite(poses)):
        return None
    return LogPoses(poses, [IcpResult(r, float(f), float(e)) for r, f, e in zip(rel, fit, rmse)], name)


def log_poses(files: list[Path], read: Callable[[Path], np.ndarray], method: str = DEFAULT_ODOMETRY,
              *, cache: bool = True) -> LogPoses:
    """The poses of a log whose sweeps are `files` (in time order): from the cache where this
    estimator already ran on these files, else estimated from `read(file)` ((N, 3) metres, sensor
    frame) and cached. cache: False estimates without reading or writing the cache."""
    files = [Path(f) for f in files]
    est = odometry(method)
    path = None
    if cache and files:
        path = cache_dir() / "poses" / f"{_key(files, est)}.npz"
        if path.is_file():
            hit = _read_cache(path, len(files), est.name)
            if hit is not None:
                return hit
    result = est.estimate([np.asarray(read(f), np.float64)[:, :3] for f in files])
    if path is not None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(path) as tmp:
                with open(tmp, "wb") as fh:
                    np.savez(fh, poses=result.poses, method=np.array(result.method),
                             steps=np.stack([s.pose for s in result.steps]) if result.steps else np.zeros((0, 4, 4)),
                             fitness=np.array([s.fitness for s in result.steps], np.float64),
                             rmse=np.array([s.rmse for s in result.steps], np.float64))
        except OSError:
            pass  # a read-only home: the poses are still returned, estimated again next time
    return result
