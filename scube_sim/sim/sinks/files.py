"""Per-frame point-cloud files and their JSON-lines manifests."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...atomic import atomic_path, with_path
from ...errors import InputError
from ...io.las import write_las
from ...io.pointcloud import write_kitti_bin, write_npz, write_pcd, write_ply_points
from ..frame import Frame
from .base import RunInfo, Sink


class FileSink(Sink):
    """Per-frame files under `folder`: for each LiDAR sweep `<sensor>/<tick:06d>_<k>.<fmt>` for
    each format in `formats` ('pcd', 'bin' KITTI x y z intensity, 'npz' all fields + poses, 'ply',
    'las' / 'laz' LAS 1.4 with ring, time, label, instance as extra dimensions), and a
    manifest `frames.jsonl` with one line per written sweep (tick, time, sensor, sweep span,
    poses, file names) and `boxes.jsonl` with each tick's actor boxes. Every file is written
    atomically and the manifest line only after its files: a manifest line means complete files."""

    def __init__(self, folder: str | Path, formats=("pcd",)):
        self.folder = Path(folder)
        bad = set(formats) - {"pcd", "bin", "npz", "ply", "las", "laz"}
        if bad:
            raise InputError(f"FileSink formats: unknown {sorted(bad)}; use pcd, bin, npz, ply, las or laz")
        self.formats = tuple(formats)
        self._manifest = None
        self._boxes = None

    def open(self, run: RunInfo) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        with atomic_path(self.folder / "run.json") as tmp:
            Path(tmp).write_text(json.dumps({"sensors": _jsonable(run.sensors), "start_time": run.start_time,
                                             "origin": run.origin.tolist(), "metadata": _jsonable(run.metadata)},
                                            indent=1))
        self._manifest = open(self.folder / "frames.jsonl", "a", encoding="utf-8")
        self._boxes = open(self.folder / "boxes.jsonl", "a", encoding="utf-8")

    def write(self, frame: Frame) -> None:
        for k, s in enumerate(frame.sweeps()):
            sub = self.folder / s.name
            sub.mkdir(exist_ok=True)
            stem = f"{frame.index:06d}_{k}"
            files = []
            for fmt in self.formats:
                path = sub / f"{stem}.{fmt}"
                if fmt == "pcd":
                    write_pcd(path, s.points, viewpoint=s.pose)
                elif fmt == "bin":
                    write_kitti_bin(path, s.points)
                elif fmt == "ply":
                    write_ply_points(path, s.points)
                elif fmt in ("las", "laz"):
                    write_las(path, s.points)
                else:
                    write_npz(path, s.points, pose=s.pose, pose_start=s.pose_start, pose_end=s.pose_end,
                              t_start=s.t_start, t_end=s.t_end, t_ref=s.t_ref, tick=frame.index)
                files.append(path.relative_to(self.folder).as_posix())
            _append(self._manifest, json.dumps({
                "tick": frame.index, "time": frame.time, "sensor": s.name, "sweep": s.sweep_index,
                "t_start": s.t_start, "t_end": s.t_end, "t_ref": s.t_ref, "points": int(len(s.points)),
                "pose": s.pose.tolist(), "ego_pose": frame.ego_pose.tolist(), "files": files}) + "\n")
        _append(self._boxes, json.dumps({"tick": frame.index, "time": frame.time,
                                         "boxes": [b.to_json() for b in frame.boxes]}) + "\n")

    def close(self) -> None:
        for fh in (self._manifest, self._boxes):
            if fh is not None:
                fh.close()
        self._manifest = self._boxes = None


def _append(fh, line: str) -> None:
    """Append a manifest line and flush it; a write error names the manifest."""
    try:
        fh.write(line)
        fh.flush()
    except OSError as exc:
        raise with_path(exc, fh.name) from exc


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return obj
