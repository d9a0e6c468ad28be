"""RosbagSink and the PointCloud2 layouts: the bag read back with an independent reader (the `mcap`
reader with mcap-ros2's CDR decoder, not rosbags, which wrote it) and a PointCloud2 decoder written
here from the sensor_msgs/PointField definition."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

pytest.importorskip("rosbags")
pytest.importorskip("mcap_ros2")
from mcap.reader import make_reader  # noqa: E402
from mcap.records import Channel, Message  # noqa: E402
from mcap.stream_reader import StreamReader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

from scube_sim.boxes import Box  # noqa: E402
from scube_sim.errors import InputError  # noqa: E402
from scube_sim.io.ros2_points import PointLayout, pack_points  # noqa: E402
from scube_sim.lidar.model import POINT_DTYPE  # noqa: E402
from scube_sim.sim.frame import Frame, SensorFrame  # noqa: E402
from scube_sim.sim.sinks import CallbackSink, RunInfo, SinkError, SinkRunner  # noqa: E402
from scube_sim.sim.sinks.rosbag import RosbagSink  # noqa: E402
from scube_sim.transforms import pose_from_xyz_rpy  # noqa: E402

START = 12.5  # host seconds of the first tick
TICK = 0.05  # 20 Hz ticks
RATES = {"top": 10.0, "front-left": 30.0}  # slower (no sweep every other tick) and faster than the ticks
TOPIC = {"top": "/lidar/top/points", "front-left": "/lidar/front_left/points"}
MOUNTS = {"top": pose_from_xyz_rpy([0.5, 0, 1.8], [0, 0, 0]),
          "front-left": pose_from_xyz_rpy([2.0, 0.7, 0.6], [0, 5, 30])}
EXTRA_DTYPE = np.dtype(POINT_DTYPE.descr + [("observed", np.bool_), ("confidence", np.float32)])

# sensor_msgs/msg/PointField.msg constants -> little-endian numpy types (our own table, for decoding)
POINTFIELD = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}
# rmw_qos_durability_policy_e (rmw/types.h): what a v8 metadata.yaml stores as 'durability'
RMW_TRANSIENT_LOCAL, RMW_VOLATILE = 1, 2

# autoware_point_types, autowarefoundation/autoware_core commit 2d693b8229147fc81ce4807e630b5bcb7ac625a4
# (2026-08-20): common/autoware_point_types/include/autoware/point_types/types.hpp (the structs;
# offsets are their offsetof) and memory.hpp (is_data_layout_compatible_with_point_xyzirc: >= 6
# fields, the first six checked; ..._xyzircaedt: exactly 10 fields). (name, offset, datatype, count)
AUTOWARE = {
    "autoware_xyzirc": ([("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 12, 2, 1),
                         ("return_type", 13, 2, 1), ("channel", 14, 4, 1)], 16),
    "autoware_xyzircaedt": ([("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 12, 2, 1),
                             ("return_type", 13, 2, 1), ("channel", 14, 4, 1), ("azimuth", 16, 7, 1),
                             ("elevation", 20, 7, 1), ("distance", 24, 7, 1), ("time_stamp", 28, 6, 1)], 32),
}
# ros-drivers/velodyne branch ros2 (04a7ca722eaed13fe902366e0831717e91f9f77a):
# velodyne_pointcloud/src/lib/pointcloudXYZIRT.cpp lists the six fields; DataContainerBase packs
# them with addPointField (offset += size, no padding) and sets point_step to the sum.
VELODYNE = ([("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 12, 7, 1), ("ring", 16, 4, 1),
             ("time", 18, 7, 1)], 22)
# ouster-lidar/ouster-ros branch ros2 (f5c4ef872684c748a018e9343958bc53f95f7845):
# ouster-ros/include/ouster_ros/os_point.h, EIGEN_ALIGN16 struct {PCL_ADD_POINT4D (x y z + pad);
# float intensity; uint32 t; uint16 reflectivity, ring, ambient; uint32 range} -> sizeof 48.
OUSTER = ([("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 16, 7, 1), ("t", 20, 6, 1),
           ("reflectivity", 24, 4, 1), ("ring", 26, 4, 1), ("ambient", 28, 4, 1), ("range", 32, 6, 1)], 48)


def ego_pose(t: float) -> np.ndarray:
    return pose_from_xyz_rpy([100.0 + 8.0 * t, -40.0 + 0.5 * t * t, 0.01 * t], [0.3 * t, 0.0, 20.0 * t])


def make_points(rng, n: int, extra: bool = False) -> np.ndarray:
    p = np.zeros(n, EXTRA_DTYPE if extra else POINT_DTYPE)
    for f in ("x", "y", "z"):
        p[f] = rng.normal(0, 30, n)
    p["intensity"] = rng.random(n) * 1.1  # a little above 1: the uint8 conversion clips
    p["ring"] = rng.integers(0, 128, n)
    p["time"] = np.sort(rng.random(n)) * 0.09
    p["range"] = np.sqrt(p["x"].astype(np.float64) ** 2 + p["y"] ** 2 + p["z"] ** 2)
    p["azimuth"] = np.arctan2(p["y"], p["x"])  # (-pi, pi]
    p["label"] = rng.integers(-1, 26, n)
    p["instance"] = rng.integers(0, 1 << 20, n)
    p["column"] = rng.integers(0, 2048, n)
    p["return_id"] = rng.integers(0, 2, n)
    if extra:
        p["observed"] = rng.random(n) < 0.5
        p["confidence"] = rng.random(n)
    return p


def make_boxes(t: float, k: int) -> list[Box]:
    boxes = [Box.on_ground(pose_from_xyz_rpy([110.0 + 5 * t, -38.0, 0.0], [0, 0, 40.0 * t]), [4.5, 1.9, 1.6],
                           label=1, instance=3, track_id="car-3"),
             Box.on_ground(pose_from_xyz_rpy([95.0, -45.0, 0.0], [0, 0, 90.0]), [0.6, 0.6, 1.8], label=7, instance=9)]
    return boxes[: 1 + k % 2]  # one or two boxes: the DELETEALL must clear a vanished one


def make_frames(rng, n_ticks: int = 12, extra: bool = False) -> list[Frame]:
    """Ticks at 20 Hz; 'top' at 10 Hz (none every other tick), 'front-left' at 30 Hz (one or two per
    tick); one empty sweep."""
    frames, sweep_no = [], {s: 0 for s in RATES}
    for i in range(n_ticks):
        t = START + TICK * i
        sensors = {}
        for name, rate in RATES.items():
            group = []
            while START - 0.04 + (sweep_no[name] + 1) / rate <= t + 1e-12:
                k = sweep_no[name]
                t_end = START - 0.04 + (k + 1) / rate
                t_start, t_ref = t_end - 1 / rate, t_end - 0.5 / rate
                n = 0 if (name == "top" and k == 2) else int(rng.integers(50, 300))
                group.append(SensorFrame(name, "lidar", make_points(rng, n, extra), t_start, t_end, t_ref,
                                         ego_pose(t_ref) @ MOUNTS[name], ego_pose(t_start) @ MOUNTS[name],
                                         ego_pose(t_end) @ MOUNTS[name], k))
                sweep_no[name] += 1
            if group:
                sensors[name] = group
        frames.append(Frame(i, t, ego_pose(t), sensors, make_boxes(t, i)))
    assert any(len(f.sensors.get("front-left", [])) == 2 for f in frames)
    return frames


def run_info() -> RunInfo:
    sensors = {name: {"kind": "lidar", "rate_hz": r, "mount": MOUNTS[name].tolist()} for name, r in RATES.items()}
    sensors["cam"] = {"kind": "camera"}
    return RunInfo(sensors=sensors, origin=np.array([1.0e6, 2.0e6, 30.0]), start_time=START)


def record(folder, frames, fail_after: int | None = None, **options) -> list[Frame]:
    """The frames through a SinkRunner with [RosbagSink, callback]; returns what the callback
    received (fail_after=k: the callback raises on the k-th frame, after the bag wrote it)."""
    got = []

    def collect(frame):
        got.append(frame)
        if fail_after is not None and len(got) == fail_after:
            raise RuntimeError("interrupted")

    runner = SinkRunner([RosbagSink(folder, **options), CallbackSink(collect)], run_info(), maxsize=2)
    runner.start()
    try:
        for f in frames:
            runner.put(f)
    finally:
        runner.close()
    return got


def read_bag(folder) -> dict[str, list]:
    """topic -> [(log_time ns, decoded message)] in log-time order, via mcap + mcap-ros2."""
    (mcap_path,) = folder.glob("*.mcap")
    out: dict[str, list] = {}
    with open(mcap_path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append((message.log_time, decoded))
    return out


def decode_cloud(msg) -> np.ndarray:
    """A PointCloud2 as a structured array, from its fields (our own decoder)."""
    assert msg.height == 1 and not msg.is_bigendian
    data = bytes(msg.data)
    assert len(data) == msg.width * msg.point_step == msg.row_step
    dt = np.dtype({"names": [f.name for f in msg.fields], "offsets": [f.offset for f in msg.fields],
                   "formats": [POINTFIELD[f.datatype] for f in msg.fields], "itemsize": msg.point_step})
    assert all(f.count == 1 for f in msg.fields)
    return np.frombuffer(data, dt, count=msg.width)


def ns(t: float) -> int:
    return int(round(t * 1e9))


def stamp_ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def same_bits(a: np.ndarray, b: np.ndarray) -> None:
    assert a.dtype == b.dtype and a.shape == b.shape
    np.testing.assert_array_equal(a.view(f"u{a.dtype.itemsize}"), b.view(f"u{b.dtype.itemsize}"))


def expected(points: np.ndarray, kind: str) -> dict[str, np.ndarray]:
    """Each output field's values from our points, by the drivers' units (independent of the packer)."""
    f32 = {c: points[c] for c in ("x", "y", "z")}
    driver = not kind.startswith("autoware")
    extras = {c: points[c] for c in ("label", "instance") if driver}
    if driver and "observed" in points.dtype.names:
        extras.update(observed=points["observed"].astype(np.uint8), confidence=points["confidence"])
    t_ns = np.rint(points["time"].astype(np.float64) * 1e9).astype(np.uint32)
    u8 = np.clip(np.rint(points["intensity"].astype(np.float64) * 255), 0, 255)
    if kind == "velodyne":
        return {**f32, "intensity": points["intensity"], "ring": points["ring"], "time": points["time"], **extras}
    if kind == "ouster":
        return {**f32, "intensity": points["intensity"], "t": t_ns, "reflectivity": u8.astype(np.uint16),
                "ring": points["ring"], "ambient": np.zeros(len(points), np.uint16),
                "range": np.rint(points["range"].astype(np.float64) * 1000).astype(np.uint32), **extras}
    base = {**f32, "intensity": u8.astype(np.uint8), "return_type": np.where(points["return_id"] == 0, 1, 2)
            .astype(np.uint8), "channel": points["ring"]}
    if kind == "autoware_xyzirc":
        return base
    az = np.mod(points["azimuth"].astype(np.float64), 2 * np.pi)
    el = np.arctan2(points["z"].astype(np.float64), np.hypot(points["x"], points["y"]))
    return {**base, "azimuth": az.astype(np.float32), "elevation": el.astype(np.float32),
            "distance": points["range"], "time_stamp": t_ns}


@pytest.mark.parametrize("kind", ["scube", "velodyne", "ouster", "autoware_xyzirc", "autoware_xyzircaedt"])
def test_points_decode_to_what_the_callback_received(tmp_path, rng, kind):
    extra = kind != "autoware_xyzircaedt"  # observed / confidence present: kept where allowed
    frames = make_frames(rng, extra=extra)
    got = record(tmp_path / "bag", frames, default_layout=kind)
    bag = read_bag(tmp_path / "bag")
    for name in RATES:
        sweeps = [s for f in got for s in f.sensors.get(name, [])]
        msgs = bag[TOPIC[name]]
        assert len(msgs) == len(sweeps) > 3
        for (log_time, msg), s in zip(msgs, sweeps):
            assert log_time == ns(s.t_end) and stamp_ns(msg.header.stamp) == ns(s.t_start)
            assert msg.header.frame_id == name.replace("-", "_")
            cloud = decode_cloud(msg)
            assert len(cloud) == len(s.points) and msg.is_dense
            if kind == "scube":
                assert cloud.dtype.names == s.points.dtype.names
                for f in s.points.dtype.names:
                    want = s.points[f].astype(np.uint8) if f == "observed" else s.points[f]
                    same_bits(cloud[f].copy(), want)
                continue
            want = expected(s.points, kind)
            assert set(cloud.dtype.names) == set(want), kind
            for f, v in want.items():
                if f in ("azimuth", "elevation"):  # float32 of float64 maths: within one ulp
                    np.testing.assert_allclose(cloud[f], v, rtol=0, atol=1e-6, err_msg=f)
                else:
                    same_bits(cloud[f].copy(), np.asarray(v).astype(cloud.dtype[f]))
                    np.testing.assert_array_equal(cloud[f], v, err_msg=f)  # no wrap-around in the cast


def test_layouts_match_the_drivers_and_autoware_byte_for_byte(tmp_path, rng):
    frames = make_frames(rng, n_ticks=4, extra=True)
    tables = {"velodyne": VELODYNE, "ouster": OUSTER, **AUTOWARE}
    for kind, (fields, step) in tables.items():
        folder = tmp_path / kind
        record(folder, frames, layouts={"top": PointLayout(kind=kind, extras=False), "front-left": kind})
        bag = read_bag(folder)
        msg = bag[TOPIC["top"]][0][1]
        assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == fields, kind
        assert msg.point_step == step, kind
        fl = bag[TOPIC["front-left"]][0][1]  # default extras: appended after the driver's own fields
        if kind in AUTOWARE:
            assert [(f.name, f.offset, f.datatype, f.count) for f in fl.fields] == fields and fl.point_step == step
            assert autoware_compatible(kind, fl.fields)
        else:
            extra = [(f.name, f.offset, f.datatype) for f in fl.fields[len(fields):]]
            assert extra == [("label", step, 3), ("instance", step + 2, 5), ("observed", step + 6, 2),
                             ("confidence", step + 7, 7)]
            assert fl.point_step == step + 11
        # padding bytes (Ouster's 12..16 and 36..48) are zero
        data = np.frombuffer(bytes(msg.data), np.uint8).reshape(-1, step)
        used = np.zeros(step, bool)
        for name, off, dt, _ in fields:
            used[off: off + np.dtype(POINTFIELD[dt]).itemsize] = True
        assert not data[:, ~used].any()


def autoware_compatible(kind: str, fields) -> bool:
    """memory.hpp's checks ported: the field count rule, then name / offset / datatype / count."""
    table, _ = AUTOWARE[kind]
    if kind == "autoware_xyzirc" and len(fields) < 6 or kind == "autoware_xyzircaedt" and len(fields) != 10:
        return False
    return all((f.name, f.offset, f.datatype, f.count) == row for f, row in zip(fields, table))


