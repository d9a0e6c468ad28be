"""`scube-sim render`: a scene through a camera rig with the CPU renderer."""

from __future__ import annotations

import numpy as np
from PIL import Image
from typer.testing import CliRunner

from scube_sim.camera.rig import load_rig
from scube_sim.cli import app
from scube_sim.io.ply3dgs import write_3dgs_ply
from scube_sim.model.views import render_rig
from scube_sim.voxsplat import SH_C0, Gaussians


def red_wall(origin=(0.0, 0.0, 0.0)) -> Gaussians:
    """Flat 0.3 m Gaussians tiling x = 10 m, |y| < 6 m, 0 < z < 4 m (ego frame at the origin), red."""
    y, z = np.meshgrid(np.arange(-6, 6, 0.25), np.arange(0, 4, 0.25), indexing="ij")
    n = y.size
    means = np.stack([np.full(n, 10.0), y.ravel(), z.ravel()], 1)
    rgb = np.tile([0.9, 0.1, 0.1], (n, 1))
    return Gaussians(means=means, scales=np.tile([0.01, 0.3, 0.3], (n, 1)), quats=np.tile([1.0, 0, 0, 0], (n, 1)),
                     opacities=np.full(n, 0.95), sh_dc=((rgb - 0.5) / SH_C0).astype(np.float32),
                     origin=np.asarray(origin, np.float64))


def test_the_front_camera_sees_the_wall_and_the_rear_ones_do_not():
    rig = load_rig("waymo-5")
    views = render_rig(red_wall(), rig, np.eye(4), scale=0.04)
    front = views["FRONT"]
    h, w, _ = front.shape
    assert (h, w) == (51, 77)
    np.testing.assert_allclose(front[h // 2, w // 2], [0.9, 0.1, 0.1], atol=0.02)
    assert float(views["SIDE_LEFT"].max()) < 0.05  # looking sideways-back: nothing there
    # far from the origin (float32 world coordinates would step by 0.25 m): the same picture
    far_pose = np.eye(4)
    far_pose[:3, 3] = [3.0e6, -1.0e6, 0.0]
    far = render_rig(red_wall(origin=(3.0e6, -1.0e6, 0.0)), rig, far_pose, scale=0.04)
    np.testing.assert_allclose(far["FRONT"], front, atol=1e-3)


def test_render_command_writes_a_mosaic(tmp_path):
    path = write_3dgs_ply(tmp_path / "wall.ply", red_wall())
    out = tmp_path / "views.png"
    res = CliRunner().invoke(app, ["render", str(path), "--rig", "nuscenes-6", "--scale", "0.05", "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert "nuscenes-6: 6 views of wall.ply" in res.output
    with Image.open(out) as im:
        assert im.size[0] > 300
    res = CliRunner().invoke(app, ["render", str(path), "--rig", "nuscenes-6", "--scale", "2", "-o", str(out)])
    assert res.exit_code == 2 and "--scale: expected a factor in (0, 1]" in res.output
