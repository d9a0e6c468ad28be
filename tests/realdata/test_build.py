"""Real-LiDAR -> VoxSplat building and the fidelity metrics, against analytic scenes.

Synthetic "real" sweeps come from the LiDAR model on exact meshes (a flat ground and walls), so
the truth at any other pose is an analytic ray-plane intersection.
"""

from __future__ import annotations

import numpy as np

from scube_sim.boxes import Box, points_in_boxes
from scube_sim.datasets.base import LidarSpec, LidarSweep, Sample
from scube_sim.lidar.config import load_lidar_config
from scube_sim.lidar.model import Lidar
from scube_sim.mesh import TriangleMesh
from scube_sim.raytrace.tracer import Tracer
from scube_sim.realdata.build import (
    BuildOptions,
    accumulate,
    build_voxsplat,
    free_space_mask,
    grow_to_objects,
    height_above_ground,
    range_image_mesh,
)
from scube_sim.realdata.fidelity import (
    RealRays,
    SimRays,
    compare,
    poisson_mesh,
    real_rays,
    simulate_rays,
    voxel_cube_mesh,
)
from scube_sim.transforms import make_pose
from scube_sim.worlds import primitives as pr

H = 1.8  # sensor height above the ground, metres


def ground(z=-H, half=60.0):
    return pr.quad([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])


def quiet(name="HDL-32E"):
    """A preset without noise or drops: synthetic sweeps are exact."""
    cfg = load_lidar_config(name)
    return cfg.model_copy(update={
        "noise": cfg.noise.model_copy(update={"range_sigma_m": 0.0, "quantization_m": 0.0}),
        "drop": cfg.drop.model_copy(update={"max_incidence_deg": 90.0}), "ego_body": None})


def synthetic_sweep(mesh: TriangleMesh, pose: np.ndarray, cfg=None, name="lidar") -> LidarSweep:
    out = Lidar(cfg or quiet()).scan(Tracer(mesh), pose)
    p = np.stack([out.points["x"], out.points["y"], out.points["z"]], 1).astype(np.float64)
    return LidarSweep(name, p, pose, 0.0, out.points["intensity"].astype(np.float32), 1.0,
                      out.points["ring"].astype(np.int16))


def sample_of(sweep, boxes=()):
    return Sample("s", sweep.timestamp, sweep.sensor_to_world, sweeps=[sweep], boxes=list(boxes),
                  lidars={sweep.sensor: None})


# --- meshing the range image -----------------------------------------------------------------

def test_range_image_mesh_covers_the_ground_but_never_bridges_a_depth_jump():
    scene = TriangleMesh.concatenate([ground(), pr.box([6.0, 0.0, -H + 0.75], [1.0, 1.0, 1.5])])
    sw = synthetic_sweep(scene, make_pose())
    faces = range_image_mesh(sw.points)
    assert len(faces) > 0.8 * len(sw)  # a grid has about two triangles per point
    on_box = np.all(np.abs(sw.points[:, :2] - [6.0, 0.0]) <= 0.5 + 1e-6, axis=1) & (sw.points[:, 2] > -H + 1e-3)
    mixed = on_box[faces].any(1) & ~on_box[faces].all(1)
    # A triangle with corners on the box and on the ground must be short (the box's foot),
    # never one spanning the shadow behind the box.
    tri = sw.points[faces[mixed]]
    longest = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
    assert np.all(longest <= 2.0)  # the shadow behind the box is 30 m deep
    # Every kept ground triangle lies on the ground plane.
    g = faces[~on_box[faces].any(1)]
    assert np.allclose(sw.points[g][..., 2], -H, atol=1e-6)


# --- build, then replay at a novel pose -------------------------------------------------------

