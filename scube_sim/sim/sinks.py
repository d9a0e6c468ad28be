"""Where frames go: sinks, and the writer thread that feeds them behind a bounded queue.

A sink has `open(run)`, `write(frame)` and `close()`. The simulator never calls sinks itself: it
puts frames into a `SinkRunner`, whose single writer thread calls every sink in order. The queue
is bounded, so a slow sink slows the loop down (back-pressure) and no frame is ever dropped. A
sink that raises stops the run: the error is re-raised in the loop at its next `put` (or at
`close`). `close()` — also on Ctrl-C or an exception in the host — writes every frame already
queued, then closes every sink, so each completed frame is on disk and files are finalised.
"""

from __future__ import annotations

import json
import queue
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..io.atomic import atomic_path
from .frame import Frame


@dataclass
class RunInfo:
    """What sinks may need to know when a run starts.

    sensors: name -> dict (kind, rate_hz, preset/config name, channels, mount (4, 4)); scene:
    the static scene object (VoxSplat / Gaussians / TriangleMesh) or None; origin: float64 world
    offset of the scene's local frame; time_codes_per_second: the USD time base; metadata: free."""

    sensors: dict = field(default_factory=dict)
    scene: object | None = None
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    time_codes_per_second: float = 100.0
    start_time: float = 0.0
    metadata: dict = field(default_factory=dict)


class Sink:
    """Base class: override what you need."""

    def open(self, run: RunInfo) -> None:  # noqa: B027 - optional hook
        pass

    def write(self, frame: Frame) -> None:
        raise NotImplementedError

    def close(self) -> None:  # noqa: B027 - optional hook
        pass


class CallbackSink(Sink):
    """Calls `fn(frame)` on the writer thread for every frame."""

    def __init__(self, fn: Callable[[Frame], None]):
        self.fn = fn

    def write(self, frame: Frame) -> None:
        self.fn(frame)


class QueueSink(Sink):
    """Puts every frame into `self.queue` (a `queue.Queue`, bounded by `maxsize`) for an
    in-process consumer; a full queue blocks the writer thread, hence the loop."""

    def __init__(self, maxsize: int = 0):
        self.queue: queue.Queue = queue.Queue(maxsize)

    def write(self, frame: Frame) -> None:
        self.queue.put(frame)

    def close(self) -> None:
        self.queue.put(None)  # end-of-run marker for consumers


class FileSink(Sink):
    """Per-frame files under `folder`: for each LiDAR sweep `<sensor>/<tick:06d>_<k>.<fmt>` for
    each format in `formats` ('pcd', 'bin' KITTI x y z intensity, 'npz' all fields + poses), and a
    manifest `frames.jsonl` with one line per written sweep (tick, time, sensor, sweep span,
    poses, file names) and `boxes.jsonl` with each tick's actor boxes. Every file is written
    atomically and the manifest line only after its files: a manifest line means complete files."""

    def __init__(self, folder: str | Path, formats=("pcd",)):
        self.folder = Path(folder)
        bad = set(formats) - {"pcd", "bin", "npz", "ply"}
        if bad:
            raise ValueError(f"FileSink formats: unknown {sorted(bad)}; use pcd, bin, npz or ply")
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
        from ..io.pointcloud import write_kitti_bin, write_npz, write_pcd, write_ply_points

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
                else:
                    write_npz(path, s.points, pose=s.pose, pose_start=s.pose_start, pose_end=s.pose_end,
                              t_start=s.t_start, t_end=s.t_end, t_ref=s.t_ref, tick=frame.index)
                files.append(path.relative_to(self.folder).as_posix())
            self._manifest.write(json.dumps({
                "tick": frame.index, "time": frame.time, "sensor": s.name, "sweep": s.sweep_index,
                "t_start": s.t_start, "t_end": s.t_end, "t_ref": s.t_ref, "points": int(len(s.points)),
                "pose": s.pose.tolist(), "ego_pose": frame.ego_pose.tolist(), "files": files}) + "\n")
        self._boxes.write(json.dumps({"tick": frame.index, "time": frame.time,
                                      "boxes": [_box_json(b) for b in frame.boxes]}) + "\n")
        self._manifest.flush()
        self._boxes.flush()

    def close(self) -> None:
        for fh in (self._manifest, self._boxes):
            if fh is not None:
                fh.close()
        self._manifest = self._boxes = None


def _box_json(b: dict) -> dict:
    return {"instance": int(b["instance"]), "label": int(b["label"]), "center": [float(v) for v in b["center"]],
            "size": [float(v) for v in b["size"]], "yaw": float(b["yaw"])}


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


class SinkError(RuntimeError):
    """A sink failed; the run stops. `__cause__` is the sink's own exception."""


_STOP = object()


class SinkRunner:
    """Feeds frames to sinks on one writer thread behind a bounded queue (see module doc)."""

    def __init__(self, sinks: list[Sink], run: RunInfo, maxsize: int = 8):
        self.sinks = list(sinks)
        self.run = run
        self._queue: queue.Queue = queue.Queue(maxsize=max(1, maxsize))
        self._error: BaseException | None = None
        self._failed_sink: Sink | None = None
        self._thread: threading.Thread | None = None
        self.written = 0

    def start(self) -> None:
        for sink in self.sinks:
            sink.open(self.run)
        self._thread = threading.Thread(target=self._loop, name="scube-sim-sinks", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is _STOP:
                    return
                if self._error is not None:
                    continue  # stopped: drain without writing
                for sink in self.sinks:
                    try:
                        sink.write(item)
                    except BaseException as exc:  # noqa: BLE001 - handed to the loop's thread
                        self._error, self._failed_sink = exc, sink
                        break
                else:
                    self.written += 1
            finally:
                self._queue.task_done()

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise SinkError(f"sink {type(self._failed_sink).__name__} failed: {self._error}") from self._error

    def put(self, frame: Frame) -> None:
        """Queue a frame; blocks while the queue is full (a slow sink slows the loop)."""
        self._raise_if_failed()
        while True:
            try:
                self._queue.put(frame, timeout=0.1)
                return
            except queue.Full:
                self._raise_if_failed()
                if self._thread is not None and not self._thread.is_alive():
                    raise SinkError("the sink writer thread stopped") from self._error

    def close(self) -> None:
        """Write what is queued, stop the thread and close every sink (also after an error).
        Re-raises a sink's error after closing."""
        if self._thread is not None and self._thread.is_alive():
            self._queue.put(_STOP)
            self._thread.join()
        close_error = None
        for sink in self.sinks:
            try:
                sink.close()
            except BaseException as exc:  # noqa: BLE001 - close them all, then report
                close_error = close_error or exc
        self._raise_if_failed()
        if close_error is not None:
            raise SinkError(f"closing a sink failed: {close_error}") from close_error
