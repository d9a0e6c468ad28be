"""The simulated scene against closed forms: rays through posed and moving parts hit the planes
analytic geometry says, culling drops no hit a brute-force trace finds, boxes sit where the pose
puts them, and a bare tracer wrapped for the simulator traces exactly as itself."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.boxes import Box
from scube_sim.labels import label_id
from scube_sim.lidar.config import config_from_dict
from scube_sim.lidar.model import Lidar
from scube_sim.raytrace.tracer import Tracer
from scube_sim.sim.contracts import SimulatedScene
from scube_sim.sim.scene import Part, SimScene, StaticScene, as_simulated_scene
from scube_sim.sim.simulator import LidarSensor, Simulator
from scube_sim.sim.sources import track_pose_fn
from scube_sim.transforms import invert_pose, pose_from_xyz_rpy
from scube_sim.worlds import primitives as pr

WALL = label_id("building")
CAR = label_id("car")


def _yaw_pose(x, y, yaw_rad, z=0.0):
    return pose_from_xyz_rpy([x, y, z], [0.0, 0.0, np.degrees(yaw_rad)])


def _wall_tracer():
    """A wall 0.2 m thick, 40 m wide, 6 m high, centred on its frame's origin: its front face is
    the plane x = -0.1 of the part frame."""
    return Tracer(pr.box([0.0, 0.0, 0.0], [0.2, 40.0, 6.0], label=WALL))


@pytest.mark.parametrize("moving", [False, True])
def test_rays_hit_a_posed_or_moving_wall_on_its_analytic_plane(rng, moving):
    # Wall centre c(tau) and yaw theta(tau): linear in the fire time tau for the moving wall
    # (two track samples; SLERP about z is linear in yaw), fixed for the posed one. A ray
    # o + s d meets the front plane n . p = n . c - 0.1, n = (cos theta, sin theta, 0), at
    # s = (n . c - 0.1 - n . o) / (n . d), and sees the normal -n.
    c0, c1 = np.array([15.0, -2.0, 0.0]), np.array([25.0, 3.0, 0.0])
    th0, th1 = np.radians(-10.0), np.radians(15.0)
    if moving:
        fn = track_pose_fn([0.0, 1.0], [_yaw_pose(*c0[:2], th0), _yaw_pose(*c1[:2], th1)])
        part = Part(_wall_tracer(), pose_fn=fn, instance=9, label=WALL)
    else:
        part = Part(_wall_tracer(), pose=_yaw_pose(*c0[:2], th0), instance=9, label=WALL)
    scene = SimScene(actors=[part])
    n_rays = 400
    tau = rng.uniform(0.0, 1.0, n_rays)
    phi = np.radians(rng.uniform(-15.0, 15.0, n_rays))
    o = np.column_stack([rng.uniform(-1, 1, n_rays), rng.uniform(-1, 1, n_rays), rng.uniform(-1, 1, n_rays)])
    d = np.column_stack([np.cos(phi), np.sin(phi), np.zeros(n_rays)])
    h = scene.trace_world(o, d, 0.0, 100.0, times=tau)

    c = c0 + tau[:, None] * (c1 - c0) if moving else np.broadcast_to(c0, (n_rays, 3))
    th = th0 + tau * (th1 - th0) if moving else np.full(n_rays, th0)
    n = np.column_stack([np.cos(th), np.sin(th), np.zeros(n_rays)])
    want = (np.einsum("ij,ij->i", n, c) - 0.1 - np.einsum("ij,ij->i", n, o)) / np.einsum("ij,ij->i", n, d)
    assert h.hit.all()
    np.testing.assert_allclose(h.t, want, atol=1e-4)
    np.testing.assert_allclose(h.points, o + want[:, None] * d, atol=1e-4)
    np.testing.assert_allclose(h.normals, -n, atol=1e-5)
    assert np.all(h.instance == 9) and np.all(h.label == WALL)  # the mesh has no instance: the part's


def test_rays_fired_without_times_see_moving_parts_at_the_scene_time():
    # A wall moving at 10 m/s along x from x = 20: at scene time 0.5 its face is at 25 - 0.1.
    fn = track_pose_fn([0.0, 1.0], [_yaw_pose(20.0, 0.0, 0.0), _yaw_pose(30.0, 0.0, 0.0)])
    scene = SimScene(actors=[Part(_wall_tracer(), pose_fn=fn)])
    scene.update(0.5)
    h = scene.trace_world(np.zeros((1, 3)), [[1.0, 0.0, 0.0]])
    assert h.hit[0] and h.t[0] == pytest.approx(24.9, abs=1e-4)


def _brute_force(parts, o, d, tmax, times):
    """Nearest hit over parts without any culling: every ray into every part's frame (by the
    inverse pose matrix at its fire time), traced there."""
    best = np.full(len(o), np.inf)
    inst = np.zeros(len(o), np.int64)
    for part in parts:
        inv = np.stack([invert_pose(p) for p in part.poses_at(times)])
        o_l = np.einsum("nij,nj->ni", inv[:, :3, :3], o) + inv[:, :3, 3]
        d_l = np.einsum("nij,nj->ni", inv[:, :3, :3], d)
        h = part.tracer.trace_world(o_l, d_l, 0.0, tmax)
        take = h.hit & (h.t < best)
        best[take] = h.t[take]
        inst[take] = part.instance
    return best, inst


def test_bounding_sphere_culling_drops_no_hit(rng):
    # Small boxes, off-centre in their frames (so rotation moves their spheres), static and
    # moving; rays from all around aimed near them, with short and long range limits.
    parts = [
        Part(Tracer(pr.box([1.0, 0.5, 0.0], [1.0, 2.0, 1.5])), pose=_yaw_pose(8.0, 3.0, 0.4), instance=1),
        Part(Tracer(pr.box([0.0, 0.0, 0.0], [4.0, 1.8, 1.5])), pose=_yaw_pose(-6.0, -4.0, -1.0), instance=2),
        Part(Tracer(pr.box([0.5, -0.5, 0.2], [4.5, 2.0, 1.6])), instance=3,
             pose_fn=track_pose_fn([0.0, 0.1], [_yaw_pose(0.0, 8.0, 0.2), _yaw_pose(2.0, 8.5, 0.5)])),
        Part(Tracer(pr.box([0.0, 0.0, 0.0], [0.6, 0.6, 1.8])), instance=4,
             pose_fn=track_pose_fn([0.0, 0.1], [_yaw_pose(3.0, -7.0, 0.0), _yaw_pose(2.8, -6.0, 1.5)])),
    ]
    scene = SimScene(static=parts[:2], actors=parts[2:])
    n_rays = 3000
    o = rng.uniform(-15.0, 15.0, (n_rays, 3)) * [1.0, 1.0, 0.1]
    centres = np.array([[8.0, 3.0, 0.0], [-6.0, -4.0, 0.0], [1.0, 8.2, 0.0], [2.9, -6.5, 0.0]])
    target = centres[rng.integers(0, 4, n_rays)] + rng.normal(scale=2.0, size=(n_rays, 3))
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tmax = rng.uniform(2.0, 40.0, n_rays)
    times = rng.uniform(0.0, 0.1, n_rays)
    h = scene.trace_world(o, d, 0.0, tmax, times=times)
    want_t, want_inst = _brute_force(parts, o, d, tmax, times)
    hit = np.isfinite(want_t)
    assert hit.sum() > 500 and (~hit).sum() > 200 and len(np.unique(want_inst[hit])) == 4
    np.testing.assert_array_equal(h.hit, hit)
    np.testing.assert_allclose(h.t[hit], want_t[hit], rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(h.instance[hit], want_inst[hit])


def _old_sphere_cull(part, o, d, tmin, tmax, times):
    """The per-ray bounding-sphere test, written out: each ray's own origin against the part's
    sphere (moving parts: around the centre's path between the batch's first and last time)."""
    centre, radius = part.sphere()
    if part.moving:
        ends = part.poses_at(np.array([times.min(), times.max()]))
        c_ends = np.stack([p[:3, :3] @ centre + p[:3, 3] for p in ends])
        c, r = c_ends.mean(axis=0), radius + 0.5 * np.linalg.norm(c_ends[1] - c_ends[0])
    else:
        p = np.eye(4) if part.pose is None else part.pose
        c, r = p[:3, :3] @ centre + p[:3, 3], radius
    oc = c - o
    along = (oc * d).sum(axis=1)
    perp2 = (oc * oc).sum(axis=1) - along * along
    return (perp2 <= r * r) & (along + r >= tmin) & (along - r <= tmax)


def _spin_rays(rng, n_cols=720, rings=16, centre=(0.0, 0.0, 1.8), spread=0.5):
    """A spinning LiDAR's rays in firing order (column by column) from origins spread over a
    short path: o (N, 3), unit d (N, 3)."""
    az = np.repeat(np.linspace(-np.pi, np.pi, n_cols, endpoint=False), rings)
    el = np.tile(np.radians(np.linspace(-20.0, 5.0, rings)), n_cols)
    d = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    o = np.asarray(centre) + np.column_stack([np.linspace(0.0, spread, len(az)), np.zeros(len(az)),
                                              np.zeros(len(az))])
    return o, d


@pytest.mark.parametrize("layout", ["sweep", "sweep_far_limits", "random"])
def test_the_cull_keeps_every_ray_the_per_ray_sphere_test_keeps(rng, layout):
    # Blocks of directions and the origins' ball against the per-ray test written out, part by
    # part; the rays left out must be ones the per-ray test leaves out.
    from scube_sim.sim.scene import _RayBatch

    parts = []
    for k in range(10):
        size = rng.uniform(0.5, 5.0, 3)
        at = rng.uniform(-40.0, 40.0, 2)
        if k % 2:
            parts.append(Part(Tracer(pr.box([0.3, 0.0, 0.5], size)), pose=_yaw_pose(*at, rng.uniform(-3, 3))))
        else:
            fn = track_pose_fn([0.0, 0.1], [_yaw_pose(*at, 0.2), _yaw_pose(*(at + rng.normal(size=2)), 0.6)])
            parts.append(Part(Tracer(pr.box([0.3, 0.0, 0.5], size)), pose_fn=fn))
    if layout == "random":
        o = rng.uniform(-20.0, 20.0, (4000, 3))
        d = rng.normal(size=(4000, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
    else:
        o, d = _spin_rays(rng)
    n = len(o)
    tmin = np.zeros(n) if layout != "random" else rng.uniform(0.0, 3.0, n)
    tmax = np.full(n, 120.0) if layout == "sweep" else rng.uniform(1.0, 60.0, n)
    times = np.linspace(0.0, 0.1, n)
    batch = _RayBatch(o, d, tmin, tmax, times)
    best_t = np.where(rng.random(n) < 0.3, rng.uniform(1.0, 50.0, n), np.inf)  # hits found by earlier parts
    engaged = 0
    for part in parts:
        want = _old_sphere_cull(part, o, d, tmin, np.minimum(tmax, best_t), times)
        got = batch.near(part, best_t)
        kept = np.zeros(n, bool)
        if got is not None:
            assert np.all(np.diff(got) > 0)  # ascending, no repeats
            kept[got] = True
        assert not np.any(want & ~kept)
        if part.moving:  # moving parts: exactly the per-ray test's rays
            np.testing.assert_array_equal(kept, want)
        engaged += kept.sum() < n
    assert engaged >= 5  # the cull left rays out for most parts


def test_a_sweep_through_a_street_of_actors_equals_the_brute_force_trace(rng):
    # LiDAR-like rays in firing order (the block cull engages), a ground part that every
    # downward ray reaches (the dense path), and static and moving boxes around: nearest hits as
    # every ray traced through every part without culling.
    ground = Part(Tracer(pr.box([0.0, 0.0, -0.05], [200.0, 200.0, 0.1])), instance=0)
    actors, static = [], [ground]
    for k in range(12):
        at = rng.uniform(-30.0, 30.0, 2)
        size = rng.uniform(1.0, 4.5, 3)
        if k % 3 == 0:
            static.append(Part(Tracer(pr.box([0.0, 0.0, size[2] / 2], size)), pose=_yaw_pose(*at, rng.uniform(-3, 3)),
                               instance=100 + k))
        else:
            fn = track_pose_fn([0.0, 0.05, 0.1], [_yaw_pose(*at, 0.0), _yaw_pose(*(at + [0.5, 0.2]), 0.1),
                                                  _yaw_pose(*(at + [1.0, 0.1]), 0.3)])
            actors.append(Part(Tracer(pr.box([0.0, 0.0, size[2] / 2], size)), pose_fn=fn, instance=100 + k))
    scene = SimScene(static=static, actors=actors)
    o, d = _spin_rays(rng, n_cols=900, rings=16, spread=1.5)
    tmax = np.full(len(o), 80.0)
    times = np.linspace(0.0, 0.1, len(o))
    h = scene.trace_world(o, d, 0.0, tmax, times=times)
    want_t, want_inst = _brute_force(static + actors, o, d, tmax, times)
    hit = np.isfinite(want_t)
    assert len(np.unique(want_inst[hit])) >= 8 and (~hit).sum() > 1000
    np.testing.assert_array_equal(h.hit, hit)
    np.testing.assert_allclose(h.t[hit], want_t[hit], rtol=1e-12, atol=1e-9)
    np.testing.assert_array_equal(h.instance[hit], want_inst[hit])
    np.testing.assert_allclose(h.points[hit], o[hit] + want_t[hit, None] * d[hit], atol=1e-9)
    assert np.all(np.isnan(h.points[~hit]))


def test_bounding_sphere_holds_every_vertex_of_the_part():
    mesh = pr.box([3.0, -1.0, 2.0], [1.0, 6.0, 0.5], yaw=0.3)
    centre, radius = Part(Tracer(mesh)).sphere()
    world = mesh.vertices + mesh.origin
    assert np.all(np.linalg.norm(world - centre, axis=1) <= radius + 1e-9)
    # ... and is the sphere around the (slightly padded) axis-aligned bounds: its diameter is
    # their diagonal
    diagonal = np.linalg.norm(world.max(0) - world.min(0))
    assert diagonal <= 2 * radius <= diagonal + 1e-3
    np.testing.assert_allclose(centre, 0.5 * (world.max(0) + world.min(0)), atol=1e-9)


def test_boxes_sit_on_the_ground_under_the_part_pose():
    # Footprint centre at (x, y, z) with yaw psi: the box centre is h / 2 above it, its yaw psi.
    size = np.array([4.5, 1.9, 1.6])
    fn = track_pose_fn([0.0, 2.0], [_yaw_pose(10.0, 0.0, 0.2, z=0.3), _yaw_pose(30.0, 4.0, 0.6, z=0.3)])
    actor = Part(Tracer(pr.box([0, 0, 0.8], size)), pose_fn=fn, instance=5, label=CAR, size=size)
    parked = Box([1.0, 2.0, 0.75], [4.0, 1.8, 1.5], np.eye(3), label=CAR, instance=2)
    scene = SimScene(actors=[actor], static_boxes=[parked])
    boxes = scene.boxes_at(0.5)
    assert boxes[0] is parked and len(boxes) == 2
    b = boxes[1]
    assert isinstance(b, Box) and b.instance == 5 and b.label == CAR
    np.testing.assert_allclose(b.center, [15.0, 1.0, 0.3 + 0.8], atol=1e-12)
    np.testing.assert_array_equal(b.size, size)
    assert b.yaw == pytest.approx(0.3, abs=1e-12)
    assert b.to_json() == {"instance": 5, "label": CAR, "center": pytest.approx([15.0, 1.0, 1.1], abs=1e-12),
                           "size": [4.5, 1.9, 1.6], "yaw": pytest.approx(0.3, abs=1e-12)}
    # held at the ends of the track
    np.testing.assert_allclose(scene.boxes_at(5.0)[1].center, [30.0, 4.0, 1.1], atol=1e-12)
    # a part without a size has a zero-size box at its footprint
    assert np.array_equal(Part(Tracer(pr.box([0, 0, 0], [1, 1, 1])), pose=_yaw_pose(1.0, 2.0, 0.0)).box_at(0.0).center,
                          [1.0, 2.0, 0.0])


def test_a_bare_tracer_is_wrapped_without_changing_a_hit(rng):
    tracer = _wall_tracer()
    assert not isinstance(tracer, SimulatedScene)
    wrapped = as_simulated_scene(tracer)
    assert isinstance(wrapped, StaticScene) and isinstance(wrapped, SimulatedScene)
    scene = SimScene(static=[Part(tracer)])
    assert as_simulated_scene(scene) is scene
    with pytest.raises(TypeError, match="SimulatedScene"):
        as_simulated_scene(object())
    wrapped.update(3.0, np.zeros(3))
    assert wrapped.time == 3.0 and wrapped.boxes_at(3.0) == [] and wrapped.accepts_times is False

    o = rng.normal(size=(500, 3))
    d = rng.normal(size=(500, 3)) + [3.0, 0.0, 0.0]  # not unit: passed on as given
    a, b = tracer.trace_world(o, d, 0.0, 50.0), wrapped.trace_world(o, d, 0.0, 50.0)
    for name in ("hit", "t", "points", "normals", "label", "instance"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))

    # a whole sweep through the simulator equals the LiDAR's own sweep of the bare tracer
    cfg = config_from_dict({"name": "ring", "pattern": {"type": "spinning", "columns": 360, "rotation_hz": 10.0,
                                                         "channels": {"elevation_deg": [-2.0, 0.0, 2.0]}},
                            "range": {"min_m": 0.3, "max_m": 100.0}})
    pose = _yaw_pose(-10.0, 0.0, 0.0)
    sim = Simulator(tracer, [LidarSensor(Lidar(cfg), mount=np.eye(4))], seed=5)
    sim.step(0.0, pose)
    sweep = sim.step(0.1, pose).sensors["ring"][0]
    seed = int(np.random.SeedSequence([5, 0, 1]).generate_state(1)[0])  # the simulator's per-sweep seed
    bare = Lidar(cfg).scan(tracer, None, pose_fn=lambda ts: np.broadcast_to(pose, (len(ts), 4, 4)), t_start=0.0,
                           seed=seed)
    assert len(sweep.points) > 100
    assert sweep.points.tobytes() == bare.points.tobytes()


def test_a_list_of_tracers_is_traced_nearest_hit_first():
    near = Tracer(pr.box([10.0, 0.0, 0.0], [0.2, 10.0, 4.0]))
    far = Tracer(pr.box([20.0, 0.0, 0.0], [0.2, 10.0, 4.0]))
    h = as_simulated_scene([far, near]).trace_world(np.zeros((1, 3)), [[1.0, 0.0, 0.0]], 0.0, 100.0)
    assert h.hit[0] and h.t[0] == pytest.approx(9.9, abs=1e-5)