def test_autoware_layouts_refuse_extra_fields(rng):
    with pytest.raises(ValueError, match="exactly 10 fields"):
        PointLayout(kind="autoware_xyzircaedt", extras=True)
    with pytest.raises(ValueError, match="extra fields"):
        PointLayout(kind="autoware_xyzirc", extras=True)
    # Why: with one more field XYZIRCAEDT's check fails on the count alone.
    packed = pack_points(make_points(rng, 5, extra=True), "autoware_xyzircaedt")
    assert autoware_compatible("autoware_xyzircaedt", packed.fields)
    label = pack_points(make_points(rng, 5), PointLayout(kind="velodyne")).fields[6]
    assert label.name == "label" and not autoware_compatible("autoware_xyzircaedt", packed.fields + [label])


def test_tf_tf_static_clock_and_qos(tmp_path, rng):
    frames = make_frames(rng)
    record(tmp_path / "bag", frames)
    bag = read_bag(tmp_path / "bag")
    tf = bag["/tf"]
    assert [t for t, _ in tf] == [ns(f.time) for f in frames]
    for (_, msg), f in zip(tf, frames):
        (tr,) = msg.transforms
        assert (tr.header.frame_id, tr.child_frame_id) == ("map", "base_link")
        assert stamp_ns(tr.header.stamp) == ns(f.time)
        check_transform(tr.transform, f.ego_pose)
    (static,) = bag["/tf_static"]
    first = min([frames[0].time] + [s.t_start for s in frames[0].sweeps()])
    assert static[0] == ns(first) <= min(t for msgs in bag.values() for t, _ in msgs)
    by_child = {tr.child_frame_id: tr for tr in static[1].transforms}
    assert set(by_child) == {"top", "front_left"}
    for name, child in (("top", "top"), ("front-left", "front_left")):
        assert by_child[child].header.frame_id == "base_link"
        check_transform(by_child[child].transform, MOUNTS[name])
    clock = bag["/clock"]
    assert [t for t, _ in clock] == [ns(f.time) for f in frames]
    assert [stamp_ns(m.clock) for _, m in clock] == [ns(f.time) for f in frames]

    meta = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    qos = {t["topic_metadata"]["name"]: yaml.safe_load(t["topic_metadata"]["offered_qos_profiles"])
           for t in meta["topics_with_message_count"]}
    (latched,) = qos["/tf_static"]
    assert latched["durability"] == RMW_TRANSIENT_LOCAL and latched["depth"] == 1
    assert all(q[0]["durability"] == RMW_VOLATILE for t, q in qos.items() if t != "/tf_static")


