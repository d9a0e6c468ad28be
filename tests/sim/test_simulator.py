"""The simulator loop: instancing, motion, rates, determinism, sinks under stress, chunks, sources."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from scube_sim.io.pointcloud import read_pcd
from scube_sim.labels import label_id
from scube_sim.lidar.config import config_from_dict, load_lidar_config
from scube_sim.mesh import TriangleMesh
from scube_sim.raytrace.tracer import Tracer
from scube_sim.sim.scene import ChunkSet, ChunkSpec, Part, SimScene
from scube_sim.sim.simulator import LidarSensor, Simulator
from scube_sim.sim.sinks import CallbackSink, FileSink, SinkError
from scube_sim.sim.sources import EditedTrajectory, TrajectorySource, track_pose_fn
from scube_sim.transforms import make_pose, pose_from_xyz_rpy, transform_points
from scube_sim.worlds import primitives as pr

WALL = label_id("building")
CAR = label_id("car")


def ring_lidar(columns=360, hz=10.0, elev=(0.0,), name="ring", max_m=200.0, **extra):
    cfg = {"name": name, "pattern": {"type": "spinning", "columns": columns, "rotation_hz": hz,
                                     "channels": {"elevation_deg": list(map(float, elev))}},
           "range": {"min_m": 0.3, "max_m": max_m}}
    cfg.update(extra)
    return config_from_dict(cfg)


def room(half=30.0):
    """Four walls around the origin (inward faces) and a floor at z = -1.5."""
    walls = [pr.box([x, y, 0.0], size, label=WALL) for x, y, size in
             [(half, 0, [0.2, 2 * half, 6]), (-half, 0, [0.2, 2 * half, 6]),
              (0, half, [2 * half, 0.2, 6]), (0, -half, [2 * half, 0.2, 6])]]
    floor = pr.quad([[-half, -half, -1.5], [half, -half, -1.5], [half, half, -1.5], [-half, half, -1.5]],
                    label=label_id("road"))
    return TriangleMesh.concatenate(walls + [floor])


# --- instancing -----------------------------------------------------------------------------


def test_instanced_actor_equals_the_rebuilt_posed_mesh(rng):
    from scube_sim.worlds.street import car

    actor_mesh = car([0.0, 0.0], 0.0, instance=7)
    pose = pose_from_xyz_rpy([12.0, -3.0, 0.2], [2.0, -1.0, 35.0])
    scene = SimScene(static=[Part(Tracer(room()))], actors=[Part(Tracer(actor_mesh), pose=pose, instance=7, label=CAR)])
    posed = TriangleMesh(transform_points(pose, actor_mesh.vertices), actor_mesh.faces, actor_mesh.labels,
                         actor_mesh.instances, actor_mesh.colors)
    reference = Tracer(TriangleMesh.concatenate([room(), posed]))
    o = rng.uniform(-5, 5, (4000, 3)) * [1, 1, 0.2]
    target = np.array([12.0, -3.0, 0.8]) + rng.normal(scale=1.5, size=(4000, 3))
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = scene.trace_world(o, d, 0.0, 100.0)
    b = reference.trace_world(o, d, 0.0, 100.0)
    assert np.array_equal(a.hit, b.hit)
    assert (a.instance == 7).sum() > 500
    np.testing.assert_allclose(a.t[a.hit], b.t[b.hit], rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(a.instance, b.instance)
    np.testing.assert_allclose(a.normals[a.hit], b.normals[b.hit], atol=1e-5)


def test_moving_actor_is_seen_where_it_is_at_each_fire_time():
    # A wall 0.2 m thick, 40 m wide, approaching a static LiDAR at 20 m/s; its front face starts
    # at x = 20 - 0.1. A ray fired at time tau sees the face at x = 19.9 - 20 tau (raw points).
    v = 20.0
    wall = pr.box([0.0, 0.0, 0.0], [0.2, 40.0, 6.0], label=WALL, instance=3)
    times = np.array([0.0, 1.0])
    poses = np.stack([make_pose(None, [20.0, 0.0, 0.0]), make_pose(None, [20.0 - v, 0.0, 0.0])])
    scene = SimScene(actors=[Part(Tracer(wall), pose_fn=track_pose_fn(times, poses), instance=3, label=WALL)])
    lidar = LidarSensor.from_config(ring_lidar(columns=3600), mount=np.eye(4))
    sim = Simulator(scene, [lidar])
    frames = [sim.step(t, np.eye(4)) for t in (0.0, 0.1)]
    p = frames[1].sensors["ring"][0].points
    ahead = np.abs(p["azimuth"]) < np.deg2rad(40)
    assert ahead.sum() > 300 and np.all(p["instance"][ahead] == 3)
    np.testing.assert_allclose(p["x"][ahead], 19.9 - v * p["time"][ahead].astype(np.float64), atol=2e-4)


# --- ego motion, rates, timing -----------------------------------------------------------------


def test_host_driven_pose_pairs_equal_a_pose_function():
    scene = SimScene(static=[Part(Tracer(room()))])
    cfg = ring_lidar(columns=720, elev=(-5.0, 0.0, 5.0))
    poses = {t: pose_from_xyz_rpy([8.0 * t, 0.5 * t, 0.0], [0, 0, 20.0 * t]) for t in np.round(np.arange(0, 0.5, 0.1), 6)}
    traj = TrajectorySource(list(poses), list(poses.values()))
    a = Simulator(scene, [LidarSensor.from_config(cfg, mount=np.eye(4))], seed=3)
    b = Simulator(scene, [LidarSensor.from_config(cfg, mount=np.eye(4))], seed=3)
    fa = [a.step(t, p) for t, p in poses.items()]
    fb = list(b.run(traj, dt=0.1))
    assert len(fa) == len(fb) == 5
    for x, y in zip(fa[1:], fb[1:]):
        px, py = x.sensors["ring"][0].points, y.sensors["ring"][0].points
        assert len(px) == len(py)
        np.testing.assert_allclose(px["range"], py["range"], atol=1e-4)  # float32 ranges


def test_velocity_twist_moves_the_ego():
    scene = SimScene(static=[Part(Tracer(room()))])
    sim = Simulator(scene, [LidarSensor.from_config(ring_lidar(), mount=np.eye(4))])
    sim.step(0.0, np.eye(4))
    f = sim.step(0.1, ego_velocity=[10.0, 0, 0, 0, 0, 0])
    np.testing.assert_allclose(f.ego_pose[:3, 3], [1.0, 0, 0], atol=1e-12)
    s = f.sensors["ring"][0]
    np.testing.assert_allclose(s.pose_start[:3, 3], [0.0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(s.pose_end[:3, 3], [1.0, 0, 0], atol=1e-9)


def test_twist_poses_turn_about_the_twist_axis_and_move_along_the_ego_frame():
    # Against the closed form: after tau seconds the body has turned by |w| tau about w's axis
    # and moved v tau in the end pose's frame (first order), pose = pose_end @ [R(w tau), v tau].
    from scipy.spatial.transform import Rotation

    from scube_sim.sim.simulator import _twist_poses

    pose_end = pose_from_xyz_rpy([5.0, -2.0, 0.3], [3.0, -4.0, 70.0])
    vel = np.array([8.0, 0.5, -0.1, 0.05, -0.02, 0.4])
    times = np.r_[np.linspace(9.8, 10.1, 41), 10.0]
    got = _twist_poses(pose_end, 10.0, vel, times)
    tau = times - 10.0
    delta = np.zeros((len(tau), 4, 4))
    delta[:, :3, :3] = Rotation.from_rotvec(tau[:, None] * vel[3:]).as_matrix()
    delta[:, :3, 3] = tau[:, None] * vel[:3]
    delta[:, 3, 3] = 1.0
    np.testing.assert_allclose(got, np.stack([pose_end @ m for m in delta]), atol=1e-13)
    np.testing.assert_allclose(got[np.argmin(np.abs(tau))], pose_end, atol=1e-15)  # at t_end: the pose
    # no rotation: translation only
    still = _twist_poses(pose_end, 10.0, [1.0, 2.0, 3.0, 0, 0, 0], np.array([10.5]))[0]
    np.testing.assert_allclose(still[:3, :3], pose_end[:3, :3], atol=1e-15)
    np.testing.assert_allclose(still[:3, 3], pose_end[:3, 3] + pose_end[:3, :3] @ [0.5, 1.0, 1.5], atol=1e-12)


def test_each_sensor_sweeps_at_its_own_rate():
    scene = SimScene(static=[Part(Tracer(room()))])
    fast = LidarSensor.from_config(ring_lidar(hz=20.0, name="fast"), mount=np.eye(4))
    slow = LidarSensor.from_config(ring_lidar(hz=5.0, name="slow"), mount=np.eye(4))
    sim = Simulator(scene, [fast, slow])
    frames = [sim.step(t, np.eye(4)) for t in np.round(np.arange(0, 1.0001, 0.1), 6)]
    n_fast = [len(f.sensors.get("fast", [])) for f in frames]
    n_slow = [len(f.sensors.get("slow", [])) for f in frames]
    assert n_fast == [0] + [2] * 10
    assert n_slow == [0, 0, 1, 0, 1, 0, 1, 0, 1, 0, 1]
    # a sweep's timestamp is its end; it covers one period before it
    ends = [s.t_end for f in frames for s in f.sensors.get("fast", [])]
    np.testing.assert_allclose(ends, np.arange(1, 21) * 0.05, atol=1e-9)
    s = frames[4].sensors["slow"][0]
    assert s.t_end - s.t_start == pytest.approx(0.2)
    with pytest.raises(ValueError, match="overlap"):
        LidarSensor.from_config(ring_lidar(hz=10.0), rate_hz=20.0)


def test_same_seed_same_frames_and_boxes():
    from scube_sim.worlds.generator import WorldConfig, generate_world

    w = generate_world(WorldConfig(style="intersection", seed=2, duration_s=1.0))

    def run(seed):
        actors = [Part(Tracer(a.mesh), pose_fn=track_pose_fn(a.times, a.poses), instance=a.instance, label=a.label,
                       size=a.size) for a in w.actors]
        scene = SimScene(static=[Part(Tracer(w.static))], actors=actors, static_boxes=w.boxes_static)
        sensors = [LidarSensor.from_config(load_lidar_config("vlp16"))]
        sim = Simulator(scene, sensors, seed=seed)
        return list(sim.run(TrajectorySource(w.ego_times, w.ego_poses), t_end=0.4))

    a, b, c = run(1), run(1), run(2)
    for fa, fb in zip(a, b):
        assert [s.points.tobytes() for s in fa.sweeps()] == [s.points.tobytes() for s in fb.sweeps()]
        assert [bx.center.tolist() for bx in fa.boxes] == [bx.center.tolist() for bx in fb.boxes]
    assert any(x.points.tobytes() != y.points.tobytes() for fa, fc in zip(a, c) for x, y in zip(fa.sweeps(), fc.sweeps()))
    # actor boxes move between ticks
    moving = {bx.instance for bx in a[0].boxes} & {a_.instance for a_ in w.actors}
    assert moving and any(not np.allclose([b_.center for b_ in a[0].boxes if b_.instance == i],
                                          [b_.center for b_ in a[-1].boxes if b_.instance == i]) for i in moving)


# --- sinks under stress ------------------------------------------------------------------------


def small_sim(sinks, queue_size=2):
    scene = SimScene(static=[Part(Tracer(room()))])
    return Simulator(scene, [LidarSensor.from_config(ring_lidar(columns=90), mount=np.eye(4))], sinks,
                     queue_size=queue_size)


def test_slow_sink_applies_back_pressure_and_loses_nothing():
    got = []
    in_sink = threading.Event()

    def slow(frame):
        in_sink.set()
        time.sleep(0.03)
        got.append(frame.index)

    sim = small_sim([CallbackSink(slow)], queue_size=2)
    t0 = time.perf_counter()
    with sim:
        for i in range(20):
            sim.step(i * 0.1, np.eye(4))
    assert got == list(range(20))  # every frame, in order
    # 20 frames through a sink taking 30 ms each: the loop could not run ahead by more than the queue
    assert time.perf_counter() - t0 >= 20 * 0.03 * 0.9


def test_failing_sink_stops_the_loop_with_its_error():
    written = []

    def boom(frame):
        if frame.index == 3:
            raise OSError("disk full")
        written.append(frame.index)

    sim = small_sim([CallbackSink(boom)], queue_size=1)
    with pytest.raises(SinkError, match="disk full"):
        with sim:
            for i in range(50):
                sim.step(i * 0.1, np.eye(4))
    assert written == [0, 1, 2]


def test_interrupted_run_leaves_complete_files(tmp_path):
    sink = FileSink(tmp_path / "frames", ("pcd", "bin"))
    sim = small_sim([sink], queue_size=4)
    with pytest.raises(KeyboardInterrupt):
        with sim:
            for i in range(30):
                sim.step(i * 0.1, np.eye(4))
                if i == 12:
                    raise KeyboardInterrupt
    lines = (tmp_path / "frames" / "frames.jsonl").read_text().splitlines()
    assert len(lines) == 12  # ticks 1..12 each finished one sweep; tick 0 none
    import json

    for line in lines:
        rec = json.loads(line)
        for f in rec["files"]:
            path = tmp_path / "frames" / f
            assert path.exists()
            if f.endswith(".pcd"):
                assert len(read_pcd(path)) == rec["points"]
    assert not list((tmp_path / "frames").rglob(".*tmp*"))


# --- chunks along a route ----------------------------------------------------------------------


def test_only_chunks_near_the_ego_are_loaded(tmp_path):
    from scube_sim.fit import fit_voxsplat

    specs = []
    for k in range(6):  # six 40 m pieces of ground with a wall, 40 m apart along x
        m = TriangleMesh.concatenate([pr.ground_grid(0, -10, 40, 10, 0.0, 5.0, label=label_id("road"), color=(0.3,) * 3),
                                      pr.box([20, 8, 1.5], [30, 0.3, 3], label=WALL)])
        s = m.sample_surface_grid(0.5)
        vs = fit_voxsplat(s["points"], 1.0, weights=s["weights"], labels=s["labels"], patch_cov=(s["patch_cov"], s["face"]))
        path = tmp_path / f"c{k}.npz"
        vs.save(path)
        specs.append(ChunkSpec(path, make_pose(None, [40.0 * k, 0, 0])))
    chunks = ChunkSet(specs, reach=30.0)
    scene = SimScene(chunks=chunks)
    sim = Simulator(scene, [LidarSensor.from_config(ring_lidar(elev=(-10.0, 0.0), max_m=30.0),
                                                   mount=make_pose(None, [0, 0, 1.0]))])
    loaded = []
    for i, x in enumerate(np.arange(5.0, 230.0, 5.0)):
        f = sim.step(i * 0.1, make_pose(None, [x, 0, 0]))
        loaded.append(len(chunks.loaded))
        if i:
            assert sum(len(s.points) for s in f.sweeps()) > 100  # the ground and the wall are seen
    assert max(loaded) <= 3 and chunks.loads >= 6
    assert chunks.loaded[-1] == 5


# --- pose sources ------------------------------------------------------------------------------


def test_edited_trajectory_lane_change_speed_and_shift():
    times = np.arange(0, 10.01, 0.5)
    poses = np.stack([make_pose(None, [10.0 * t, 0, 0]) for t in times])
    base = TrajectorySource(times, poses)
    e = EditedTrajectory(base, lateral_offset_m=3.5, lateral_ramp=(2.0, 4.0), speed_scale=1.5, time_shift=1.0)
    p = e.poses_at(np.array([0.0, 2.0, 3.0, 4.0, 5.0]))
    # base time = 0 + t * 1.5 + 1 -> x = 10 * (1.5 t + 1)
    np.testing.assert_allclose(p[:, 0, 3], 10 * (1.5 * np.array([0, 2, 3, 4, 5]) + 1))
    np.testing.assert_allclose(p[:, 1, 3], [0, 0, 1.75, 3.5, 3.5], atol=1e-12)
    assert e.t_end == pytest.approx((10 - 1) / 1.5)


def test_trajectory_files(tmp_path):
    kitti = tmp_path / "poses.txt"
    rows = [np.eye(4)[:3].ravel(), make_pose(None, [1.0, 2.0, 3.0])[:3].ravel()]
    np.savetxt(kitti, rows)
    src = TrajectorySource.from_file(kitti, rate_hz=10.0)
    np.testing.assert_allclose(src.pose_at(0.05)[:3, 3], [0.5, 1.0, 1.5])
    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 3\n")
    with pytest.raises(ValueError, match="bad.txt: expected 12 numbers"):
        TrajectorySource.from_file(bad)
    with pytest.raises(ValueError, match="strictly increasing"):
        TrajectorySource([0.0, 0.0], [np.eye(4), np.eye(4)])


@pytest.mark.parametrize("output", ["raw", "compensated"])
def test_ego_at_20_mps_skews_a_wall_and_compensation_removes_it(output):
    """Host-driven at 20 m/s towards a wall 30 m ahead: a ray fired tau seconds into the sweep
    sees the wall (30 - 0.1) - x_ego(tau) ahead; compensated output puts every point back in the
    sensor frame at the sweep start, where the wall is a plane."""
    v = 20.0
    wall = pr.box([30.0, 0.0, 0.0], [0.2, 80.0, 10.0], label=WALL)
    cfg = ring_lidar(columns=3600, motion={"output": output, "reference": "start"})
    sim = Simulator(SimScene(static=[Part(Tracer(wall))]), [LidarSensor.from_config(cfg, mount=np.eye(4))])
    sim.step(0.0, np.eye(4))
    f = sim.step(0.1, make_pose(None, [v * 0.1, 0, 0]))
    s = f.sensors["ring"][0]
    p = s.points
    ahead = np.abs(p["azimuth"]) < np.deg2rad(30)
    tau = p["time"][ahead].astype(np.float64)
    want = 29.9 - v * tau if output == "raw" else np.full(tau.shape, 29.9)
    np.testing.assert_allclose(p["x"][ahead], want, atol=2e-4)
    np.testing.assert_allclose(s.pose_start[:3, 3], [0, 0, 0], atol=1e-12)
