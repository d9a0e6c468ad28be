"""A sink that records a run as a ROS 2 bag (rosbag2 folder, MCAP storage), written without ROS.

The folder holds ``metadata.yaml`` and ``<folder name>.mcap`` (written by `rosbags`, metadata
version 8: its QoS profiles are a YAML string, which Humble reads as well as Jazzy and later).
``ros2 bag play FOLDER`` plays it; play it *without* ``--clock``, since the bag has its own.

Topics (all names configurable; sensor names are made ROS-safe, e.g. 'front-left' -> front_left):

- ``/lidar/<sensor>/points`` sensor_msgs/msg/PointCloud2: one per sweep, sensor frame, packed by
  the sensor's `PointLayout` (`scube_sim.io.ros2_points`). Header stamp: the sweep start (or its
  `t_ref` with stamp='ref'); log time: the sweep end (when a driver would publish it).
- ``/tf`` tf2_msgs/msg/TFMessage: world_frame -> ego_frame (`Frame.ego_pose`) at each tick.
- ``/tf_static`` tf2_msgs/msg/TFMessage: ego_frame -> each LiDAR (`RunInfo.sensors[name]['mount']`),
  once at the run's first instant, offered transient_local (latched, as a static broadcaster).
- ``/clock`` rosgraph_msgs/msg/Clock: the tick time.
- ``/boxes`` visualization_msgs/msg/MarkerArray: a DELETEALL, then one CUBE per box (world frame,
  coloured by label), at each tick.
- ``/detections`` (opt-in) vision_msgs/msg/Detection3DArray: one Detection3D per box (class_id =
  category or label name, id = track or instance), at each tick.

Times are the host's seconds plus `time_offset_s` (a bag's timestamps are unsigned nanoseconds).
The world frame is the scene's local frame; `RunInfo.origin` goes into the metadata's custom_data.
Cameras are not recorded: frames carry no images yet.

Interruption: an error in the run closes the bag as usual (every frame written is in it). Every
frame also ends an MCAP chunk and rewrites metadata.yaml (atomically), so even a killed process
leaves a bag of the frames written: the MCAP then lacks its summary, which rosbag2's MCAP reader
rebuilds by scanning (``ros2 bag reindex`` also rewrites metadata.yaml).
"""

from __future__ import annotations

import re
from io import StringIO
from pathlib import Path
from types import SimpleNamespace
from typing import Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator

from ...atomic import atomic_path
from ...config import StrictModel
from ...errors import InputError
from ...io.ros2_points import LayoutKind, PointLayout, as_layout, pack_points
from ...labels import LABEL_COLORS, LABEL_NAMES
from ...transforms import rotmat_to_quat
from ..frame import Frame
from .base import RunInfo, Sink

BAG_VERSION = 8  # rosbag2 metadata version: the newest whose QoS profiles Humble can parse

# vision_msgs 4.1.1 (ros-perception/vision_msgs, branch ros2, tag 4.1.1): the fields of the five
# messages a Detection3DArray needs (comments dropped; they do not enter the type hash).
VISION_MSGS = {
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": ("vision_msgs/ObjectHypothesis hypothesis\n"
                                                 "geometry_msgs/PoseWithCovariance pose\n"),
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": ("std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
                                    "vision_msgs/BoundingBox3D bbox\nstring id\n"),
    "vision_msgs/msg/Detection3DArray": "std_msgs/Header header\nvision_msgs/Detection3D[] detections\n",
}

_TOPIC = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


def ros_name(name: str) -> str:
    """`name` as one ROS name token: [A-Za-z0-9_], not starting with a digit."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", str(name)) or "sensor"
    return f"s_{token}" if token[0].isdigit() else token


def check_topic(v: str, key: str) -> str:
    """`v` if it is an absolute ROS topic name, else a ValueError naming `key`."""
    if not _TOPIC.match(v):
        raise ValueError(f"{key}: {v!r} is not an absolute ROS topic name (/[A-Za-z_][A-Za-z0-9_]* tokens)")
    return v


def check_frame(v: str, key: str) -> str:
    """`v` if it is a usable tf frame id, else a ValueError naming `key`."""
    if not v or v.startswith("/") or any(c.isspace() for c in v):
        raise ValueError(f"{key}: {v!r} is not a tf frame id (non-empty, no leading '/', no spaces)")
    return v


class RosNamesConfig(StrictModel):
    """Topic and frame names shared by the ROS-flavoured sinks: per-sensor topics and frame ids,
    the world and ego frames, each checked against ROS 2's naming rules."""

    topics: dict[str, str] = Field(default_factory=dict)
    frame_ids: dict[str, str] = Field(default_factory=dict)
    world_frame: str = "map"
    ego_frame: str = "base_link"

    @field_validator("topics")
    @classmethod
    def _topics(cls, v):
        return {k: check_topic(t, f"topics[{k!r}]") for k, t in v.items()}

    @field_validator("frame_ids")
    @classmethod
    def _frames(cls, v):
        return {k: check_frame(f, f"frame_ids[{k!r}]") for k, f in v.items()}

    @field_validator("world_frame", "ego_frame")
    @classmethod
    def _frame(cls, v, info):
        return check_frame(v, info.field_name)


