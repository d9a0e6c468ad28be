"""The LiDAR model against analytic scenes: planes, walls, edges, boxes and moving sensors."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.labels import LABEL_REFLECTIVITY, label_id
from scube_sim.lidar.config import config_from_dict, load_lidar_config
from scube_sim.lidar.model import POINT_DTYPE, Lidar
from scube_sim.mesh import TriangleMesh
from scube_sim.raytrace.tracer import Tracer
from scube_sim.transforms import make_pose, pose_from_xyz_rpy
from scube_sim.voxsplat import Gaussians, VoxSplat
from scube_sim.worlds import primitives as pr

from ..raytrace.engines import ENGINES, core_of

WALL = label_id("building")


def spinning(elev, columns=360, hz=10.0, **extra):
    cfg = {"name": "test", "pattern": {"type": "spinning", "columns": columns, "rotation_hz": hz,
                                       "channels": {"elevation_deg": list(map(float, elev))}},
           "range": {"min_m": 0.3, "max_m": 200.0}}
    for key, val in extra.items():
        if key in cfg and isinstance(val, dict):
            cfg[key].update(val)
        else:
            cfg[key] = val
    return config_from_dict(cfg)


def emitter(az, el, t=None, **extra):
    pat = {"type": "emitter", "azimuth_deg": list(map(float, az)), "elevation_deg": list(map(float, el))}
    if t is not None:
        pat["time_s"] = list(map(float, t))
    cfg = {"name": "emit", "pattern": pat, "range": {"min_m": 0.3, "max_m": 200.0}}
    cfg.update(extra)
    return config_from_dict(cfg)


def wall_x(x, half=200.0, label=WALL, instance=0):
    """A wall at the plane x = const facing -x (towards a sensor at the origin)."""
    c = [[x, -half, -half], [x, -half, half], [x, half, half], [x, half, -half]]
    return pr.quad(c, label=label, instance=instance)


def plane_of_gaussians(x=10.0, half_y=14.0, half_z=6.0, spacing=0.1, sigma_n=1e-3):
    ys, zs = np.meshgrid(np.arange(-half_y, half_y + 1e-9, spacing), np.arange(-half_z, half_z + 1e-9, spacing))
    n = ys.size
    means = np.c_[np.full(n, x), ys.ravel(), zs.ravel()]
    scales = np.tile([sigma_n, spacing / 2, spacing / 2], (n, 1))  # identity rotation: x is the normal
    return Gaussians(means, scales, np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.99), np.zeros((n, 3), np.float32))


# --- geometry --------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ENGINES)
def test_plane_of_gaussians_at_10m_matches_the_plane_within_noise(name):
    g = plane_of_gaussians()
    sigma = 0.02
    cfg = spinning(np.linspace(-15, 15, 16), columns=720, noise={"range_sigma_m": sigma},
                   intensity={"source": "constant"})
    sweep = Lidar(cfg).scan(Tracer(g, "max_response", core=core_of(name)), np.eye(4), seed=3)
    p = sweep.points
    front = np.abs(p["azimuth"]) < np.deg2rad(40)
    assert front.sum() > 1000
    d = np.stack([np.cos(p["azimuth"]) * np.cos(np.arcsin(p["z"] / p["range"])), p["y"], p["z"]], 1)
    el = np.arcsin(np.clip(p["z"] / p["range"], -1, 1))
    expected = 10.0 / (np.cos(p["azimuth"]) * np.cos(el))
    res = (p["range"] - expected)[front]
    assert abs(res.mean()) < 3 * sigma / np.sqrt(front.sum()) + 1e-3
    assert res.std() == pytest.approx(sigma, rel=0.1)
    del d


@pytest.mark.parametrize("mode,offset", [("max_response", 0.0), ("entry", 3e-3)])
def test_plane_depth_definitions(mode, offset):
    g = plane_of_gaussians(sigma_n=1e-3)
    cfg = spinning(np.linspace(-10, 10, 9), columns=360)
    p = Lidar(cfg).scan(Tracer(g, mode=mode), np.eye(4)).points
    front = np.abs(p["azimuth"]) < np.deg2rad(35)
    # the point lies on x = 10 - offset (entry: the 3-sigma skin in front of the plane); the max-
    # response point of an oblique ray leaves the plane by at most (sigma_n / sigma_t)^2 * u * tan
    # (u <= 0.1 m from the mean): 4e-4 * 0.1 * 0.7 = 3e-5 m here.
    x = p["x"][front]
    if mode == "max_response":
        np.testing.assert_allclose(x, 10.0, atol=5e-5)
    else:
        # the skin is 3 sigma_n thick at a disc's centre and thins towards its rim
        assert np.all((x >= 10.0 - offset - 1e-5) & (x <= 10.0 + 1e-5))
        assert np.median(x) == pytest.approx(10.0 - offset, abs=2e-4)


def test_scene_far_from_the_origin_gives_the_same_sweep():
    g = plane_of_gaussians(half_y=8, half_z=4, spacing=0.2, sigma_n=0.01)
    rng = np.random.default_rng(0)
    g.means += rng.normal(scale=0.02, size=g.means.shape)
    vs0 = VoxSplat.from_gaussians(g, 0.4)
    far = np.array([1.0e6, -2.0e6, 1.0e6 / 3])
    g_far = Gaussians(g.means, g.scales, g.quats, g.opacities, g.sh_dc, origin=far)
    vs1 = VoxSplat.from_gaussians(g_far, 0.4)  # world coordinates near 1e6 m, kept in float64
    assert np.abs(vs1.origin - far).max() < 20  # a voxel-aligned origin near the data
    cfg = load_lidar_config("vlp16")
    pose0 = pose_from_xyz_rpy([0.5, 0.3, 0.2], [1.0, -2.0, 3.0])
    pose1 = pose0.copy()
    pose1[:3, 3] += far
    s0 = Lidar(cfg).scan(Tracer(vs0), pose0, seed=1)
    s1 = Lidar(cfg).scan(Tracer(vs1), pose1, seed=1)
    assert len(s0) > 500 and len(s0) == len(s1)
    np.testing.assert_allclose(s1.xyz(), s0.xyz(), atol=1e-3)


# --- motion ----------------------------------------------------------------------------------


@pytest.mark.parametrize("output", ["raw", "compensated"])
def test_motion_distortion_of_a_wall_at_20_mps(output):
    v = 20.0
    cfg = spinning([0.0], columns=3600, hz=10.0, motion={"output": output})
    lidar = Lidar(cfg)
    start = np.eye(4)
    end = make_pose(None, [v * 0.1, 0, 0])  # 2 m over the 0.1 s sweep
    sweep = lidar.scan(Tracer(wall_x(30.0)), start, end)
    p = sweep.points
    ahead = np.abs(p["azimuth"]) < np.deg2rad(30)
    assert ahead.sum() > 200
    t = p["time"][ahead].astype(np.float64)
    # Raw: each point is seen from where the sensor is at its fire time, 30 - v t metres away.
    want = 30.0 - v * t if output == "raw" else np.full(t.shape, 30.0)
    np.testing.assert_allclose(p["x"][ahead], want, atol=2e-4)
    if output == "raw":
        # The points ahead come from both ends of the sweep (cw spin: azimuth 0 at t=0 and t=T):
        assert np.ptp(p["x"][ahead]) > 1.5


def test_pose_function_equals_start_end_interpolation():
    cfg = spinning(np.linspace(-10, 10, 8), columns=720)
    lidar = Lidar(cfg)
    scene = Tracer(TriangleMesh.concatenate([wall_x(15.0), pr.box([0, 12, 0], [40, 1, 20], label=WALL)]))
    start = pose_from_xyz_rpy([0, 0, 0], [0, 0, 0])
    end = pose_from_xyz_rpy([1.5, 0.2, 0], [0, 0, 20])
    from scube_sim.transforms import interpolate_poses

    def fn(times):
        return interpolate_poses(start, end, (np.asarray(times) - 5.0) / 0.1)

    a = lidar.scan(scene, start, end, t_start=5.0)
    b = lidar.scan(scene, None, pose_fn=fn, t_start=5.0)
    np.testing.assert_allclose(b.xyz(), a.xyz(), atol=1e-6)


def _wavy_pose(t):
    """An analytic sensor path that is no SLERP: (N,) absolute seconds -> (N, 4, 4)."""
    t = np.atleast_1d(np.asarray(t, np.float64))
    yaw = 0.3 * np.sin(20.0 * t)
    out = np.zeros((t.shape[0], 4, 4))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    out[:, 2, 2] = out[:, 3, 3] = 1.0
    out[:, 0, 3], out[:, 1, 3], out[:, 2, 3] = 4.0 * t - 12.0, 0.5 * np.cos(30.0 * t), 0.2
    return out


@pytest.mark.parametrize("output", ["raw", "compensated"])
def test_pulses_fired_together_share_one_pose_and_every_point_is_where_its_own_pose_puts_it(output):
    # Channels fire in pairs (0 and 5 us): the pose function is asked once per distinct fire
    # time. Independent check: each raw point, moved to the world by the analytic pose at its own
    # fire time, lies on the wall x = 15; each compensated one, by the reference pose.
    cfg = spinning([-6.0, -2.0, 2.0, 6.0], columns=400, motion={"output": output, "reference": "start"},
                   pattern={"channels": {"elevation_deg": [-6.0, -2.0, 2.0, 6.0],
                                         "fire_time_us": [0.0, 5.0, 0.0, 5.0]}})
    lidar = Lidar(cfg)
    asked = []

    def fn(times):
        asked.append(np.array(times))
        return _wavy_pose(times)

    t0 = 3.0
    sweep = lidar.scan(Tracer(wall_x(15.0, half=60.0)), None, pose_fn=fn, t_start=t0)
    fire = t0 + lidar.pattern.time
    assert len(asked) == 2 and np.array_equal(asked[1], np.unique(fire))  # the ends, then each time once
    assert len(asked[1]) == len(fire) // 2
    p = sweep.points
    assert len(p) > 300
    xyz = sweep.xyz().astype(np.float64)
    poses = _wavy_pose(t0 + p["time"].astype(np.float64)) if output == "raw" else _wavy_pose([t0])
    world = np.einsum("nij,nj->ni", poses[:, :3, :3], xyz) + poses[:, :3, 3]
    # float32 fire times and coordinates: 4 m/s x 1e-8 s and ~1e-6 m of rounding
    np.testing.assert_allclose(world[:, 0], 15.0, atol=2e-5)


# --- pattern ---------------------------------------------------------------------------------


def test_spinning_pattern_timing_and_direction():
    cfg = spinning([-5.0, 5.0], columns=100, hz=20.0, pattern={"channels": {
        "elevation_deg": [-5.0, 5.0], "fire_time_us": [0.0, 10.0], "azimuth_offset_deg": [0.0, 1.0]}})
    pat = Lidar(cfg).pattern
    t_col = np.arange(100) / (100 * 20.0)
    sel0 = pat.ring == 0
    np.testing.assert_allclose(np.sort(pat.time[sel0]), t_col)
    np.testing.assert_allclose(np.sort(pat.time[~sel0]), t_col + 10e-6)
    # clockwise: the azimuth decreases with time; channel 1 is 1 degree ahead, plus 10 us of turning
    az0 = pat.azimuth[sel0][np.argsort(pat.time[sel0])]
    az1 = pat.azimuth[~sel0][np.argsort(pat.time[~sel0])]
    step = np.angle(np.exp(1j * np.diff(az0)))
    np.testing.assert_allclose(step, -2 * np.pi / 100)
    dphi = np.angle(np.exp(1j * (az1 - az0)))
    np.testing.assert_allclose(dphi, np.deg2rad(1.0) - 2 * np.pi * 20.0 * 10e-6, atol=1e-12)
    assert np.all(np.diff(pat.time) >= 0)


def test_channel_origin_offsets_shift_the_beam_origin():
    # One beam at azimuth 0, elevation 0, origin 0.2 m left and 0.1 m up of the sensor.
    cfg = emitter([0.0], [0.0])
    cfg = spinning([0.0], columns=4, pattern={"channels": {"elevation_deg": [0.0], "origin_horizontal_m": [0.2],
                                                           "origin_vertical_m": [0.1]}})
    sweep = Lidar(cfg).scan(Tracer(wall_x(10.0)), np.eye(4))
    p = sweep.points[np.argmin(np.abs(sweep.points["azimuth"]))]
    assert p["range"] == pytest.approx(10.0, abs=1e-5)
    assert (p["x"], p["y"], p["z"]) == pytest.approx((10.0, 0.2, 0.1), abs=1e-5)


def test_emitter_table_from_csv_and_errors(tmp_path):
    f = tmp_path / "livox.csv"
    az = np.linspace(-30, 30, 61)
    el = 10 * np.sin(np.linspace(0, 6 * np.pi, 61))
    t = np.linspace(0, 0.05, 61)
    f.write_text("azimuth_deg,elevation_deg,time_s\n" + "\n".join(f"{a},{e},{s}" for a, e, s in zip(az, el, t)))
    cfg = config_from_dict({"name": "livox-like", "pattern": {"type": "emitter", "file": str(f), "period_s": 0.1}})
    sweep = Lidar(cfg).scan(Tracer(wall_x(20.0)), np.eye(4))
    assert len(sweep) == 61
    np.testing.assert_allclose(sweep.points["range"], 20.0 / (np.cos(np.deg2rad(az)) * np.cos(np.deg2rad(el))), rtol=1e-6)
    np.testing.assert_allclose(sweep.points["time"], t, atol=1e-7)
    bad = tmp_path / "bad.csv"
    bad.write_text("azimuth,elevation\n1,2\n")
    from scube_sim.lidar.config import ConfigError

    with pytest.raises(ConfigError, match="bad.csv: missing column 'azimuth_deg'"):
        Lidar(config_from_dict({"name": "x", "pattern": {"type": "emitter", "file": str(bad)}}))
    with pytest.raises(ConfigError, match="emitter table not found"):
        Lidar(config_from_dict({"name": "x", "pattern": {"type": "emitter", "file": str(tmp_path / "none.npy")}}))


def test_emitter_table_replays_recorded_directions_from_npy(tmp_path):
    rng = np.random.default_rng(5)
    table = np.c_[rng.uniform(-60, 60, 500), rng.uniform(-20, 20, 500), np.sort(rng.uniform(0, 0.1, 500))]
    np.save(tmp_path / "rays.npy", table)
    cfg = config_from_dict({"name": "replay", "pattern": {"type": "emitter", "file": str(tmp_path / "rays.npy")}})
    p = Lidar(cfg).scan(Tracer(wall_x(25.0)), np.eye(4)).points
    np.testing.assert_allclose(np.rad2deg(p["azimuth"]), table[:, 0], atol=1e-4)
    np.testing.assert_allclose(np.rad2deg(np.arcsin(p["z"] / p["range"])), table[:, 1], atol=1e-4)


# --- beam, returns, intensity, drops ---------------------------------------------------------


def edge_scene():
    near = pr.quad([[10, -50, -20], [10, -50, 20], [10, 0, 20], [10, 0, -20]], label=WALL)  # y < 0 at 10 m
    far = wall_x(20.0, label=label_id("vegetation"))
    return Tracer(TriangleMesh.concatenate([near, far]))


@pytest.mark.parametrize("mode", ["first", "last", "strongest", "mean", "dual"])
def test_divergence_straddling_an_edge(mode):
    # Beams sweep across the edge at y = 0 (10 m away), 20 mrad wide footprints (0.2 m at 10 m).
    az = np.linspace(-2.0, 2.0, 201)
    cfg = emitter(az, np.zeros_like(az), beam={"divergence_mrad": 20.0, "samples": 32, "return_mode": mode},
                  intensity={"source": "constant"})
    p = Lidar(cfg).scan(edge_scene(), np.eye(4)).points
    az_p = np.rad2deg(p["azimuth"])
    half = np.rad2deg(0.010)  # footprint half-angle
    clear_near, clear_far = az_p < -half - 0.05, az_p > half + 0.05
    straddle = np.abs(az_p) < half - 0.2
    r = p["range"] * np.cos(np.deg2rad(az_p))  # the distance along x
    assert np.allclose(r[clear_near], 10.0, atol=1e-3) and np.allclose(r[clear_far], 20.0, atol=1e-3)
    mid = r[straddle]
    if mode == "first":
        assert np.allclose(mid, 10.0, atol=1e-3)
    elif mode == "last":
        assert np.allclose(mid, 20.0, atol=1e-3)
    elif mode == "strongest":
        assert np.all(np.isclose(mid, 10.0, atol=1e-3) | np.isclose(mid, 20.0, atol=1e-3))
    elif mode == "mean":
        assert np.all((mid > 10.01) & (mid < 19.99))  # the mixed pixel between the surfaces
    else:
        # two returns per straddling beam, one at each surface, return_id 0 (strongest) and 1
        sp = p[straddle]
        assert np.all(np.bincount(sp["return_id"]) == straddle.sum() // 2)
        assert set(np.round(mid, 2)) == {10.0, 20.0}
        # beams clear of the edge give a single return
        assert np.all(p["return_id"][clear_near | clear_far] == 0)


def test_intensity_is_reflectivity_times_cosine_with_falloff():
    cfg = emitter(np.linspace(-50, 50, 21), np.zeros(21), intensity={"falloff_exponent": 2.0, "reference_range_m": 5.0})
    p = Lidar(cfg).scan(Tracer(wall_x(10.0)), np.eye(4)).points
    cos_i = np.cos(p["azimuth"])
    want = LABEL_REFLECTIVITY[WALL] * cos_i * (5.0 / p["range"]) ** 2
    np.testing.assert_allclose(p["intensity"], want, rtol=1e-5)
    assert np.all(p["label"] == WALL)


def test_drops_grazing_random_and_reflectivity_range():
    az = np.linspace(-80, 80, 161)
    cfg = emitter(az, np.zeros_like(az), drop={"max_incidence_deg": 60.0})
    p = Lidar(cfg).scan(Tracer(wall_x(10.0)), np.eye(4)).points
    assert np.all(np.abs(np.rad2deg(p["azimuth"])) <= 60.0 + 1e-4)
    assert len(p) == np.sum(np.abs(az) <= 60.0)

    az = np.linspace(-30, 30, 4001)
    cfg = emitter(az, np.zeros_like(az), drop={"random_rate": 0.3})
    n = len(Lidar(cfg).scan(Tracer(wall_x(10.0)), np.eye(4), seed=4))
    assert abs(n - 0.7 * 4001) < 4 * np.sqrt(4001 * 0.21)

    # max_m = 100 m at reflectivity 0.1: a building (0.35) at 150 m is seen, road (0.12) is not.
    for label, seen in ((WALL, True), (label_id("road"), False)):
        cfg = emitter([0.0], [0.0], range={"min_m": 0.3, "max_m": 200.0},
                      drop={"reflectivity_range": 0.1 * (200.0 / 100.0) ** 2 / 1.0})
        assert (len(Lidar(cfg).scan(Tracer(wall_x(150.0, label=label)), np.eye(4))) == 1) == seen


def test_noise_and_quantisation_are_seeded():
    cfg = spinning(np.linspace(-10, 10, 8), columns=720, noise={"range_sigma_m": 0.03, "quantization_m": 0.004})
    lidar = Lidar(cfg)
    tracer = Tracer(TriangleMesh.concatenate([wall_x(12.0), wall_x(-9.0)]))
    a = lidar.scan(tracer, np.eye(4), seed=7)
    b = lidar.scan(tracer, np.eye(4), seed=7)
    c = lidar.scan(tracer, np.eye(4), seed=8)
    assert a.points.tobytes() == b.points.tobytes()
    assert a.points.tobytes() != c.points.tobytes()
    q = a.points["range"].astype(np.float64) / 0.004
    np.testing.assert_allclose(q, np.round(q), atol=1e-3)


def test_ego_body_blocks_rays_and_can_return():
    body = {"min": [-2.5, -1.0, 0.0], "max": [2.5, 1.0, 1.5]}
    mount = {"xyz": [0.0, 0.0, 1.8], "rpy_deg": [0, 0, 0]}
    el = [-60.0, -30.0, -5.0]
    ground = pr.quad([[-100, -100, 0], [100, -100, 0], [100, 100, 0], [-100, 100, 0]], label=label_id("road"))
    for returns in (False, True):
        cfg = spinning(el, columns=36, ego_body={**body, "returns": returns}, mount=mount)
        lidar = Lidar(cfg)
        sweep = lidar.scan(Tracer(ground), lidar.sensor_pose(np.eye(4)))
        p = sweep.points
        el_p = np.rad2deg(np.arcsin(p["z"] / p["range"]))
        steep = el_p < -45
        if returns:
            # the roof at z = 1.5 m in the ego frame, 0.3 m below the sensor
            np.testing.assert_allclose(p["z"][steep], -0.3, atol=1e-6)
            assert np.all(p["label"][steep] == 0)
        else:
            assert not steep.any()
        # -5 degrees clears the body and reaches the ground 1.8 / tan(5 deg) away
        shallow = np.abs(el_p + 5) < 0.1
        np.testing.assert_allclose(p["range"][shallow], 1.8 / np.sin(np.deg2rad(5)), rtol=1e-5)


def test_range_image_rows_follow_elevation():
    cfg = spinning([5.0, -10.0, 0.0], columns=90)
    sweep = Lidar(cfg).scan(Tracer(TriangleMesh.concatenate([wall_x(10.0), wall_x(-10.0)])), np.eye(4))
    img = sweep.range_image()
    assert img.shape == (3, 90)
    # row 0 = +5 deg, row 1 = 0 deg, row 2 = -10 deg; at column 0 (azimuth 0) the wall is 10 m ahead
    np.testing.assert_allclose(img[:, 0], 10.0 / np.cos(np.deg2rad([5.0, 0.0, -10.0])), rtol=1e-6)
    assert sweep.points.dtype == POINT_DTYPE


def test_gaussian_scene_labels_follow_voxels():
    g = plane_of_gaussians(half_y=5, half_z=3, spacing=0.2, sigma_n=0.01)
    vs = VoxSplat.from_gaussians(g, 0.4, labels=np.full(len(g), label_id("sign")))
    p = Lidar(emitter([0.0, 10.0], [0.0, 5.0])).scan(Tracer(vs), np.eye(4)).points
    assert len(p) == 2 and np.all(p["label"] == label_id("sign"))


def test_bad_pose_is_a_clear_error():
    lidar = Lidar(spinning([0.0], columns=8))
    tracer = Tracer(wall_x(5.0))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="pose_start: contains NaN"):
        lidar.scan(tracer, bad)
    with pytest.raises(ValueError, match="pose_end: rotation"):
        lidar.scan(tracer, np.eye(4), np.diag([2.0, 1, 1, 1]))


@pytest.mark.parametrize("pattern, match", [
    ({"azimuth_deg": [0.0, float("inf")], "elevation_deg": [0.0, 1.0]}, r"pattern\.azimuth_deg(\[\d+\])?: .*finite"),
    ({"azimuth_deg": [0.0, 1.0], "elevation_deg": [float("nan"), 1.0]}, r"pattern\.elevation_deg(\[\d+\])?: .*finite"),
    ({"azimuth_deg": [0.0], "elevation_deg": [95.0]}, r"pattern\.elevation_deg: .*\[-90, 90\]"),
    ({"azimuth_deg": [], "elevation_deg": []}, r"pattern\.azimuth_deg: .*at least one ray"),
    ({"azimuth_deg": [0.0], "elevation_deg": [0.0], "time_s": [float("inf")]}, r"pattern\.time_s(\[\d+\])?: .*finite"),
])
def test_bad_inline_emitter_tables_are_refused_in_the_schema(tmp_path, pattern, match):
    """Infinite or NaN angles, elevations past the pole, an empty table: refused when the sensor
    file is read, naming the file and key (not deep inside the tracer, and never a silent run)."""
    import yaml

    from scube_sim.lidar.config import ConfigError

    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump({"name": "x", "pattern": {"type": "emitter", **pattern}}))
    with pytest.raises(ConfigError, match=rf"/s\.yaml: {match}"):
        load_lidar_config(path)


def test_an_emitter_file_with_no_rays_is_refused(tmp_path):
    from scube_sim.lidar.config import ConfigError

    f = tmp_path / "empty.csv"
    f.write_text("azimuth_deg,elevation_deg\n")
    with pytest.raises(ConfigError, match=r"empty\.csv: emitter table has no rays"):
        Lidar(config_from_dict({"name": "x", "pattern": {"type": "emitter", "file": str(f)}}))


def test_a_sensor_asking_for_too_many_rays_is_refused_before_any_is_made(tmp_path):
    """100 000 columns x 16 channels x 64 sub-rays (10^8 rays; past 6 GB before) is refused when
    the file is read, naming the keys and the limit; the same sensor with 1 sub-ray loads."""
    import yaml

    from scube_sim.lidar.config import MAX_RAYS_PER_SWEEP, ConfigError

    spec = load_lidar_config("vlp16").model_dump(mode="json")
    spec["pattern"]["columns"] = 100_000
    spec["beam"]["samples"] = 64
    path = tmp_path / "huge.yaml"
    path.write_text(yaml.safe_dump(spec))
    with pytest.raises(ConfigError, match=r"huge\.yaml: .*pattern\.columns 100000 x 16 channels x beam\.samples 64 = "
                                          r"102,400,000 traced rays per sweep; at most 33,554,432"):
        load_lidar_config(path)
    spec["beam"]["samples"] = 1
    path.write_text(yaml.safe_dump(spec))
    assert load_lidar_config(path).pattern.columns * 16 <= MAX_RAYS_PER_SWEEP
    # an emitter table file is checked when the Lidar reads it
    rays = tmp_path / "rays.npy"
    np.save(rays, np.zeros((MAX_RAYS_PER_SWEEP // 64 + 1, 2)))
    cfg = config_from_dict({"name": "dense", "pattern": {"type": "emitter", "file": str(rays)},
                            "beam": {"samples": 64, "divergence_mrad": 1.0}})
    with pytest.raises(ConfigError, match=r"dense: 524,289 rays x beam\.samples 64"):
        Lidar(cfg)