def check_transform(tr, pose) -> None:
    np.testing.assert_array_equal([tr.translation.x, tr.translation.y, tr.translation.z], pose[:3, 3])
    q = np.array([tr.rotation.w, tr.rotation.x, tr.rotation.y, tr.rotation.z])
    w, x, y, z = q / np.linalg.norm(q)
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    np.testing.assert_allclose(r, pose[:3, :3], atol=1e-12)


def test_metadata_lists_topics_types_and_counts(tmp_path, rng):
    from rosbags.rosbag2 import Reader

    frames = make_frames(rng)
    record(tmp_path / "bag", frames, boxes=["markers", "detections"], compression="zstd")
    meta = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 8 and meta["storage_identifier"] == "mcap"
    assert meta["relative_file_paths"] == ["bag.mcap"] and (tmp_path / "bag" / "bag.mcap").is_file()
    n_sweeps = {name: sum(len(f.sensors.get(name, [])) for f in frames) for name in RATES}
    want = {TOPIC["top"]: ("sensor_msgs/msg/PointCloud2", n_sweeps["top"]),
            TOPIC["front-left"]: ("sensor_msgs/msg/PointCloud2", n_sweeps["front-left"]),
            "/tf": ("tf2_msgs/msg/TFMessage", len(frames)), "/tf_static": ("tf2_msgs/msg/TFMessage", 1),
            "/clock": ("rosgraph_msgs/msg/Clock", len(frames)),
            "/boxes": ("visualization_msgs/msg/MarkerArray", len(frames)),
            "/detections": ("vision_msgs/msg/Detection3DArray", len(frames))}
    got = {t["topic_metadata"]["name"]: (t["topic_metadata"]["type"], t["message_count"])
           for t in meta["topics_with_message_count"]}
    assert got == want
    assert meta["message_count"] == sum(c for _, c in want.values())
    assert all(t["topic_metadata"]["type_description_hash"].startswith("RIHS01_")
               for t in meta["topics_with_message_count"])
    assert meta["custom_data"]["scube_sim.start_time"] == repr(START)
    bag = read_bag(tmp_path / "bag")  # zstd chunks read back too
    assert {t: len(m) for t, m in bag.items()} == {t: c for t, (_, c) in want.items()}
    with Reader(tmp_path / "bag") as reader:  # and rosbags' own reader agrees
        assert {c.topic: c.msgcount for c in reader.connections} == {t: c for t, (_, c) in want.items()}