class RosbagConfig(RosNamesConfig):
    """What a `RosbagSink` writes.

    layouts: sensor name -> point layout (a kind name or a `PointLayout`); others get
    default_layout. topics / frame_ids: sensor name -> PointCloud2 topic / frame id (default
    ``/lidar/<token>/points`` and ``<token>``). stamp: PointCloud2 header stamp at the sweep start
    (drivers' convention: point times >= 0) or at its reference instant `t_ref` (where a
    motion-compensated sweep's points are). boxes: which box messages to write. compression:
    MCAP chunk compression. time_offset_s: added to every time (s)."""

    layouts: dict[str, PointLayout | LayoutKind] = Field(default_factory=dict)
    default_layout: PointLayout | LayoutKind = "velodyne"
    stamp: Literal["start", "ref"] = "start"
    boxes: list[Literal["markers", "detections"]] = Field(default_factory=lambda: ["markers"])
    markers_topic: str = "/boxes"
    detections_topic: str = "/detections"
    compression: Literal["none", "zstd"] = "none"
    time_offset_s: float = 0.0

    @field_validator("markers_topic", "detections_topic")
    @classmethod
    def _topic(cls, v, info):
        return check_topic(v, info.field_name)

    def layout(self, sensor: str) -> PointLayout:
        return as_layout(self.layouts.get(sensor, self.default_layout), f"layouts[{sensor!r}]")

    def topic(self, sensor: str) -> str:
        return self.topics.get(sensor, f"/lidar/{ros_name(sensor)}/points")

    def frame_id(self, sensor: str) -> str:
        return self.frame_ids.get(sensor, ros_name(sensor))


