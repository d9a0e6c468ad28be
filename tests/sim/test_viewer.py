"""ViewerSink: the Foxglove MCAP read back with the `mcap` reader and the published Foxglove
protobuf classes (not the sink's own decoder), counts and values equal to what was written; and a
short simulated run through it, which also draws docs/viewer_recording.png when run as a script:

    .venv/bin/python -m tests.sim.test_viewer
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("foxglove_schemas_protobuf")
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms  # noqa: E402
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud  # noqa: E402
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate  # noqa: E402
from mcap.reader import make_reader  # noqa: E402

from scube_sim.errors import InputError  # noqa: E402
from scube_sim.labels import LABELS  # noqa: E402
from scube_sim.sim.sinks import CallbackSink, SinkError, SinkRunner  # noqa: E402
from scube_sim.sim.sinks.viewer import ViewerSink, plot_bev, read_recording  # noqa: E402

from .test_rosbag import make_frames, ns, run_info  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
# foxglove.PackedElementField.NumericType (foxglove/schemas PackedElementField.proto)
NUMERIC = {1: "u1", 2: "i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<f4", 8: "<f8"}
CLASSES = {"foxglove.PointCloud": PointCloud, "foxglove.SceneUpdate": SceneUpdate,
           "foxglove.FrameTransforms": FrameTransforms}


def record(path, frames, fail_after=None, **options) -> list:
    got = []

    def collect(frame):
        got.append(frame)
        if fail_after is not None and len(got) == fail_after:
            raise RuntimeError("interrupted")

    runner = SinkRunner([ViewerSink(path, **options), CallbackSink(collect)], run_info(), maxsize=2)
    runner.start()
    try:
        for f in frames:
            runner.put(f)
    finally:
        runner.close()
    return got


def read(path) -> dict[str, list]:
    """topic -> [(log_time, message)] via the mcap reader and foxglove_schemas_protobuf."""
    out: dict[str, list] = {}
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages(log_time_order=True):
            assert schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
            out.setdefault(channel.topic, []).append((message.log_time, CLASSES[schema.name].FromString(message.data)))
    return out


def decode(msg: PointCloud) -> np.ndarray:
    dt = np.dtype({"names": [f.name for f in msg.fields], "offsets": [f.offset for f in msg.fields],
                   "formats": [NUMERIC[f.type] for f in msg.fields], "itemsize": msg.point_stride})
    assert len(msg.data) % msg.point_stride == 0
    return np.frombuffer(msg.data, dt)


def test_recording_reads_back_with_what_was_written(tmp_path, rng):
    frames = make_frames(rng)
    got = record(tmp_path / "run.mcap", frames)
    rec = read(tmp_path / "run.mcap")
    assert set(rec) == {"/lidar/top", "/lidar/front_left", "/boxes", "/tf"}
    colours = {lab.id: lab.color for lab in LABELS}
    for name, topic in (("top", "/lidar/top"), ("front-left", "/lidar/front_left")):
        sweeps = [s for f in got for s in f.sensors.get(name, [])]
        assert len(rec[topic]) == len(sweeps)
        for (t, msg), s in zip(rec[topic], sweeps):
            assert t == ns(s.t_end) and msg.timestamp.seconds * 10**9 + msg.timestamp.nanos == ns(s.t_ref)
            assert msg.frame_id == "map"
            np.testing.assert_array_equal([msg.pose.position.x, msg.pose.position.y, msg.pose.position.z],
                                          s.pose[:3, 3])
            pts = decode(msg)
            assert len(pts) == len(s.points)
            for f in ("x", "y", "z", "intensity", "label", "ring", "instance", "time"):
                np.testing.assert_array_equal(pts[f], s.points[f], err_msg=f)
            want = np.array([colours.get(int(v), (128, 128, 128)) for v in s.points["label"]]).reshape(-1, 3)
            np.testing.assert_array_equal(np.stack([pts["red"], pts["green"], pts["blue"]], 1), want)
            assert np.all(pts["alpha"] == 255)
    assert [t for t, _ in rec["/boxes"]] == [ns(f.time) for f in frames]
    for (_, upd), f in zip(rec["/boxes"], frames):
        assert [d.type for d in upd.deletions] == [SceneUpdate().deletions.add(type=1).type]
        assert len(upd.entities) == len(f.boxes) and all(len(e.cubes) == 1 for e in upd.entities)
        for e, b in zip(upd.entities, f.boxes):
            c = e.cubes[0]
            np.testing.assert_array_equal([c.size.x, c.size.y, c.size.z], b.size)
            np.testing.assert_array_equal([c.pose.position.x, c.pose.position.y, c.pose.position.z], b.center)
            assert {kv.key: kv.value for kv in e.metadata}["instance"] == str(b.instance)
    for (_, tfs), f in zip(rec["/tf"], frames):
        ego, *mounts = tfs.transforms
        assert (ego.parent_frame_id, ego.child_frame_id) == ("map", "base_link")
        np.testing.assert_array_equal([ego.translation.x, ego.translation.y, ego.translation.z], f.ego_pose[:3, 3])
        assert sorted(m.child_frame_id for m in mounts) == ["front_left", "top"]
    with open(tmp_path / "run.mcap", "rb") as fh:  # the summary's statistics agree
        stats = make_reader(fh).get_summary().statistics
    assert stats.message_count == sum(len(v) for v in rec.values())

    # The sink's own decoder (used for the PNG) agrees with the independent one.
    mine = read_recording(tmp_path / "run.mcap")
    assert [len(c[3]) for c in mine.clouds["/lidar/top"]] == [len(decode(m)) for _, m in rec["/lidar/top"]]
    assert [len(s) for _, s in mine.scenes] == [len(f.boxes) for f in frames]
    s0 = [s for f in got for s in f.sensors.get("top", [])][0]
    world = mine.clouds["/lidar/top"][0][1]
    xyz = np.stack([s0.points[c] for c in "xyz"], 1).astype(np.float64)
    np.testing.assert_allclose(world, xyz @ s0.pose[:3, :3].T + s0.pose[:3, 3], atol=1e-6)


def test_an_interrupted_run_is_finished(tmp_path, rng):
    frames = make_frames(rng)
    with pytest.raises(SinkError, match="interrupted"):
        record(tmp_path / "run.mcap", frames, fail_after=3)
    rec = read(tmp_path / "run.mcap")
    assert len(rec["/boxes"]) >= 3 and len(rec["/tf"]) == len(rec["/boxes"])


def test_errors(tmp_path):
    with pytest.raises(InputError, match="boxes_topic"):
        ViewerSink(tmp_path / "a.mcap", boxes_topic="boxes")
    with pytest.raises(InputError, match="is a folder"):
        ViewerSink(tmp_path).open(run_info())
    with pytest.raises(InputError, match="time_offset_s"):
        ViewerSink(tmp_path / "b.mcap", time_offset_s=-1e3).open(run_info())


# ------------------------------------------------------------------ a simulated run
def simulated_run(path: Path, ticks: int = 3) -> list:
    """A street, two moving cars, an HDL-32E-like ring on a car driving along x at 8 m/s; the
    frames go to a ViewerSink at `path`. Returns the frames."""
    from scube_sim.labels import label_id
    from scube_sim.lidar.config import load_lidar_config
    from scube_sim.raytrace.tracer import Tracer
    from scube_sim.sim.scene import Part, SimScene
    from scube_sim.sim.simulator import LidarSensor, Simulator
    from scube_sim.sim.sources import track_pose_fn
    from scube_sim.transforms import pose_from_xyz_rpy
    from scube_sim.worlds.street import car, street_scene

    def track(x0, y, v, yaw_deg):
        times = np.array([0.0, 2.0])
        return track_pose_fn(times, np.stack([pose_from_xyz_rpy([x0 + v * t, y, 0.0], [0, 0, yaw_deg]) for t in times]))

    actors = [Part(Tracer(car([0.0, 0.0], 0.0, instance=11)), pose_fn=track(4.0, -2.0, 10.0, 0.0), instance=11,
                   label=label_id("car"), size=np.array([4.5, 1.8, 1.5])),
              Part(Tracer(car([0.0, 0.0], 0.0, instance=12, color=(0.1, 0.3, 0.7))),
                   pose_fn=track(20.0, 2.0, -6.0, 180.0), instance=12, label=label_id("car"),
                   size=np.array([4.5, 1.8, 1.5]))]
    scene = SimScene(static=[Part(Tracer(street_scene(80.0)))], actors=actors)
    mount = pose_from_xyz_rpy([0.0, 0, 1.9], [0, 0, 0])
    lidar = LidarSensor.from_config(load_lidar_config("hdl32e"), "top", mount=mount)
    frames = []
    with Simulator(scene, [lidar], [ViewerSink(path)]) as sim:
        for i in range(ticks):
            t = 0.1 * (i + 1)
            frames.append(sim.step(t, pose_from_xyz_rpy([-10.0 + 8.0 * t, 0.0, 0.0], [0, 0, 0])))
    return frames


def test_a_simulated_run_records_and_plots(tmp_path):
    frames = simulated_run(tmp_path / "sim.mcap")
    rec = read(tmp_path / "sim.mcap")
    sweeps = [s for f in frames for s in f.sensors.get("top", [])]
    assert [len(decode(m)) for _, m in rec["/lidar/top"]] == [len(s.points) for s in sweeps]
    assert sum(len(s.points) for s in sweeps) > 10_000
    assert [len(u.entities) for _, u in rec["/boxes"]] == [len(f.boxes) for f in frames] == [2] * len(frames)
    labels = np.concatenate([decode(m)["label"] for _, m in rec["/lidar/top"]])
    assert {1, 14, 18} <= set(labels.tolist())  # cars, buildings and road seen
    png = plot_bev(tmp_path / "sim.mcap", tmp_path / "bev.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


if __name__ == "__main__":  # the README picture
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        run = Path(d) / "viewer.mcap"
        simulated_run(run)
        out = plot_bev(run, REPO / "docs" / "viewer_recording.png", extent=(-32.0, 28.0, -12.0, 12.0))
    print(out)