def test_boxes_as_markers_and_detections(tmp_path, rng):
    frames = make_frames(rng, n_ticks=5)
    record(tmp_path / "bag", frames, boxes=["markers", "detections"], world_frame="odom")
    bag = read_bag(tmp_path / "bag")
    for (t, arr), (_, det), f in zip(bag["/boxes"], bag["/detections"], frames):
        assert t == ns(f.time)
        clear, *cubes = arr.markers
        assert clear.action == 3 and len(cubes) == len(f.boxes)  # DELETEALL, then the tick's boxes
        assert det.header.frame_id == "odom" and len(det.detections) == len(f.boxes)
        for m, d, b in zip(cubes, det.detections, f.boxes):
            assert m.type == 1 and m.action == 0 and m.header.frame_id == "odom"
            assert stamp_ns(m.header.stamp) == ns(f.time)
            np.testing.assert_array_equal([m.pose.position.x, m.pose.position.y, m.pose.position.z], b.center)
            np.testing.assert_array_equal([m.scale.x, m.scale.y, m.scale.z], b.size)
            q = m.pose.orientation
            assert math.isclose(2 * math.atan2(q.z, q.w), b.yaw, abs_tol=1e-12)
            np.testing.assert_array_equal([d.bbox.size.x, d.bbox.size.y, d.bbox.size.z], b.size)
            assert d.bbox.center.position.x == b.center[0]
            assert d.id == (b.track_id or str(b.instance))
            assert d.results[0].hypothesis.class_id == {1: "car", 7: "pedestrian"}[b.label]


