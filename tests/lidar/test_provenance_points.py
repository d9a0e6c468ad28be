"""Per-point `observed` and `confidence` (issue 13): a return from a converted VoxSplat carries its
voxel's channels; a return from anything not inferred (a mesh, a scene without the channels)
carries 1 and 1.0; a sweep has the fields only when its scene holds such voxels; PCD (read back by
open3d), npz and USD (read back by pxr) keep them."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.fit import FitOptions, fit_voxsplat
from scube_sim.io.pointcloud import write_npz, write_pcd
from scube_sim.lidar.config import load_lidar_config
from scube_sim.lidar.model import CONVERTED_POINT_DTYPE, POINT_DTYPE, Lidar
from scube_sim.mesh import TriangleMesh
from scube_sim.raytrace.tracer import Tracer


def _wall(x: float, spacing: float = 0.05) -> np.ndarray:
    """Points of a vertical wall at `x` (y in [-6, 6], z in [-2, 4]) facing the origin."""
    y, z = np.meshgrid(np.arange(-6, 6, spacing), np.arange(-2, 4, spacing))
    return np.stack([np.full(y.size, x), y.ravel(), z.ravel()], 1)


@pytest.fixture(scope="module")
def converted():
    """Two walls, 10 m in front of and behind the sensor; the front one 'seen' (observed 1,
    confidence 0.8 per voxel), the back one inferred (observed 0, confidence 0.3)."""
    vs = fit_voxsplat(np.concatenate([_wall(10.0), _wall(-10.0)]), 0.5, fit=FitOptions(gaussians_per_voxel=1))
    front = vs.voxel_centers()[:, 0] > 0
    vs.set_channel("observed", front)
    vs.set_channel("confidence", np.where(front, 0.8, 0.3).astype(np.float32))
    return vs


def _lidar() -> Lidar:
    cfg = load_lidar_config("vlp16")
    return Lidar(cfg.model_copy(update={"noise": cfg.noise.model_copy(update={"range_sigma_m": 0.0,
                                                                              "range_sigma_rel": 0.0})}))


def test_returns_carry_their_voxels_channels_and_one_on_surfaces_not_inferred(converted):
    sweep = _lidar().scan(Tracer(converted, mode="entry"), np.eye(4))
    p = sweep.points
    assert p.dtype == CONVERTED_POINT_DTYPE
    front = p["x"] > 0
    assert front.sum() > 100 and (~front).sum() > 100
    assert (p["observed"][front] == 1).all() and np.allclose(p["confidence"][front], 0.8)
    assert (p["observed"][~front] == 0).all() and np.allclose(p["confidence"][~front], 0.3)
    # a mesh roof traced beside it: its returns were not inferred
    roof = TriangleMesh(np.array([[-30, -30, 3.0], [30, -30, 3.0], [30, 30, 3.0], [-30, 30, 3.0]]),
                        np.array([[0, 1, 2], [0, 2, 3]]))
    both = _lidar().scan([Tracer(converted, mode="entry"), Tracer(roof)], np.eye(4)).points
    on_roof = (np.abs(both["z"] - 3.0) < 0.01) & (np.abs(both["x"]) < 9)  # not the walls up there
    assert on_roof.sum() > 100
    assert (both["observed"][on_roof] == 1).all() and (both["confidence"][on_roof] == 1).all()


def test_a_scene_without_the_channels_gives_the_plain_point_records(converted):
    plain = fit_voxsplat(_wall(10.0), 0.5, fit=FitOptions(gaussians_per_voxel=1))
    assert _lidar().scan(Tracer(plain, mode="entry"), np.eye(4)).points.dtype == POINT_DTYPE
    mesh = TriangleMesh(np.array([[5, -5, -2.0], [5, 5, -2], [5, 5, 4], [5, -5, 4]]), np.array([[0, 1, 2], [0, 2, 3]]))
    assert _lidar().scan(Tracer(mesh), np.eye(4)).points.dtype == POINT_DTYPE


def test_pcd_npz_and_usd_keep_the_fields(converted, tmp_path):
    o3d = pytest.importorskip("open3d")
    from pxr import Usd, UsdGeom

    from scube_sim.sim.frame import Frame, SensorFrame
    from scube_sim.sim.sinks import RunInfo, UsdSink
    from scube_sim.sim.sinks.usd import POINTS_NAME, SENSORS_PATH

    p = _lidar().scan(Tracer(converted, mode="entry"), np.eye(4)).points
    write_pcd(tmp_path / "s.pcd", p)
    pc = o3d.t.io.read_point_cloud(str(tmp_path / "s.pcd"))
    np.testing.assert_array_equal(pc.point["observed"].numpy().ravel(), p["observed"])
    np.testing.assert_array_equal(pc.point["confidence"].numpy().ravel(), p["confidence"])
    write_npz(tmp_path / "s.npz", p)
    with np.load(tmp_path / "s.npz", allow_pickle=False) as z:
        np.testing.assert_array_equal(z["points"]["confidence"], p["confidence"])
    plain = np.empty(len(p), POINT_DTYPE)
    for f in POINT_DTYPE.names:
        plain[f] = p[f]
    pose = np.eye(4)
    sink = UsdSink(tmp_path / "run.usda", write_scene=False)
    sink.open(RunInfo(time_codes_per_second=10.0, start_time=0.0))
    for i in range(2):
        t = 0.1 * (i + 1)
        pts = p if i == 0 else plain  # the second sweep from a scene without the channels
        sink.write(Frame(i, t, pose, {"top": [SensorFrame("top", "lidar", pts, t - 0.1, t, t, pose, pose, pose, i)]}))
    sink.close()
    stage = Usd.Stage.Open(str(tmp_path / "run.usda"))  # held: its prims die with it
    prim = stage.GetPrimAtPath(f"{SENSORS_PATH}/top/{POINTS_NAME}")
    pv = UsdGeom.PrimvarsAPI(prim)
    np.testing.assert_array_equal(np.asarray(pv.GetPrimvar("observed").Get(1.0)), p["observed"])
    np.testing.assert_allclose(np.asarray(pv.GetPrimvar("confidence").Get(1.0)), p["confidence"])
    assert (np.asarray(pv.GetPrimvar("confidence").Get(2.0)) == 1).all()  # nothing inferred
