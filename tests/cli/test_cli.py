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


def test_export_keeps_the_gaussians_that_cover_the_most_surface(tmp_path):
    """--max-gaussians ranks by alpha * (product of the two largest std-devs), read back by plyfile."""
    from plyfile import PlyData

    from scube_sim.splat_params import opacities_to_raw, scales_to_raw
    from scube_sim.voxsplat import VoxSplat

    # One Gaussian per voxel: areas 1, 4, 0.25, 4 (m^2) at alphas 0.9, 0.1, 0.9, 0.5 -> scores
    # 0.9, 0.4, 0.225, 2.0: the best two are voxels 3 and 0, written in index order.
    scales = np.array([[1, 1, 0.01], [2, 0.01, 2], [0.5, 0.5, 0.5], [2, 2, 0.01]])
    alpha = np.array([0.9, 0.1, 0.9, 0.5])
    params = np.zeros((4, 1, 14), np.float32)
    params[:, 0, 3] = opacities_to_raw(alpha)
    params[:, 0, 4:7] = scales_to_raw(scales)
    params[:, 0, 7] = 1.0
    vs = VoxSplat(ijk=np.array([[0, 0, 0], [10, 0, 0], [20, 0, 0], [30, 0, 0]]), params=params, voxel_size=1.0)
    vs.save(tmp_path / "four.npz")
    res = run("export", tmp_path / "four.npz", "--to", "ply", "--max-gaussians", 2, "-o", tmp_path / "two.ply")
    assert res.exit_code == 0, res.output
    v = PlyData.read(str(tmp_path / "two.ply"))["vertex"]
    assert np.allclose(v["x"] - v["x"][0], [0.0, 30.0])
    assert np.allclose(1 / (1 + np.exp(-v["opacity"])), [0.9, 0.5], atol=1e-5)
    one_line_error(run("export", tmp_path / "four.npz", "--to", "usd", "--max-gaussians", 2), "--max-gaussians")
    one_line_error(run("export", tmp_path / "four.npz", "--to", "ply", "--max-gaussians", 0), "--max-gaussians")


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
    one_line_error(run("lidar", scene_npz, "--sensor", "vlp16", "--soft-alpha-min", "1.5", "-o", tmp_path / "a.pcd"),
                   "--soft-alpha-min", ">= 0 and < 1")
    assert not (tmp_path / "a.pcd").exists()


def test_truncated_ply_is_an_error(shared_data, tmp_path):
    src = shared_data / "gaussian-splat-ply" / "donut_mip-splatting_fused.ply"
    if not src.exists():
        pytest.skip(f"{src} is absent")
    cut = tmp_path / "cut.ply"
    cut.write_bytes(src.read_bytes()[:-1000])
    one_line_error(run("lidar", cut, "--sensor", "vlp16", "-o", tmp_path / "a.pcd"), "cut.ply")
    one_line_error(run("export", cut, "--to", "usd"), "cut.ply")


def test_progress_off_a_terminal_is_one_line_per_item(capsys):
    """Off a terminal (a log file, CI) rich's bar prints nothing until the end; `track` then
    writes one line per finished item on stderr instead."""
    from scube_sim.cli._common import track

    seen = list(track(["a", "b", "c"], "sensor to sensor"))
    assert seen == ["a", "b", "c"]
    err = capsys.readouterr().err.splitlines()
    assert [line.split(",")[0] for line in err] == [f"sensor to sensor: {i}/3 done" for i in (1, 2, 3)]


def test_fidelity_checks_its_arguments_before_reading_the_dataset(scene_npz, tmp_path):
    """A bad --mode or --static-from is refused before the dataset is opened (whose poses may
    take long to estimate); a sample past the end names the last one."""
    base = ["fidelity", str(tmp_path / "no-such-dataset"), "--dataset", "folder", "--scene", str(scene_npz)]
    r = CliRunner().invoke(app, [*base, "--mode", "fuzzy"])
    assert r.exit_code == 2 and one_line_error(r, "--mode: expected entry, max_response or soft, got 'fuzzy'")
    r = CliRunner().invoke(app, [*base, "--static-from", "1,x"])
    assert r.exit_code == 2 and one_line_error(r, "--static-from: expected comma-separated sample indices")