def test_stamp_at_the_reference_instant(tmp_path, rng):
    frames = make_frames(rng, n_ticks=4)
    got = record(tmp_path / "v", frames, default_layout="velodyne", stamp="ref")
    msgs = read_bag(tmp_path / "v")[TOPIC["front-left"]]
    s = [x for f in got for x in f.sensors.get("front-left", [])][1]
    msg = msgs[1][1]
    assert s.t_ref > s.t_start and stamp_ns(msg.header.stamp) == ns(s.t_ref)
    want = (s.points["time"].astype(np.float64) - (s.t_ref - s.t_start)).astype(np.float32)
    same_bits(decode_cloud(msg)["time"].copy(), want)  # negative before t_ref: Velodyne's float allows it
    with pytest.raises(SinkError, match="uint32 nanoseconds after the header stamp"):
        record(tmp_path / "o", frames, default_layout="ouster", stamp="ref")
    assert (tmp_path / "o" / "metadata.yaml").is_file()  # closed after the error


def test_an_interrupted_run_leaves_a_bag_of_the_frames_written(tmp_path, rng):
    frames = make_frames(rng)
    with pytest.raises(SinkError, match="interrupted"):
        record(tmp_path / "bag", frames, fail_after=4)
    bag = read_bag(tmp_path / "bag")
    assert len(bag["/tf"]) >= 4 and len(bag["/clock"]) == len(bag["/tf"])  # each frame complete, in order

    # A killed process: no close(). Each frame ended a chunk, wrote a summary and footer after it
    # and rewrote metadata.yaml (a real SIGKILL: tests/sim/test_rosbag_kill.py).
    sink = RosbagSink(tmp_path / "killed")
    sink.open(run_info())
    for f in frames[:3]:
        sink.write(f)
    meta = yaml.safe_load((tmp_path / "killed" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert counts["/tf"] == 3 and counts["/tf_static"] == 1
    seen: dict[str, int] = {}
    topics: dict[int, str] = {}
    with open(tmp_path / "killed" / "killed.mcap", "rb") as fh:  # a whole MCAP, footer and all
        for rec in StreamReader(fh).records:
            if isinstance(rec, Channel):
                topics[rec.id] = rec.topic
            elif isinstance(rec, Message):
                seen[topics[rec.channel_id]] = seen.get(topics[rec.channel_id], 0) + 1
    assert seen == {k: v for k, v in counts.items() if v}
    assert {k: len(v) for k, v in read_bag(tmp_path / "killed").items()} == seen  # and indexed
    sink.write(frames[3])
    sink.close()
    assert len(read_bag(tmp_path / "killed")["/tf"]) == 4  # closed by rosbags over the last summary


def test_errors_name_the_key(tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(InputError, match="not an empty folder"):
        RosbagSink(tmp_path / "full").open(run_info())
    with pytest.raises(InputError, match=r"topics\['top'\]"):
        RosbagSink(tmp_path / "b", topics={"top": "/lidar/top-1"})
    with pytest.raises(InputError, match="frame_ids"):
        RosbagSink(tmp_path / "b", frame_ids={"top": "/top"})
    with pytest.raises(InputError, match=r"layouts\['rear'\]"):
        RosbagSink(tmp_path / "b", layouts={"rear": "velodyne"}).open(run_info())
    info = run_info()
    del info.sensors["top"]["mount"]
    with pytest.raises(InputError, match="has no 'mount'"):
        RosbagSink(tmp_path / "c").open(info)
    with pytest.raises(InputError, match="time_offset_s"):
        RosbagSink(tmp_path / "d", time_offset_s=-100.0).open(run_info())


def test_the_messages_are_defined_alike_in_humble_and_jazzy():
    from rosbags.typesys import Stores, get_typestore

    humble, jazzy = get_typestore(Stores.ROS2_HUMBLE), get_typestore(Stores.ROS2_JAZZY)
    todo = ["sensor_msgs/msg/PointCloud2", "tf2_msgs/msg/TFMessage", "rosgraph_msgs/msg/Clock",
            "visualization_msgs/msg/MarkerArray"]
    seen = set()
    while todo:  # every type reachable from the ones written
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        # the fields decide the bytes (constants may differ: Jazzy's Marker adds ARROW_STRIP)
        assert humble.fielddefs[name][1] == jazzy.fielddefs[name][1], name
        for _field, (node, detail) in jazzy.fielddefs[name][1]:
            inner = detail[0] if node.value in (3, 4) else (node, detail)
            if inner[0].value == 2:
                todo.append(inner[1])
    assert "sensor_msgs/msg/CompressedImage" in seen  # Marker's texture: in both