def _rosbags() -> SimpleNamespace:
    """What this sink uses of rosbags, imported on first use (~0.05 s): `scube_sim.sim` imports this module, and
    only a run that writes a bag needs it."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
    from rosbags.rosbag2.metadata import dump_qos_v8
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    return SimpleNamespace(
        Qos=Qos, QosDurability=QosDurability, QosHistory=QosHistory, QosLiveliness=QosLiveliness,
        QosReliability=QosReliability, QosTime=QosTime, StoragePlugin=StoragePlugin, Writer=Writer,
        CompressionFormat=CompressionFormat, CompressionMode=CompressionMode, dump_qos_v8=dump_qos_v8,
        Stores=Stores, get_types_from_msg=get_types_from_msg, get_typestore=get_typestore)


def typestore():
    """The rosbags typestore of ROS 2 Jazzy with vision_msgs registered. Every message written
    here has the same fields in Humble's store (Marker's texture and mesh_file included; only a
    constant differs), so one bag serves both."""
    rb = _rosbags()
    ts = rb.get_typestore(rb.Stores.ROS2_JAZZY)
    types = {}
    for name, text in VISION_MSGS.items():
        types.update(rb.get_types_from_msg(text, name))
    ts.register(types)
    return ts


class RosbagSink(Sink):
    """The run as a ROS 2 bag in `folder` (new, or an empty folder). Options: `RosbagConfig`
    (pass `config=` or its fields as keywords). See the module doc for topics and times."""

    def __init__(self, folder: str | Path, config: RosbagConfig | None = None, **options):
        self.folder = Path(folder)
        try:
            self.config = config if config is not None else RosbagConfig(**options)
        except ValidationError as exc:
            raise InputError(f"RosbagSink: {exc}") from exc
        if config is not None and options:
            raise InputError("RosbagSink: give either config or keyword options, not both")
        self._writer = None
        self._conns: dict[str, object] = {}
        self._sensors: dict[str, dict] = {}
        self._layouts: dict[str, PointLayout] = {}
        self._static_done = False

    # ---------------------------------------------------------------- setup
    def open(self, run: RunInfo) -> None:
        rb = _rosbags()
        Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime = (
            rb.Qos, rb.QosDurability, rb.QosHistory, rb.QosLiveliness, rb.QosReliability, rb.QosTime)

        cfg = self.config
        if self.folder.exists():
            if not self.folder.is_dir() or any(self.folder.iterdir()):
                raise InputError(f"RosbagSink: {self.folder} exists and is not an empty folder; a bag needs a new one")
            self.folder.rmdir()  # the writer creates the folder itself
        self._ts = typestore()
        lidars = {str(n): (i if isinstance(i, dict) else {}) for n, i in (run.sensors or {}).items()
                  if not isinstance(i, dict) or i.get("kind", "lidar") == "lidar"}
        for name, info in lidars.items():
            if info.get("mount") is None:
                raise InputError(f"RosbagSink: RunInfo.sensors[{name!r}] has no 'mount' (sensor-to-ego, 4x4) for "
                                 "/tf_static")
            self._layouts[name] = cfg.layout(name)
        for key in cfg.layouts:
            if key not in lidars:
                raise InputError(f"RosbagSink: layouts[{key!r}]: no such LiDAR in the run; LiDARs: {sorted(lidars)}")
        self._sensors = lidars
        self._check_time(run.start_time, "RunInfo.start_time")

        def qos(depth: int, latched: bool = False) -> Qos:
            zero = QosTime(0, 0)  # 0 = the RMW default (infinite) for deadline, lifespan, lease
            return Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE,
                       QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE, zero, zero,
                       QosLiveliness.AUTOMATIC, zero, False)

        w = rb.Writer(self.folder, version=BAG_VERSION, storage_plugin=rb.StoragePlugin.MCAP)
        if cfg.compression == "zstd":
            w.set_compression(rb.CompressionMode.STORAGE, rb.CompressionFormat.ZSTD)
        w.set_custom_data("scube_sim.origin", " ".join(repr(float(v)) for v in np.asarray(run.origin).reshape(3)))
        w.set_custom_data("scube_sim.start_time", repr(float(run.start_time)))
        w.set_custom_data("scube_sim.time_offset_s", repr(float(cfg.time_offset_s)))
        w.open()
        self._writer = w
        add = lambda topic, typ, q: w.add_connection(topic, typ, typestore=self._ts,  # noqa: E731
                                                      offered_qos_profiles=[q])
        topics = {}
        for name in lidars:
            topic = cfg.topic(name)
            if topic in topics:
                raise InputError(f"RosbagSink: sensors {topics[topic]!r} and {name!r} share topic {topic}")
            topics[topic] = name
            self._conns[name] = add(topic, "sensor_msgs/msg/PointCloud2", qos(10))
        self._conns["/tf"] = add("/tf", "tf2_msgs/msg/TFMessage", qos(100))
        self._conns["/tf_static"] = add("/tf_static", "tf2_msgs/msg/TFMessage", qos(1, latched=True))
        self._conns["/clock"] = add("/clock", "rosgraph_msgs/msg/Clock", qos(1))
        if "markers" in cfg.boxes:
            self._conns["markers"] = add(cfg.markers_topic, "visualization_msgs/msg/MarkerArray", qos(10))
        if "detections" in cfg.boxes:
            self._conns["detections"] = add(cfg.detections_topic, "vision_msgs/msg/Detection3DArray", qos(10))
        self._flush()

    # ---------------------------------------------------------------- frames
    def write(self, frame: Frame) -> None:
        cfg, ts = self.config, self._ts
        sweeps = frame.sweeps()
        if not self._static_done:
            first = min([frame.time] + [s.t_start for s in sweeps])
            mounts = [(cfg.ego_frame, cfg.frame_id(n), np.asarray(i["mount"], np.float64))
                      for n, i in self._sensors.items()]
            self._put("/tf_static", first, self._tf_message(first, mounts))
            self._static_done = True
        for s in sweeps:
            if s.kind != "lidar":
                continue  # cameras: frames carry no images yet, so nothing to record
            if s.name not in self._conns:
                raise InputError(f"RosbagSink: sweep of sensor {s.name!r}, which is not in the run's LiDARs "
                                 f"{sorted(self._sensors)}")
            stamp = s.t_start if cfg.stamp == "start" else s.t_ref
            try:
                packed = pack_points(s.points, self._layouts[s.name], time_offset=stamp - s.t_start)
            except InputError as exc:
                raise InputError(f"RosbagSink: sensor {s.name!r}, sweep {s.sweep_index}: {exc}") from exc
            T = ts.types
            msg = T["sensor_msgs/msg/PointCloud2"](
                header=self._header(stamp, cfg.frame_id(s.name)), height=1, width=packed.width,
                fields=[T["sensor_msgs/msg/PointField"](name=f.name, offset=f.offset, datatype=f.datatype,
                                                        count=f.count) for f in packed.fields],
                is_bigendian=False, point_step=packed.point_step, row_step=packed.row_step, data=packed.data,
                is_dense=packed.is_dense)
            self._put(s.name, s.t_end, msg)
        self._put("/tf", frame.time, self._tf_message(frame.time, [(cfg.world_frame, cfg.ego_frame, frame.ego_pose)]))
        if "markers" in self._conns:
            self._put("markers", frame.time, self._markers(frame))
        if "detections" in self._conns:
            self._put("detections", frame.time, self._detections(frame))
        self._put("/clock", frame.time, ts.types["rosgraph_msgs/msg/Clock"](clock=self._time(frame.time)))
        self._flush()

    def close(self) -> None:
        w, self._writer = self._writer, None
        if w is not None:
            w.close()  # the MCAP summary, then metadata.yaml (written atomically by rosbags)

    # ---------------------------------------------------------------- messages
    def _ns(self, t: float) -> int:
        return int(round((float(t) + self.config.time_offset_s) * 1e9))

    def _check_time(self, t: float, what: str) -> None:
        if not np.isfinite(t) or self._ns(t) < 0:
            raise InputError(f"RosbagSink: {what} = {t} s gives a negative or invalid bag time; set time_offset_s "
                             "so that every time is >= 0")

    def _time(self, t: float):
        ns = self._ns(t)
        if ns < 0:
            self._check_time(t, "a time")
        return self._ts.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    def _header(self, t: float, frame_id: str):
        return self._ts.types["std_msgs/msg/Header"](stamp=self._time(t), frame_id=frame_id)

    def _pose(self, rotation: np.ndarray, translation: np.ndarray):
        T = self._ts.types
        w, x, y, z = rotmat_to_quat(rotation)
        return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](*map(float, translation)),
                                           orientation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))

    def _tf_message(self, t: float, links: list[tuple[str, str, np.ndarray]]):
        """TFMessage of (parent, child, (4, 4) child-to-parent) links stamped at t."""
        T = self._ts.types
        out = []
        for parent, child, pose in links:
            w, x, y, z = rotmat_to_quat(pose[:3, :3])
            out.append(T["geometry_msgs/msg/TransformStamped"](
                header=self._header(t, parent), child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](*map(float, pose[:3, 3])),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))))
        return T["tf2_msgs/msg/TFMessage"](transforms=out)

    def _markers(self, frame: Frame):
        T, cfg = self._ts.types, self.config
        header = self._header(frame.time, cfg.world_frame)
        clear = _default(self._ts, "visualization_msgs/msg/Marker", header=header, ns="boxes", action=3)
        markers = [clear]  # DELETEALL first: a box gone since the last tick disappears
        for i, b in enumerate(frame.boxes):
            rgb = LABEL_COLORS[b.label] / 255.0 if 0 <= b.label < len(LABEL_COLORS) else (0.5, 0.5, 0.5)
            markers.append(_default(
                self._ts, "visualization_msgs/msg/Marker", header=header, ns="boxes", id=i, type=1, action=0,
                pose=self._pose(b.rotation, b.center), scale=T["geometry_msgs/msg/Vector3"](*map(float, b.size)),
                color=T["std_msgs/msg/ColorRGBA"](r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=0.5),
                text=_box_name(b)))
        return T["visualization_msgs/msg/MarkerArray"](markers=markers)

    def _detections(self, frame: Frame):
        T, cfg = self._ts.types, self.config
        header = self._header(frame.time, cfg.world_frame)
        dets = []
        for b in frame.boxes:
            pose = self._pose(b.rotation, b.center)
            hyp = T["vision_msgs/msg/ObjectHypothesisWithPose"](
                hypothesis=T["vision_msgs/msg/ObjectHypothesis"](class_id=_box_name(b), score=1.0),
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)))
            dets.append(T["vision_msgs/msg/Detection3D"](
                header=header, results=[hyp],
                bbox=T["vision_msgs/msg/BoundingBox3D"](center=pose,
                                                        size=T["geometry_msgs/msg/Vector3"](*map(float, b.size))),
                id=str(b.track_id) if b.track_id else str(int(b.instance))))
        return T["vision_msgs/msg/Detection3DArray"](header=header, detections=dets)

    # ---------------------------------------------------------------- output
    def _put(self, key: str, t: float, msg) -> None:
        conn = self._conns[key]
        self._check_time(t, f"the time of a {conn.topic} message")
        self._writer.write(conn, self._ns(t), bytes(self._ts.serialize_cdr(msg, conn.msgtype)))

    def _flush(self) -> None:
        """End the MCAP chunk, flush it and rewrite metadata.yaml: a killed run leaves a bag of the
        frames written so far."""
        w = self._writer
        storage = getattr(w, "storage", None)
        chunk = getattr(storage, "chunk", None)
        if chunk is not None and hasattr(storage, "close_chunk") and chunk.bio.tell():
            storage.close_chunk()
        if storage is not None and hasattr(storage, "bio"):
            storage.bio.flush()
        with atomic_path(self.folder / "metadata.yaml") as tmp:
            Path(tmp).write_text(_metadata_yaml(w), encoding="utf-8")


def _box_name(b) -> str:
    if b.category:
        return str(b.category)
    return LABEL_NAMES[b.label] if 0 <= b.label < len(LABEL_NAMES) else str(int(b.label))


def _default(ts, typename: str, **given):
    """A message of `typename` with `given` fields and zero / empty values elsewhere (message
    classes need every field; Marker has 19)."""
    fields = ts.fielddefs[typename][1]
    kw = {}
    for name, (node, detail) in fields:
        if name in given:
            kw[name] = given[name]
        else:
            kw[name] = _zero(ts, node.value, detail)
    return ts.types[typename](**kw)


def _zero(ts, node: int, detail):
    # rosbags Nodetype: 1 BASE, 2 NAME, 3 ARRAY (fixed length), 4 SEQUENCE
    if node == 1:
        typ = detail[0]
        return "" if typ in ("string", "wstring") else False if typ == "bool" else 0.0 if typ.startswith("float") \
            else 0
    if node == 2:
        return _default(ts, detail)
    (inner_node, inner), length = detail
    if inner_node.value == 1 and inner[0] not in ("string", "wstring"):
        return np.zeros(length if node == 3 else 0, _NP[inner[0]])
    return [_zero(ts, inner_node.value, inner) for _ in range(length if node == 3 else 0)]


_NP = {"bool": np.bool_, "int8": np.int8, "uint8": np.uint8, "byte": np.uint8, "char": np.uint8, "int16": np.int16,
       "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
       "float32": np.float32, "float64": np.float64}


def _metadata_yaml(w) -> str:
    """metadata.yaml for what `w` (a rosbags Writer) has written so far, as its close() writes it."""
    from ruamel.yaml import YAML

    dump_qos_v8 = _rosbags().dump_qos_v8

    start = w.min_timestamp if w.counts and sum(w.counts.values()) else 0
    duration = max(0, w.max_timestamp - w.min_timestamp) if start else 0
    count = sum(w.counts.values())
    name = w.storage.path.name
    info = {
        "version": w.version, "storage_identifier": "mcap", "relative_file_paths": [name],
        "duration": {"nanoseconds": duration}, "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": count,
        "topics_with_message_count": [
            {"topic_metadata": {"name": c.topic, "type": c.msgtype, "serialization_format": c.ext.serialization_format,
                                "offered_qos_profiles": dump_qos_v8(c.ext.offered_qos_profiles),
                                "type_description_hash": c.digest},
             "message_count": w.counts[c.id]} for c in w.connections],
        "compression_format": "", "compression_mode": "",
        "files": [{"path": name, "starting_time": {"nanoseconds_since_epoch": start},
                   "duration": {"nanoseconds": duration}, "message_count": count}],
        "custom_data": w.custom_data or None, "ros_distro": "rosbags",
    }
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    out = StringIO()
    yaml.dump({"rosbag2_bagfile_information": info}, out)
    return out.getvalue()
