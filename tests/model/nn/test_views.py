"""`scube-sim render`: a scene through a camera rig with the CPU renderer."""

from __future__ import annotations

import numpy as np
from PIL import Image
from typer.testing import CliRunner

from scube_sim.camera.rig import load_rig
from scube_sim.cli import app
from scube_sim.io.ply3dgs import write_3dgs_ply
from scube_sim.model.nn.views import render_rig
from scube_sim.voxsplat import SH_C0, Gaussians, VoxSplat


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
    assert res.exit_code == 2 and "--scale: expected a finite number > 0 and <= 1, got 2.0" in res.output


def gradient_sky(h: int = 64, w: int = 128) -> np.ndarray:
    """(h, w, 3) sky whose colour is a smooth function of the direction: red = (1 + cos azimuth)/2,
    green = elevation / (pi/2) clipped to [0, 1], blue 0.8 (the VoxSplat channel's pixel grid)."""
    az = (np.arange(w) + 0.5) / w * 2 * np.pi - np.pi
    el = np.pi / 2 - (np.arange(h) + 0.5) / h * np.pi
    e, a = np.meshgrid(el, az, indexing="ij")
    return np.stack([(1 + np.cos(a)) / 2, np.clip(e / (np.pi / 2), 0, 1), np.full_like(a, 0.8)], -1).astype(np.float32)


def test_a_voxsplat_sky_shows_through_where_the_gaussians_leave_it():
    rig = load_rig("waymo-5")
    # one opaque voxel of 8 Gaussians straight ahead at 12 m, and the sky channel
    raw = np.zeros((1, 8, 14), np.float32)
    raw[..., 3] = 8.0  # opacity ~1
    raw[..., 4:7] = np.log(0.3)
    raw[..., 7] = 1.0
    vs = VoxSplat(ijk=[[30, 0, 4]], params=raw, voxel_size=0.4, origin=(0.0, -0.2, 0.0))
    vs.set_channel("sky_panorama", gradient_sky())
    views = render_rig(vs, rig, np.eye(4), scale=0.04)
    for cam in rig.cameras:
        intr = cam.intrinsics().scaled(0.04)
        rays = np.asarray(intr.pixel_rays()) @ cam.cam_to_ego()[:3, :3].T  # ego = scene axes
        az, el = np.arctan2(rays[..., 1], rays[..., 0]), np.arcsin(np.clip(rays[..., 2], -1, 1))
        want = np.stack([(1 + np.cos(az)) / 2, np.clip(el / (np.pi / 2), 0, 1), np.full_like(az, 0.8)], -1)
        img = views[cam.name]
        free = np.abs(img - want).max(-1) < 0.03
        assert free.mean() > 0.9, cam.name  # the sky everywhere but on the voxel (bilinear: ~1/128 turn)
    front = views["FRONT"]
    h, w, _ = front.shape
    assert np.abs(front[h // 2, w // 2] - 0.5).max() < 0.02  # the grey voxel covers the sky
