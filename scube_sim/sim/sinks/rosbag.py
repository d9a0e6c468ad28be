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
frame also commits: it ends an MCAP chunk, writes a complete summary and footer after it (cut
off and written anew by the next commit) and rewrites metadata.yaml (atomically). So a killed
process (SIGKILL included) leaves a bag that the rosbags reader, ``ros2 bag`` and the `mcap`
tools open as it is, holding every frame committed. Only a kill during a commit's own writes
(a few milliseconds a frame) leaves an MCAP without its footer ("File end magic is invalid"),
or metadata.yaml one frame behind it: ``scube-sim bag-reindex FOLDER`` (`reindex_bag`) cuts it
back to its last whole chunk and rewrites the summary and metadata.yaml; on a bag that reads as
it is, it changes nothing. The summary grows by a chunk index entry a frame, so a long run's
commits grow slower with it.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import re
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from types import SimpleNamespace
from typing import Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator

from ...atomic import atomic_path
from ...config import StrictModel, unique_names
from ...errors import InputError, NotFoundError
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
    _boxes_once = field_validator("boxes")(classmethod(lambda cls, v: unique_names(v)))
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
    """What this sink uses of rosbags, imported on first use: `scube_sim.sim` imports this module, and
    only a run that writes a bag needs it."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
    from rosbags.rosbag2.metadata import dump_qos_v8
    from rosbags.rosbag2.storage_mcap import Channel, McapWriter, Schema, decompress
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    return SimpleNamespace(
        Qos=Qos, QosDurability=QosDurability, QosHistory=QosHistory, QosLiveliness=QosLiveliness,
        QosReliability=QosReliability, QosTime=QosTime, StoragePlugin=StoragePlugin, Writer=Writer,
        CompressionFormat=CompressionFormat, CompressionMode=CompressionMode, dump_qos_v8=dump_qos_v8,
        Reader=Reader, Channel=Channel, McapWriter=McapWriter, Schema=Schema, decompress=decompress,
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
        # Every chunk the storage ends (each frame's, and the writer's own at 1 MiB) is committed:
        # the index after it rewritten, then metadata.yaml (see `_commit`).
        storage = w.storage
        self._data_end = None
        self._topics = None
        self._close_chunk = storage.close_chunk
        storage.close_chunk = self._commit
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
            storage = w.storage
            if storage.chunk.bio.tell():
                storage.close_chunk()  # commit what is pending first
            del storage.close_chunk  # rosbags' own again for its close
            if self._data_end is not None:  # its summary goes where the data ends, over ours
                storage.bio.seek(self._data_end)
                storage.bio.truncate()
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
        """Commit the chunk pending (this frame's messages): a killed run leaves a bag of the frames
        written so far that the rosbags reader opens as it is."""
        storage = self._writer.storage
        if storage.chunk.bio.tell():
            storage.close_chunk()

    def _commit(self) -> None:
        """End the pending chunk (rosbags' close_chunk) where the data ends, then write a complete
        MCAP summary and footer after it and flush, then metadata.yaml (atomically). The next
        commit cuts the file back to the data's end first, so at any moment but during a commit's
        own writes the file is a whole MCAP of every chunk committed; a kill during them leaves one
        that `reindex_bag` (``scube-sim bag-reindex``) cuts back to its last whole chunk."""
        w = self._writer
        storage = w.storage
        bio = storage.bio
        if self._data_end is not None:
            bio.seek(self._data_end)
            bio.truncate()
        self._close_chunk()
        self._data_end = bio.tell()
        if self._topics is None or len(self._topics) != len(w.connections):
            self._topics = self._topic_meta(w)  # the connections' metadata, dumped once
        info = _bag_info(storage.path.name, self._topics, storage.channel_stats, storage.message_start_time,
                         storage.message_end_time, w.custom_data, w.version)
        bio.write(_summary(storage, info, self._data_end))
        bio.flush()
        with atomic_path(self.folder / "metadata.yaml") as tmp:
            Path(tmp).write_text(_dump_yaml({"rosbag2_bagfile_information": info}), encoding="utf-8")

    def _topic_meta(self, w) -> list[tuple[int, dict]]:
        dump_qos_v8 = _rosbags().dump_qos_v8
        return [(c.id, {"name": c.topic, "type": c.msgtype, "serialization_format": c.ext.serialization_format,
                        "offered_qos_profiles": dump_qos_v8(c.ext.offered_qos_profiles),
                        "type_description_hash": c.digest}) for c in w.connections]


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


def _bag_info(name: str, topics: list[tuple[int, dict]], counts: dict[int, int], t_min: int, t_max: int,
              custom: dict | None, version: int = BAG_VERSION) -> dict:
    """metadata.yaml's rosbag2_bagfile_information for an MCAP `name` of `counts` messages per
    channel id (topics: (channel id, topic_metadata)), as rosbags' Writer.close writes it."""
    count = int(sum(counts.values()))
    start = int(t_min) if count else 0
    duration = max(0, int(t_max) - int(t_min)) if count else 0
    return {
        "version": version, "storage_identifier": "mcap", "relative_file_paths": [name],
        "duration": {"nanoseconds": duration}, "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": count,
        "topics_with_message_count": [{"topic_metadata": meta, "message_count": int(counts.get(cid, 0))}
                                      for cid, meta in topics],
        "compression_format": "", "compression_mode": "",
        "files": [{"path": name, "starting_time": {"nanoseconds_since_epoch": start},
                   "duration": {"nanoseconds": duration}, "message_count": count}],
        "custom_data": custom or None, "ros_distro": "rosbags",
    }


def _dump_yaml(data: dict) -> str:
    """Block-style YAML of `data` (PyYAML's C emitter where built: a commit dumps twice)."""
    import yaml

    return yaml.dump(data, Dumper=getattr(yaml, "CSafeDumper", yaml.SafeDumper), default_flow_style=False,
                     sort_keys=False)


class _At(BytesIO):
    """A BytesIO whose tell() counts from `base` (the summary's offsets are the file's)."""

    def __init__(self, base: int):
        super().__init__()
        self.base = base

    def tell(self) -> int:
        return self.base + super().tell()

    def close(self) -> None:  # rosbags' close ends by closing its file: keep the bytes
        pass


def _summary(storage, info: dict, at: int) -> bytes:
    """What rosbags' McapWriter.close writes after the last chunk (the metadata record, data end,
    schemas, channels, chunk indexes, statistics, summary offsets, footer, end magic) for the
    chunks, schemas, channels and counts in `storage` (a McapWriter or the same fields), the data
    ending at byte `at`. Its own code writes it, so the file is the one its close would leave."""
    out = _At(at)
    state = SimpleNamespace(chunk=SimpleNamespace(bio=BytesIO()), bio=out, schemas=storage.schemas,
                            channels=storage.channels, chunks=storage.chunks, channel_stats=storage.channel_stats,
                            message_start_time=storage.message_start_time, message_end_time=storage.message_end_time)
    _rosbags().McapWriter.close(state, info["version"], _dump_yaml(info).strip())
    return out.getvalue()


# ---------------------------------------------------------------- recovery
MCAP_MAGIC = b"\x89MCAP0\r\n"


@dataclass
class Reindexed:
    """What `reindex_bag` did: the MCAP, the messages and chunks it holds now, the bytes cut from
    its end (an unfinished write), and whether it had to change anything."""

    mcap: Path
    messages: int
    chunks: int
    cut_bytes: int
    changed: bool


def _u(data: bytes, at: int, n: int) -> int:
    if at + n > len(data):
        raise ValueError("truncated")
    return int.from_bytes(data[at:at + n], "little")


def _string(data: bytes, at: int) -> tuple[bytes, int]:
    n = _u(data, at, 4)
    if at + 4 + n > len(data):
        raise ValueError("truncated")
    return data[at + 4:at + 4 + n], at + 4 + n


def _records(data: bytes):
    """(op, body) of each record of `data`, which must hold whole records only."""
    at = 0
    while at < len(data):
        n = _u(data, at + 1, 8)
        if at + 9 + n > len(data):
            raise ValueError("truncated")
        yield data[at], data[at + 9:at + 9 + n]
        at += 9 + n


def reindex_bag(folder: str | Path) -> Reindexed:
    """Make a bag that a killed `RosbagSink` left readable again, like ``ros2 bag reindex``: keep
    every whole chunk of its MCAP (with its message indexes), cut what follows (a write the kill
    interrupted), write the summary and footer after them and rewrite metadata.yaml from what the
    MCAP holds (topics' type hashes and custom data from the old metadata.yaml where it is
    readable). A bag that reads as it is, is left as it is. Bags written by this sink only: an
    MCAP holding anything else than chunks before its summary is refused, not cut."""
    folder = Path(folder)
    if not folder.is_dir():
        raise NotFoundError(f"{folder}: no such bag folder (a rosbag2 folder: metadata.yaml and an .mcap)")
    old_info: dict = {}
    meta_path = folder / "metadata.yaml"
    if meta_path.is_file():
        import yaml

        try:
            loaded = yaml.safe_load(meta_path.read_text(encoding="utf-8"))
            old_info = loaded.get("rosbag2_bagfile_information") if isinstance(loaded, dict) else {}
        except (yaml.YAMLError, UnicodeDecodeError):
            old_info = {}  # unreadable: rebuilt from the MCAP alone
        if not isinstance(old_info, dict):
            old_info = {}
    named = [folder / Path(str(p)).name for p in old_info.get("relative_file_paths") or []]
    candidates = [p for p in named if p.suffix == ".mcap" and p.is_file()] or sorted(folder.glob("*.mcap"))
    if len(candidates) != 1:
        listed = f" ({', '.join(p.name for p in candidates)})" if candidates else ""
        raise NotFoundError(f"{folder}: expected one .mcap file in the bag folder, found {len(candidates)}{listed}")
    path = candidates[0]
    with open(path, "rb") as fh:  # mapped, not read: a bag can be larger than memory
        size = os.fstat(fh.fileno()).st_size
        data = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
    try:
        return _reindex(folder, path, data, old_info, meta_path)
    finally:
        if isinstance(data, mmap.mmap):
            data.close()


def _reindex(folder: Path, path: Path, data, old_info: dict, meta_path: Path) -> Reindexed:
    """`reindex_bag` of the MCAP `path` whose bytes are `data` (bytes or a map of the file)."""
    rb = _rosbags()
    Channel, Schema, decompress = rb.Channel, rb.Schema, rb.decompress

    if data[:8] != MCAP_MAGIC:
        raise InputError(f"{path}: not an MCAP file (it does not start with the MCAP magic)")
    try:
        op, n = data[8], _u(data, 9, 8)
        profile, _ = _string(data, 17)
    except ValueError:
        op, profile = 0, b""
    if op != 0x01 or profile != b"ros2":
        raise InputError(f"{path}: not a ROS 2 MCAP (no header record of profile 'ros2')")
    at = 17 + n

    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    stats: dict[int, int] = {}
    chunks: list[BytesIO] = []
    t_min, t_max = 2**63 - 1, 0
    stop = "end"
    while at < len(data):
        op = data[at]
        try:
            n = _u(data, at + 1, 8)
        except ValueError:
            stop = "torn"
            break
        if op != 0x06:
            stop = "summary" if op in (0x0C, 0x0F) else f"op 0x{op:02x}"
            break
        chunk_start, body_end = at, at + 9 + n
        if body_end > len(data):
            stop = "torn"
            break
        try:
            body = data[at + 9:body_end]
            start, end, usize = _u(body, 0, 8), _u(body, 8, 8), _u(body, 16, 8)
            compression, k = _string(body, 28)
            csize = _u(body, k, 8)
            if k + 8 + csize > len(body):
                raise ValueError("truncated")
            raw = decompress(body[k + 8:k + 8 + csize], compression.decode(), usize, _u(body, 24, 4))
            if len(raw) != usize:
                raise ValueError("size")
            new_schemas, new_channels, msgs = {}, {}, {}
            for rop, rec in _records(raw):
                if rop == 0x03:
                    sid = _u(rec, 0, 2)
                    name, j = _string(rec, 2)
                    enc, j = _string(rec, j)
                    text, j = _string(rec, j)
                    new_schemas[sid] = Schema(sid, name.decode(), enc.decode(), text.decode())
                elif rop == 0x04:
                    cid, sid = _u(rec, 0, 2), _u(rec, 2, 2)
                    topic, j = _string(rec, 4)
                    enc, j = _string(rec, j)
                    meta, j = _string(rec, j)
                    sname = {**schemas, **new_schemas}[sid].name
                    new_channels[cid] = Channel(cid, sname, topic.decode(), enc.decode(), meta)
                elif rop == 0x05:
                    cid, t = _u(rec, 0, 2), _u(rec, 6, 8)
                    msgs[cid] = msgs.get(cid, 0) + 1
                    start, end = min(start, t), max(end, t)
            # the chunk's message indexes: one record per channel with messages in it
            j, offsets = body_end, []
            while j < len(data) and data[j] == 0x07:
                m = _u(data, j + 1, 8)
                if j + 9 + m > len(data):
                    raise ValueError("truncated")
                offsets.append((_u(data, j + 9, 2), j))
                j += 9 + m
            if sorted(c for c, _ in offsets) != sorted(msgs) or any(c not in channels and c not in new_channels
                                                                    for c in msgs):
                raise ValueError("index")
        except Exception:  # noqa: BLE001 - a chunk or index that a kill cut short (or that does not decode)
            stop = "torn"
            break
        schemas.update(new_schemas)
        for cid, ch in new_channels.items():
            channels[cid] = ch
            stats.setdefault(cid, 0)
        for cid, c in msgs.items():
            stats[cid] = stats.get(cid, 0) + c
        if msgs:
            t_min, t_max = min(t_min, start), max(t_max, end)
        idx = BytesIO()
        for v in (start, end, chunk_start, body_end - chunk_start):
            idx.write(int(v).to_bytes(8, "little"))
        idx.write((len(offsets) * 10).to_bytes(4, "little"))
        for cid, off in offsets:
            idx.write(cid.to_bytes(2, "little") + off.to_bytes(8, "little"))
        idx.write((j - body_end).to_bytes(8, "little"))
        idx.write(len(compression).to_bytes(4, "little") + compression)
        idx.write(csize.to_bytes(8, "little") + usize.to_bytes(8, "little"))
        chunks.append(idx)
        at = j
    if stop.startswith("op"):
        raise InputError(f"{path}: byte {at} holds a record ({stop}) that is not a chunk before the summary; "
                         "bag-reindex rebuilds bags written by scube-sim (RosbagSink) only, and leaves this one "
                         "as it is")
    count = sum(stats.values())
    if stop == "summary" and old_info.get("message_count") == count and _reads(folder):
        return Reindexed(path, count, len(chunks), 0, False)

    old_topics = {}
    for t in old_info.get("topics_with_message_count") or []:
        meta = t.get("topic_metadata") if isinstance(t, dict) else None
        if isinstance(meta, dict) and "name" in meta:
            old_topics[meta["name"]] = meta
    ts = None
    topics = []
    for cid, ch in sorted(channels.items()):
        qos = ""
        with contextlib.suppress(ValueError):
            j = 0
            while j < len(ch.metadata):  # the channel's metadata map: (key, value) strings
                key, j = _string(ch.metadata, j)
                value, j = _string(ch.metadata, j)
                if key == b"offered_qos_profiles":
                    qos = value.decode()
        digest = (old_topics.get(ch.topic) or {}).get("type_description_hash")
        if not digest:
            ts = ts or typestore()
            digest = ts.hash_rihs01(ch.schema) if ch.schema in ts.types else ""
        topics.append((cid, {"name": ch.topic, "type": ch.schema, "serialization_format": ch.message_encoding,
                             "offered_qos_profiles": qos, "type_description_hash": digest}))
    custom = old_info.get("custom_data") if isinstance(old_info.get("custom_data"), dict) else None
    info = _bag_info(path.name, topics, stats, t_min, t_max, custom)
    state = SimpleNamespace(schemas=[schemas[k] for k in sorted(schemas)],
                            channels=[channels[k] for k in sorted(channels)], chunks=chunks, channel_stats=stats,
                            message_start_time=t_min, message_end_time=t_max)
    summary = _summary(state, info, at)
    cut = 0 if data[at:] == summary else len(data) - at  # before the file shrinks under its map
    with open(path, "r+b") as fh:
        fh.seek(at)
        fh.truncate()
        fh.write(summary)
        fh.flush()
        os.fsync(fh.fileno())
    with atomic_path(meta_path) as tmp:
        Path(tmp).write_text(_dump_yaml({"rosbag2_bagfile_information": info}), encoding="utf-8")
    with contextlib.suppress(FileNotFoundError):
        (folder / "metadata.yaml.tmp").unlink()  # what a kill inside rosbags' own close leaves
    return Reindexed(path, count, len(chunks), cut, True)


def _reads(folder: Path) -> bool:
    """Whether the rosbags reader opens the bag and reads its every message."""
    try:
        with _rosbags().Reader(folder) as reader:
            return sum(1 for _ in reader.messages()) == reader.message_count
    except Exception:  # noqa: BLE001 - any failure of the reader: not readable as it is
        return False
