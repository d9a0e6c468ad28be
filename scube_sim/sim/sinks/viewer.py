"""A sink that records a run for a viewer: one MCAP file of Foxglove messages (protobuf), opened by
Foxglove (and Lichtblick, and Rerun's MCAP loader) as it is.

- ``/lidar/<sensor>`` foxglove.PointCloud, one per sweep: x y z intensity (float32), red green
  blue alpha (uint8: the label's colour), label (int16), ring (uint16), instance (int32), time
  (float32 s after the sweep start), stride 32 bytes; frame_id = world, pose = the sensor's pose
  at `t_ref`, timestamp `t_ref`, log time the sweep end.
- ``/boxes`` foxglove.SceneUpdate at each tick: a deletion of ALL, then one entity per box (a cube
  coloured by label; metadata label, instance, track_id), world frame.
- ``/tf`` foxglove.FrameTransforms at each tick: world -> ego (`Frame.ego_pose`) and ego -> each
  LiDAR (its mount).

To colour points by label pick "RGBA (separate fields)" in the point cloud's colour mode.
Times: the host's seconds plus `time_offset_s` (MCAP times are unsigned nanoseconds).
Each frame ends an MCAP chunk, so a killed run leaves a file whose complete chunks a stream
reader reads; an error in the run closes the file normally (summary and footer written).

`read_recording` decodes such a file with the schemas stored in it, and `plot_bev` draws one
tick's points and boxes from above (the PNG in the README comes from it: the viewers need a
screen, this does not).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator

from ...atomic import atomic_path, with_path
from ...errors import InputError
from ...labels import LABEL_COLORS, LABEL_NAMES
from ...transforms import quat_to_rotmat, rotmat_to_quat
from ..frame import Frame
from .base import RunInfo, Sink
from .rosbag import RosNamesConfig, check_topic, ros_name

UNKNOWN_COLOR = np.array([128, 128, 128], np.uint8)  # labels outside the table (e.g. -1)

# The PointCloud layout: (name, offset, foxglove.PackedElementField.NumericType).
UINT8, INT16, UINT16, INT32, FLOAT32 = 1, 4, 3, 6, 7
POINT_FIELDS = (("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 12, FLOAT32),
                ("red", 16, UINT8), ("green", 17, UINT8), ("blue", 18, UINT8), ("alpha", 19, UINT8),
                ("label", 20, INT16), ("ring", 22, UINT16), ("instance", 24, INT32), ("time", 28, FLOAT32))
POINT_STRIDE = 32
_NUMPY = {UINT8: "u1", INT16: "<i2", UINT16: "<u2", INT32: "<i4", FLOAT32: "<f4", 2: "i1", 5: "<u4", 8: "<f8"}
VIEWER_DTYPE = np.dtype({"names": [n for n, _, _ in POINT_FIELDS], "offsets": [o for _, o, _ in POINT_FIELDS],
                         "formats": [_NUMPY[t] for _, _, t in POINT_FIELDS], "itemsize": POINT_STRIDE})


class ViewerConfig(RosNamesConfig):
    """What a `ViewerSink` writes. topics: sensor name -> topic (default ``/lidar/<token>``);
    frame_ids: sensor name -> frame id (default ``<token>``); box_alpha: the cubes' opacity;
    compression: MCAP chunk compression; time_offset_s: added to every time (s)."""

    boxes_topic: str = "/boxes"
    tf_topic: str = "/tf"
    box_alpha: float = Field(default=0.35, ge=0, le=1)
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    time_offset_s: float = 0.0

    @field_validator("boxes_topic", "tf_topic")
    @classmethod
    def _topic(cls, v, info):
        return check_topic(v, info.field_name)


def label_colors(labels: np.ndarray) -> np.ndarray:
    """(N,) label ids -> (N, 3) uint8 sRGB from the label table (grey outside it)."""
    labels = np.asarray(labels).astype(np.int64)
    inside = (labels >= 0) & (labels < len(LABEL_COLORS))
    out = np.broadcast_to(UNKNOWN_COLOR, (labels.shape[0], 3)).copy()
    out[inside] = LABEL_COLORS[labels[inside]]
    return out


def viewer_points(points: np.ndarray) -> np.ndarray:
    """POINT_DTYPE points (N,) -> (N,) VIEWER_DTYPE records (the PointCloud's data)."""
    out = np.zeros(points.shape[0], VIEWER_DTYPE)
    for name in ("x", "y", "z", "intensity", "label", "ring", "instance", "time"):
        out[name] = points[name]
    rgb = label_colors(points["label"])
    out["red"], out["green"], out["blue"], out["alpha"] = rgb[:, 0], rgb[:, 1], rgb[:, 2], 255
    return out


def _protobuf() -> SimpleNamespace:
    """protobuf's descriptor modules, imported on first use: `scube_sim.sim` imports this module, and only
    recording or reading back a viewer file needs them."""
    from google.protobuf import descriptor_pool, message_factory
    from google.protobuf.descriptor_pb2 import FileDescriptorSet

    return SimpleNamespace(descriptor_pool=descriptor_pool, message_factory=message_factory,
                           FileDescriptorSet=FileDescriptorSet)


def _mcap() -> SimpleNamespace:
    """mcap's writer and reader, imported on first use (as `_protobuf`)."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    return SimpleNamespace(CompressionType=CompressionType, Writer=Writer, make_reader=make_reader)


def _descriptor_set(descriptor) -> bytes:
    """The serialized FileDescriptorSet of a message's file and its imports, imports first (what
    MCAP's protobuf profile stores as the schema)."""
    fds, seen = _protobuf().FileDescriptorSet(), set()

    def add(fd):
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(fds.file.add())

    add(descriptor.file)
    return fds.SerializeToString()


class ViewerSink(Sink):
    """The run as a Foxglove MCAP at `path` (see the module doc). Options: `ViewerConfig` (pass
    `config=` or its fields as keywords)."""

    def __init__(self, path: str | Path, config: ViewerConfig | None = None, **options):
        self.path = Path(path)
        if config is not None and options:
            raise InputError("ViewerSink: give either config or keyword options, not both")
        try:
            self.config = config if config is not None else ViewerConfig(**options)
        except ValidationError as exc:
            raise InputError(f"ViewerSink: {exc}") from exc
        self._fh = None
        self._writer = None
        self._channels: dict[str, int] = {}
        self._mounts: dict[str, np.ndarray] = {}

    def open(self, run: RunInfo) -> None:
        from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
        from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
        from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

        mcap = _mcap()
        CompressionType = mcap.CompressionType
        cfg = self.config
        if self.path.is_dir():
            raise InputError(f"ViewerSink: {self.path} is a folder; give the .mcap file's path")
        self._check_time(run.start_time, "RunInfo.start_time")
        lidars = {str(n): (i if isinstance(i, dict) else {}) for n, i in (run.sensors or {}).items()
                  if not isinstance(i, dict) or i.get("kind", "lidar") == "lidar"}
        self._mounts = {n: np.asarray(i["mount"], np.float64) for n, i in lidars.items() if i.get("mount") is not None}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._fh = open(self.path, "wb")
        except OSError as exc:
            raise with_path(exc, self.path) from exc
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[cfg.compression]
        w = self._writer = mcap.Writer(self._fh, compression=comp)
        w.start(profile="", library="scube_sim")
        w.add_metadata("scube_sim", {"start_time": repr(float(run.start_time)),
                                     "origin": " ".join(repr(float(v)) for v in np.asarray(run.origin).reshape(3)),
                                     "time_offset_s": repr(float(cfg.time_offset_s))})
        schema = {cls.DESCRIPTOR.full_name: w.register_schema(cls.DESCRIPTOR.full_name, "protobuf",
                                                              _descriptor_set(cls.DESCRIPTOR))
                  for cls in (PointCloud, SceneUpdate, FrameTransforms)}
        for name in lidars:
            topic = cfg.topics.get(name, f"/lidar/{ros_name(name)}")
            self._channels[name] = w.register_channel(topic, "protobuf", schema["foxglove.PointCloud"])
        self._channels["/boxes"] = w.register_channel(cfg.boxes_topic, "protobuf", schema["foxglove.SceneUpdate"])
        self._channels["/tf"] = w.register_channel(cfg.tf_topic, "protobuf", schema["foxglove.FrameTransforms"])
        self._classes = {"PointCloud": PointCloud, "SceneUpdate": SceneUpdate, "FrameTransforms": FrameTransforms}
        w.flush()

    def write(self, frame: Frame) -> None:
        cfg = self.config
        PointCloud = self._classes["PointCloud"]
        for s in frame.sweeps():
            if s.kind != "lidar":
                continue  # cameras: frames carry no images yet
            if s.name not in self._channels:
                raise InputError(f"ViewerSink: sweep of sensor {s.name!r}, which is not in the run's LiDARs")
            msg = PointCloud(frame_id=cfg.world_frame, point_stride=POINT_STRIDE,
                             data=viewer_points(s.points).tobytes())
            self._stamp(msg.timestamp, s.t_ref)
            _set_pose(msg.pose, s.pose)
            for name, offset, typ in POINT_FIELDS:
                msg.fields.add(name=name, offset=offset, type=typ)
            self._put(s.name, s.t_end, msg)
        tfs = self._classes["FrameTransforms"]()
        links = [(cfg.world_frame, cfg.ego_frame, frame.ego_pose)]
        links += [(cfg.ego_frame, cfg.frame_ids.get(n, ros_name(n)), m) for n, m in self._mounts.items()]
        for parent, child, pose in links:
            tr = tfs.transforms.add(parent_frame_id=parent, child_frame_id=child)
            self._stamp(tr.timestamp, frame.time)
            tr.translation.x, tr.translation.y, tr.translation.z = map(float, pose[:3, 3])
            _set_quat(tr.rotation, pose[:3, :3])
        self._put("/tf", frame.time, tfs)
        self._put("/boxes", frame.time, self._scene(frame))
        self._writer.flush()  # one chunk per frame: a killed run keeps every complete frame

    def close(self) -> None:
        w, fh = self._writer, self._fh
        self._writer = self._fh = None
        try:
            if w is not None:
                w.finish()
        finally:
            if fh is not None:
                fh.close()

    # ----------------------------------------------------------------
    def _ns(self, t: float) -> int:
        return int(round((float(t) + self.config.time_offset_s) * 1e9))

    def _check_time(self, t: float, what: str) -> None:
        if not np.isfinite(t) or self._ns(t) < 0:
            raise InputError(f"ViewerSink: {what} = {t} s gives a negative or invalid MCAP time; set time_offset_s "
                             "so that every time is >= 0")

    def _stamp(self, ts, t: float) -> None:
        self._check_time(t, "a time")
        ns = self._ns(t)
        ts.seconds, ts.nanos = ns // 1_000_000_000, ns % 1_000_000_000

    def _put(self, key: str, t: float, msg) -> None:
        self._check_time(t, "a message time")
        ns = self._ns(t)
        self._writer.add_message(self._channels[key], log_time=ns, data=msg.SerializeToString(), publish_time=ns)

    def _scene(self, frame: Frame):
        cfg = self.config
        update = self._classes["SceneUpdate"]()
        gone = update.deletions.add(type=1)  # ALL: boxes of earlier ticks go
        self._stamp(gone.timestamp, frame.time)
        for i, b in enumerate(frame.boxes):
            ent = update.entities.add(frame_id=cfg.world_frame, id=f"box-{b.instance or i}")
            self._stamp(ent.timestamp, frame.time)
            name = b.category or (LABEL_NAMES[b.label] if 0 <= b.label < len(LABEL_NAMES) else str(b.label))
            for key, value in (("label", name), ("instance", str(b.instance)), ("track_id", b.track_id)):
                if value:
                    ent.metadata.add(key=key, value=value)
            cube = ent.cubes.add()
            cube.pose.position.x, cube.pose.position.y, cube.pose.position.z = map(float, b.center)
            _set_quat(cube.pose.orientation, b.rotation)
            cube.size.x, cube.size.y, cube.size.z = map(float, b.size)
            r, g, bl = label_colors(np.array([b.label]))[0] / 255.0
            cube.color.r, cube.color.g, cube.color.b, cube.color.a = float(r), float(g), float(bl), cfg.box_alpha
        return update


def _set_quat(q, rotation: np.ndarray) -> None:
    w, x, y, z = rotmat_to_quat(rotation)
    q.x, q.y, q.z, q.w = float(x), float(y), float(z), float(w)


def _set_pose(pose, t: np.ndarray) -> None:
    pose.position.x, pose.position.y, pose.position.z = map(float, t[:3, 3])
    _set_quat(pose.orientation, t[:3, :3])


# ------------------------------------------------------------------ reading back
@dataclass
class Recording:
    """A decoded viewer recording: clouds: topic -> [(log_time ns, world points (N, 3) float64,
    colours (N, 3) uint8, VIEWER_DTYPE records)]; scenes: [(log_time ns, [(center (3,), size (3,),
    yaw rad, colour (3,) float, label name)])]."""

    clouds: dict[str, list] = field(default_factory=dict)
    scenes: list = field(default_factory=list)


def read_recording(path: str | Path) -> Recording:
    """Decode a `ViewerSink` file with the protobuf schemas stored in it."""
    pb = _protobuf()
    descriptor_pool, message_factory, FileDescriptorSet = pb.descriptor_pool, pb.message_factory, pb.FileDescriptorSet
    make_reader = _mcap().make_reader

    path = Path(path)
    out = Recording()
    classes: dict[int, type] = {}
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise with_path(exc, path) from exc
    with fh:
        for schema, channel, message in make_reader(fh).iter_messages(log_time_order=True):
            if schema is None or schema.encoding != "protobuf":
                raise InputError(f"{path}: channel {channel.topic} is not protobuf-encoded")
            if schema.id not in classes:
                pool = descriptor_pool.DescriptorPool()
                for fd in FileDescriptorSet.FromString(schema.data).file:
                    pool.Add(fd)
                classes[schema.id] = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
            msg = classes[schema.id].FromString(message.data)
            if schema.name == "foxglove.PointCloud":
                out.clouds.setdefault(channel.topic, []).append((message.log_time, *_decode_cloud(msg, path)))
            elif schema.name == "foxglove.SceneUpdate":
                out.scenes.append((message.log_time, [_decode_cube(e) for e in msg.entities for _ in e.cubes]))
    return out


def _decode_cloud(msg, path: Path):
    dt = np.dtype({"names": [f.name for f in msg.fields], "offsets": [f.offset for f in msg.fields],
                   "formats": [_NUMPY[f.type] for f in msg.fields], "itemsize": msg.point_stride})
    if msg.point_stride <= 0 or len(msg.data) % msg.point_stride:
        raise InputError(f"{path}: a PointCloud's data ({len(msg.data)} bytes) is not a whole number of "
                         f"{msg.point_stride}-byte points")
    rec = np.frombuffer(msg.data, dt)
    p, q = msg.pose.position, msg.pose.orientation
    r = quat_to_rotmat(np.array([q.w, q.x, q.y, q.z]))
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64) @ r.T + [p.x, p.y, p.z]
    rgb = np.stack([rec["red"], rec["green"], rec["blue"]], axis=1) if "red" in dt.names else \
        np.zeros((len(rec), 3), np.uint8)
    return xyz, rgb, rec