def test_voxsplat_from_one_sweep_reproduces_the_ground_and_a_wall_at_a_novel_pose():
    scene = TriangleMesh.concatenate([ground(), pr.quad([[20, -30, -H], [20, 30, -H], [20, 30, 6], [20, -30, 6]])])
    pose_a = make_pose(translation=[0.0, 0.0, 0.0])
    sw_a = synthetic_sweep(scene, pose_a)
    acc = accumulate([sample_of(sw_a)])
    vs, rep = build_voxsplat(acc, voxel_size=0.1)
    assert rep.gaussians > 0 and vs.num_voxels > 0
    # Novel pose: 0.5 m ahead, 0.3 m to the side. Truth: analytic planes z = -H and x = 20.
    pose_b = make_pose(translation=[0.5, 0.3, 0.0])
    sw_b = synthetic_sweep(scene, pose_b)
    rays = real_rays(sw_b)
    d = rays.directions
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(d[:, 2] < 0, -H / d[:, 2], np.inf)
        t_wall = np.where(d[:, 0] > 0, (20.0 - 0.5) / d[:, 0], np.inf)
        t_wall[np.abs(0.3 + t_wall * d[:, 1]) > 30.0] = np.inf  # past the wall's ends
    truth = np.minimum(t_ground, t_wall)
    assert np.allclose(rays.range[rays.hit], truth[rays.hit], atol=1e-5)  # exact up to float32 points
    # Only rays landing where sweep A saw a surface are expected back: not inside A's blind disc
    # under the car (its lowest ring meets the ground 3.0 m out), not in the last ring gap before
    # the wall's foot, and within 15 m: ground rings 1.33 deg apart seen from 1.8 m are r^2 x
    # 0.0232 / 1.8 apart, over the mesh's 0.2 r edge limit beyond 15.5 m.
    p = d * np.where(rays.hit, rays.range, 0)[:, None] + [0.5, 0.3, 0.0]
    on_wall = np.abs(p[:, 0] - 20.0) < 1e-3
    seen_ground = (np.hypot(p[:, 0], p[:, 1]) > 3.5) & (p[:, 0] < 15.5)
    near = rays.hit & (on_wall | (seen_ground & (truth < 15.0)))
    sim = simulate_rays(Tracer(vs, mode="max_response"), quiet(), rays, sw_b)
    m = compare(rays, sim, mask=near)
    assert m["hit_agreement"] > 0.98
    assert m["median_abs_m"] < 0.01
    assert m["p90_abs_m"] < 0.05


# --- reflectance ---------------------------------------------------------------------------------

