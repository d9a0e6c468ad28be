"""The command line: real runs on small scenes, and one-line errors with exit code 2."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from scube_sim.cli import app
from scube_sim.fit import fit_voxsplat
from scube_sim.labels import label_id
from scube_sim.worlds import primitives as pr
from tests.conftest import one_line_error

runner = CliRunner()


@pytest.fixture(scope="module")
def scene_npz(tmp_path_factory):
    """A 30 m square room (walls 3 m high) as a 0.25 m VoxSplat, saved as .npz."""
    from scube_sim.mesh import TriangleMesh

    walls = [pr.box([x, y, 1.5], size, label=label_id("building"))
             for x, y, size in [(15, 0, [0.3, 30, 3]), (-15, 0, [0.3, 30, 3]), (0, 15, [30, 0.3, 3]), (0, -15, [30, 0.3, 3])]]
    floor = pr.ground_grid(-15, -15, 15, 15, 0.0, 5.0, label=label_id("road"), color=(0.3, 0.3, 0.3))
    mesh = TriangleMesh.concatenate(walls + [floor])
    s = mesh.sample_surface_grid(0.1)
    vs = fit_voxsplat(s["points"], 0.25, labels=s["labels"], colors=s["colors"], weights=s["weights"])
    path = tmp_path_factory.mktemp("scene") / "room.npz"
    vs.save(path)
    return path


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def test_lidar_writes_a_pcd_that_open3d_reads(scene_npz, tmp_path):
    import open3d as o3d

    out = tmp_path / "sweep.pcd"
    res = run("lidar", scene_npz, "--sensor", "VLP-16", "--pose", "1,2,1.5,0,0,30", "-o", out, "--png", tmp_path / "bev.png")
    assert res.exit_code == 0, res.output
    pc = o3d.t.io.read_point_cloud(str(out))
    xyz = pc.point.positions.numpy()
    assert xyz.shape[0] > 10000
    # Sensor frame at (1, 2, 1.5), yawed 30 deg: the floor is 1.5 m below, all points inside the room.
    floor = pc.point.label.numpy().ravel() == label_id("road")
    assert np.median(xyz[floor, 2]) == pytest.approx(-1.5, abs=0.02)
    assert (tmp_path / "bev.png").stat().st_size > 10000


def test_export_round_trips(scene_npz, tmp_path):
    res = run("export", scene_npz, "--to", "ply", "-o", tmp_path / "s.ply")
    assert res.exit_code == 0, res.output
    res = run("export", tmp_path / "s.ply", "--to", "usd", "-o", tmp_path / "s.usda")
    assert res.exit_code == 0, res.output
    from pxr import Usd

    assert Usd.Stage.Open(str(tmp_path / "s.usda")).GetPrimAtPath("/World/Gaussians")
    res = run("lidar", tmp_path / "s.ply", "--sensor", "vlp16", "--mode", "entry", "-o", tmp_path / "x.bin")
    assert res.exit_code == 0, res.output
    assert (tmp_path / "x.bin").stat().st_size % 16 == 0


def test_sensors_lists_the_presets():
    res = run("sensors")
    assert res.exit_code == 0
    for name in ("VLP-16", "HDL-64E", "OS1-128", "Pandar64", "Waymo"):
        assert name.lower() in res.output.lower()


def test_bad_inputs_give_one_line_and_exit_2(scene_npz, tmp_path):
    bad_yaml = tmp_path / "broken.yaml"
    bad_yaml.write_text("name: x\npattern:\n  type: spinning\n   columns: 10\n")
    one_line_error(run("lidar", scene_npz, "--sensor", bad_yaml, "-o", tmp_path / "a.pcd"), "broken.yaml", "line")
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text("name: x\npattern: {type: spinning, columns: ten, rotation_hz: 10, channels: {elevation_deg: [0]}}\n")
    one_line_error(run("lidar", scene_npz, "--sensor", wrong, "-o", tmp_path / "a.pcd"), "pattern.columns", "integer")
    one_line_error(run("lidar", tmp_path / "nope.npz", "--sensor", "vlp16", "-o", tmp_path / "a.pcd"), "nope.npz")
    one_line_error(run("lidar", scene_npz, "--sensor", "hdl65", "-o", tmp_path / "a.pcd"), "unknown sensor 'hdl65'", "vlp16")
    one_line_error(run("lidar", scene_npz, "--sensor", "vlp16", "--pose", "1,2,3", "-o", tmp_path / "a.pcd"), "--pose")
    one_line_error(run("lidar", scene_npz, "--sensor", "vlp16", "-o", tmp_path / "a.xyz"), "a.xyz")
    assert not (tmp_path / "a.pcd").exists()


def test_truncated_ply_is_an_error(shared_data, tmp_path):
    src = shared_data / "gaussian-splat-ply" / "donut_mip-splatting_fused.ply"
    if not src.exists():
        pytest.skip(f"{src} is absent")
    cut = tmp_path / "cut.ply"
    cut.write_bytes(src.read_bytes()[:-1000])
    one_line_error(run("lidar", cut, "--sensor", "vlp16", "-o", tmp_path / "a.pcd"), "cut.ply")
    one_line_error(run("export", cut, "--to", "usd"), "cut.ply")