def _decode_cube(entity):
    c = entity.cubes[0]
    q = c.pose.orientation
    yaw = float(np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z)))
    label = next((kv.value for kv in entity.metadata if kv.key == "label"), "")
    return (np.array([c.pose.position.x, c.pose.position.y, c.pose.position.z]),
            np.array([c.size.x, c.size.y, c.size.z]), yaw, np.array([c.color.r, c.color.g, c.color.b]), label)


def plot_bev(path: str | Path, out_png: str | Path, *, tick: int = -1,
             extent: tuple[float, float, float, float] | None = None) -> Path:
    """Bird's-eye view of one tick of a viewer recording: the points of the sweeps that ended in
    (previous tick, tick] coloured by label, and that tick's boxes outlined. tick: index into the
    ticks (-1 the last); extent: (x_min, x_max, y_min, y_max) world metres (default: the points').
    Written atomically; returns the PNG's path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch, Polygon

    rec = read_recording(path)
    if not rec.scenes:
        raise InputError(f"{path}: no ticks (SceneUpdate messages) recorded")
    k = range(len(rec.scenes))[tick]
    t1 = rec.scenes[k][0]
    t0 = rec.scenes[k - 1][0] if k > 0 else -1
    xyz, labels = [np.zeros((0, 3))], [np.zeros(0, np.int16)]
    for clouds in rec.clouds.values():
        for t, p, _rgb, points in clouds:
            if t0 < t <= t1:
                xyz.append(p)
                labels.append(points["label"])
    xyz, labels = np.concatenate(xyz), np.concatenate(labels)
    if extent is None and len(xyz):
        lo, hi = np.percentile(xyz[:, :2], [1, 99], axis=0)
        extent = (lo[0] - 2, hi[0] + 2, lo[1] - 2, hi[1] + 2)
    width = 10.0
    height = width * (extent[3] - extent[2]) / (extent[1] - extent[0]) if extent else width
    fig, ax = plt.subplots(figsize=(width, max(3.0, height + 1.0)), dpi=110)
    ax.set_facecolor("#d9d9d9")  # light grey: white lane markers and dark cars both show
    order = np.argsort(labels == 18, kind="stable")[::-1]  # road first, everything else drawn over it
    ax.scatter(xyz[order, 0], xyz[order, 1], s=0.4, c=label_colors(labels[order]) / 255.0, linewidths=0)
    for c, size, yaw, colour, _label in rec.scenes[k][1]:
        r = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
        corners = (np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * size[:2] / 2) @ r.T + c[:2]
        ax.add_patch(Polygon(corners, closed=True, fill=False, lw=1.8, ec=colour))
        ax.plot(*(c[:2] + r @ [size[0] / 2, 0]), marker=">", ms=4, color=colour)  # the heading
    present, counts = np.unique(labels, return_counts=True)
    shown = [int(v) for v, n in sorted(zip(present, counts), key=lambda x: -x[1]) if 0 <= v < len(LABEL_NAMES)][:8]
    ax.legend(handles=[Patch(color=label_colors(np.array([v]))[0] / 255.0, label=LABEL_NAMES[v]) for v in shown],
              loc="upper right", fontsize=7, ncol=2, framealpha=0.9)
    if extent:
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, world)")
    ax.set_ylabel("y (m, world)")
    ax.set_title(f"{Path(path).name}: tick {k}, {len(xyz)} points by label, {len(rec.scenes[k][1])} boxes")
    out_png = Path(out_png)
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    plt.close(fig)
    return out_png