def test_reflectance_measured_by_one_sensor_gives_another_its_own_intensities_at_a_novel_pose():
    """A wall at x = 12 m whose left half (y > 0) has reflectance 0.8 and right half 0.2, over a
    ground of 0.1. The "real" HDL-32E reports, by its manual and measured exponent, 100/255 x rho x
    cos^0.22 (written here by hand from the planes' normals); the build must recover rho, and a
    VLS-128 (110/255 x rho x cos) sweeping the scene from elsewhere must read its own scale."""
    wall_x = 12.0
    scene = TriangleMesh.concatenate([ground(), pr.quad([[wall_x, -15, -H], [wall_x, 15, -H], [wall_x, 15, 5],
                                                         [wall_x, -15, 5]])])
    cfg = quiet("HDL-32E").model_copy(update={"mount": load_lidar_config("VLP-16").mount})  # level mount
    sw = synthetic_sweep(scene, make_pose(), cfg)
    p = sw.points
    r = np.linalg.norm(p, axis=1)
    on_wall = np.abs(p[:, 0] - wall_x) < 1e-4
    cos = np.where(on_wall, np.abs(p[:, 0]), np.abs(p[:, 2])) / r  # normals +x and +z
    rho = np.where(on_wall, np.where(p[:, 1] > 0, 0.8, 0.2), 0.1)
    sw.intensity = (100 / 255 * rho * cos ** 0.22).astype(np.float32)
    sample = Sample("s", 0.0, make_pose(), sweeps=[sw], lidars={sw.sensor: LidarSpec(sw.sensor, cfg, np.eye(4))})
    vs, rep = build_voxsplat(accumulate([sample]), voxel_size=0.1)
    assert rep.reflectance == len(sw)
    g = vs.means()[vs.valid]
    est = vs.channel("reflectance")[vs.valid]
    # Away from the seam (triangles there average both halves), the wall's ends and the corner
    # at its foot (the range-image mesh bridges the last ground ring and the wall's lowest), and
    # within the meshed ground (beyond ~15 m the rings are too far apart: lone returns there are
    # read with their neighbourhood's normal, which one ring leaves uncertain).
    wall_g = (np.abs(g[:, 0] - wall_x) < 0.05) & (np.abs(g[:, 1]) > 0.5) & (g[:, 2] > -H + 0.5) & (np.abs(g[:, 1]) < 14)
    ground_g = (np.abs(g[:, 2] + H) < 0.05) & (g[:, 0] < wall_x - 2.0) & (np.hypot(g[:, 0], g[:, 1]) < 14)
    assert wall_g.sum() > 500 and ground_g.sum() > 500
    # float32 intensities and points: a few 1e-4 of relative error.
    np.testing.assert_allclose(est[wall_g], np.where(g[wall_g, 1] > 0, 0.8, 0.2), rtol=2e-3)
    assert np.mean(np.abs(est[ground_g] / 0.1 - 1) < 2e-3) > 0.999  # but a few lone returns
    # A VLS-128 1 m ahead and 2 m to the left: its own gain and the Lambertian cosine.
    pose_b = make_pose(translation=[1.0, 2.0, 0.0])
    vls = quiet("VLS-128").model_copy(update={"mount": cfg.mount})
    out = Lidar(vls).scan(Tracer(vs, mode="max_response"), pose_b).points
    q = np.stack([out["x"], out["y"], out["z"]], 1).astype(np.float64)
    rq = np.linalg.norm(q, axis=1)
    world_y = q[:, 1] + 2.0
    sel = (np.abs(q[:, 0] - (wall_x - 1.0)) < 0.01) & (np.abs(world_y) > 0.5) & (q[:, 2] > -H + 0.5) & (np.abs(world_y) < 14)
    assert sel.sum() > 1000
    want = 110 / 255 * np.where(world_y[sel] > 0, 0.8, 0.2) * np.abs(q[sel, 0]) / rq[sel]
    np.testing.assert_allclose(out["intensity"][sel], want, rtol=5e-3)


# --- moving objects ----------------------------------------------------------------------------

def test_free_space_carving_grows_to_the_whole_car_and_spares_the_scene():
    wall = pr.quad([[15, -30, -H], [15, 30, -H], [15, 30, 5], [15, -30, 5]])
    car_a = pr.box([8.0, 3.0, -H + 0.8], [4.5, 1.9, 1.6])
    car_b = pr.box([11.0, 3.0, -H + 0.8], [4.5, 1.9, 1.6])  # 3 m further on in sweep B
    sw_a = synthetic_sweep(TriangleMesh.concatenate([ground(), wall, car_a]), make_pose())
    sw_b = synthetic_sweep(TriangleMesh.concatenate([ground(), wall, car_b]), make_pose(translation=[0.5, 0, 0]))
    p = sw_a.world_points()
    on_car = np.all(np.abs(p - [8.0, 3.0, -H + 0.8]) <= [2.25 + 1e-6, 0.95 + 1e-6, 0.8 + 1e-6], axis=1)
    on_car &= p[:, 2] > -H + 1e-3
    seeds = free_space_mask(p, sw_b)
    assert seeds.any() and np.all(on_car[seeds])  # only car points are seen through
    grown = grow_to_objects(p, seeds, ground_height=0.3)
    # The whole car above the ground band (its lowest 0.3 m is not told apart from the road;
    # the seeds there stay), nothing else.
    assert np.array_equal(grown, (on_car & (p[:, 2] > -H + 0.3)) | seeds)


def test_height_above_ground_follows_a_slope():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-20, 20, (20000, 2))
    z = 0.05 * xy[:, 0]  # a 5 % slope
    pole = np.c_[np.zeros(50), np.zeros(50), np.linspace(0.5, 3.0, 50)]
    p = np.vstack([np.c_[xy, z], pole])
    h = height_above_ground(p)
    assert np.percentile(h[:20000], 99) < 0.12  # a 1 m cell on a 5 % slope: up to ~0.1 m
    assert np.allclose(h[20000:], pole[:, 2], atol=0.12)


def test_boxes_select_and_remove_points():
    box = Box(np.array([5.0, 0, 0]), np.array([4.0, 2.0, 1.5]), np.eye(3), category="car", label=1, velocity=np.array([3.0, 0, 0]))
    yaw = np.deg2rad(90)
    rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    turned = Box(np.array([-5.0, 0, 0]), np.array([4.0, 2.0, 1.5]), rot, category="car", label=1, velocity=np.zeros(3))
    pts = np.array([[6.9, 0.9, 0.7], [7.1, 0, 0], [-5.0, 1.9, 0], [-3.9, 0, 0], [0, 0, 0]])
    assert list(points_in_boxes(pts, [box, turned])) == [0, -1, 1, -1, -1]
    assert list(points_in_boxes(pts, [box, turned], margin=0.15)) == [0, 0, 1, 1, -1]
    # remove="dynamic" drops the moving box's points only; the parked one's keep its label.
    sw = LidarSweep("l", pts[:3] + [0, 0, 0], make_pose(), 0.0)
    opts = BuildOptions(samples=[0], min_range=0.0, remove="dynamic", mesh=False)
    acc = accumulate([sample_of(sw, [box, turned])], opts)
    assert len(acc) == 1 and acc.removed == 2 and acc.labels[0] == 1


# --- rays, metrics, baselines -------------------------------------------------------------------

def test_full_grid_no_returns_get_their_ring_and_column_directions():
    rings, cols = 8, 90
    el = np.deg2rad(np.linspace(-20, 5, rings))
    az = np.deg2rad(np.arange(cols) * 4.0 - 178.0)
    E, A = np.meshgrid(el, az)  # (cols, rings): column-major firing order, rings inside
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    r = np.full(len(d), 10.0)
    miss = np.zeros(len(d), bool)
    miss[::7] = True
    pts = d * r[:, None]
    pts[miss] = [0.0, -0.45, -0.01]  # a no-return stored after motion compensation
    sw = LidarSweep("grid", pts, make_pose(), 0.0, ring=np.tile(np.arange(rings), cols).astype(np.int16))
    rays = real_rays(sw)
    assert rays.no_returns_known and len(rays) == len(d)
    assert np.array_equal(~rays.hit, miss)
    ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", rays.directions, d), -1, 1)))
    assert ang.max() < 1e-5


def test_compare_metrics_by_hand():
    d = np.tile([1.0, 0, 0], (4, 1))
    d[1] = [0, 1, 0]
    d[2] = [0, -1, 0]
    d[3] = [-1, 0, 0]
    rays = RealRays(d, np.array([10.0, 10.0, 10.0, np.inf]), np.zeros(4), np.array([0.2, 0.4, 0.6, np.nan]),
                    np.zeros(4, int), np.arange(4), 1, 4, True)
    sim = SimRays(np.array([10.01, 10.1, np.inf, 5.0]), np.array([0.3, 0.5, np.nan, 0.1]), np.zeros(4, np.int16))
    m = compare(rays, sim)
    assert m["both_return"] == 2 and m["hit_agreement"] == 0.5 and m["false_returns"] == 1.0
    assert np.isclose(m["median_abs_m"], 0.055) and np.isclose(m["p90_abs_m"], 0.01 + 0.9 * 0.09)
    # Clouds: real {(10,0,0), (0,10,0), (0,-10,0)}, sim {(10.01,0,0), (0,10.1,0), (-5,0,0)}.
    d_sr = [0.01, 0.1, np.hypot(5, 10)]
    d_rs = [0.01, 0.1, np.hypot(5, 10)]
    assert np.isclose(m["chamfer_m"], 0.5 * (np.mean(d_sr) + np.mean(d_rs)))
    assert np.isclose(m["fscore_5cm"], 1 / 3)  # precision 1/3, recall 1/3
    assert np.isclose(m["fscore_20cm"], 2 / 3)
    assert np.isnan(m["intensity_r"])  # two rays: no correlation to speak of
    assert np.isclose(m["intensity_rmse"], 0.1)  # |0.3 - 0.2| and |0.5 - 0.4| on the two both return
    n = 20
    rays5 = RealRays(np.tile([1.0, 0, 0], (n, 1)), np.full(n, 10.0), np.zeros(n), np.linspace(0.1, 0.9, n),
                     np.zeros(n, int), np.arange(n), 1, n, True)
    sim5 = SimRays(np.full(n, 10.0), 0.5 * np.linspace(0.1, 0.9, n) + 0.1, np.zeros(n, np.int16))
    assert np.isclose(compare(rays5, sim5)["intensity_r"], 1.0)


def test_voxel_cube_baseline_is_hit_on_the_cube_face():
    mesh = voxel_cube_mesh(np.array([[5.05, 0.05, 0.05], [5.07, 0.01, 0.02]]), 0.1)
    assert mesh.num_faces == 12  # one voxel
    h = Tracer(mesh).trace(np.array([[0.0, 0.05, 0.05]]), np.array([[1.0, 0, 0]]))
    assert h.hit[0] and np.isclose(h.t[0], 5.0)


def test_poisson_baseline_recovers_a_sphere():
    rng = np.random.default_rng(3)
    n = rng.normal(size=(6000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    mesh = poisson_mesh(2.0 * n, n, depth=7)
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert np.percentile(np.abs(r - 2.0), 95) < 0.03


# --- motion --------------------------------------------------------------------------------------

def test_raw_sweep_replayed_with_the_motion_model_equals_the_measurement():
    wall = pr.quad([[20, -40, -10], [20, 40, -10], [20, 40, 10], [20, -40, 10]])
    v = np.array([10.0, 2.0, 0.0])  # m/s

    def pose_fn(t):
        t = np.atleast_1d(t)
        out = np.tile(np.eye(4), (len(t), 1, 1))
        out[:, :3, 3] = t[:, None] * v
        return out

    cfg = quiet("VLP-16")
    meas = Lidar(cfg.model_copy(update={"motion": cfg.motion.model_copy(update={"output": "raw"})})).scan(
        Tracer(wall), make_pose(), pose_fn=pose_fn, t_start=0.0)
    p = np.stack([meas.points["x"], meas.points["y"], meas.points["z"]], 1).astype(np.float64)
    t = meas.points["time"].astype(np.float64)
    raw = LidarSweep("vlp", p, pose_fn(np.array([0.0]))[0], 0.0, time_offset=t, motion_compensated=False,
                     pose_fn=pose_fn)
    comp = raw.compensated()
    assert np.allclose(comp.world_points(), raw.world_points(), atol=1e-9)
    assert np.allclose(np.abs(raw.world_points()[:, 0] - 20.0), 0, atol=1e-4)  # all on the wall
    back = comp.raw()
    assert np.allclose(back.points, raw.points, atol=1e-9)
    rays = real_rays(raw)
    with_model = simulate_rays(Tracer(wall), cfg, rays, raw, distortion=True)
    without = simulate_rays(Tracer(wall), cfg, rays, raw, distortion=False)
    assert np.allclose(with_model.range, rays.range, atol=1e-4)
    # Without the model the sensor stands at the sweep-start pose: it is v * t further away.
    expect = rays.range + v[0] * rays.time / rays.directions[:, 0]
    hit = without.hit  # a few rays near the wall's ends now pass it
    assert hit.mean() > 0.99
    assert np.allclose(without.range[hit], expect[hit], atol=1e-4)
    assert np.max(np.abs(without.range[hit] - rays.range[hit])) > 0.5
