"""LiDAR returns projected into a camera with occlusions removed (`camera.depth`)."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.camera import CameraImage, Intrinsics
from scube_sim.camera.depth import lidar_depth, lidar_depth_index, min_filter
from scube_sim.errors import InputError

W, H, F = 64, 48, 50.0


def _camera(cam_to_world=None, intr=None) -> CameraImage:
    intr = intr or Intrinsics(W, H, F, F, W / 2, H / 2)
    return CameraImage("cam", np.zeros((intr.height, intr.width, 3), np.uint8), intr,
                       np.eye(4) if cam_to_world is None else cam_to_world, 0.0)


def _grid(x0, x1, y0, y1, z, step):
    """Points on the plane camera-z = z over [x0, x1] x [y0, y1] (camera frame = world here)."""
    xs = np.arange(x0, x1 + 1e-9, step)
    ys = np.arange(y0, y1 + 1e-9, step)
    xx, yy = np.meshgrid(xs, ys)
    return np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)])


def test_projection_matches_a_hand_computation():
    # pinhole, camera at the world origin looking along +z; u = fx x / z + cx, pixel = floor(u)
    cam = _camera()
    pts = np.array([[1.0, -0.5, 10.0],    # u = 5 + 32 = 37, v = -2.5 + 24 = 21.5 -> pixel (21, 37)
                    [0.0, 0.0, 4.0],      # centre: u = 32, v = 24 -> pixel (24, 32)
                    [0.0, 0.0, -3.0],     # behind: dropped
                    [10.0, 0.0, 5.0]])    # u = 132: outside
    depth, index = lidar_depth_index(pts, cam)
    assert depth.dtype == np.float32 and depth.shape == (H, W)
    assert depth[21, 37] == pytest.approx(10.0) and index[21, 37] == 0
    assert depth[24, 32] == pytest.approx(4.0) and index[24, 32] == 1
    assert np.isfinite(depth).sum() == 2 and (index >= 0).sum() == 2
    # a camera moved and turned: world point -> camera frame by the inverse pose
    pose = np.eye(4)
    pose[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]  # camera z = world x, camera x = -world y
    pose[:3, 3] = [100.0, 20.0, 3.0]
    world = np.array([[108.0, 20.0 - 0.8, 3.0 + 0.4]])  # camera (0.8, -0.4, 8)
    d = lidar_depth(world, _camera(pose))
    u, v = F * 0.8 / 8 + W / 2, F * -0.4 / 8 + H / 2  # 37.0, 21.5
    assert d[int(v), int(u)] == pytest.approx(8.0) and np.isfinite(d).sum() == 1


def test_projection_follows_the_lens_distortion():
    intr = Intrinsics(W, H, F, F, W / 2, H / 2, "opencv", (-0.3, 0.05, 0.001, -0.002, 0.0))
    p = np.array([[1.5, -1.0, 5.0]])
    uv, _ = intr.project(p)
    d = lidar_depth(p, _camera(intr=intr))
    rows, cols = np.nonzero(np.isfinite(d))
    assert (rows[0], cols[0]) == (int(uv[0, 1]), int(uv[0, 0]))
    assert (int(uv[0, 0]), int(uv[0, 1])) != (int(F * 0.3 + W / 2), int(F * -0.2 + H / 2))  # the distortion moved it


def test_occlusion_filter_on_a_box_in_front_of_a_wall():
    # a far wall at 20 m seen through a sparse sweep, and a near box face at 8 m in front of it; the
    # LiDAR sits 1 m to the right of the camera, so it sees wall points the camera sees only
    # through the box (they project inside the box's silhouette, between its returns).
    cam = _camera()
    lidar = np.array([1.0, 0.0, 0.0])
    box = _grid(-1.0, 1.0, -1.0, 1.0, 8.0, 0.4)              # 6 x 6 returns, 2.5 px apart in the image
    wall = _grid(-8.0, 8.0, -6.0, 6.0, 20.0, 0.5)            # returns 1.25 px apart
    # the LiDAR sees a wall point unless the segment from it crosses the box face
    t = (8.0 - lidar[2]) / (wall[:, 2] - lidar[2])
    cross = lidar + t[:, None] * (wall - lidar)
    lidar_sees = ~((np.abs(cross[:, 0]) <= 1.0) & (np.abs(cross[:, 1]) <= 1.0))
    wall = wall[lidar_sees]
    pts = np.concatenate([box, wall])
    depth, index = lidar_depth_index(pts, cam)
    is_box = index >= 0
    is_box[is_box] = index[is_box] < len(box)
    # every box return survives (its own pixel each, nearest in every window)
    assert is_box.sum() == len(box)
    # the camera sees the box over u, v in [cx -/+ 6.25] x [cy -/+ 6.25] (pixels 25..38 x 17..30):
    # inside it, wall returns
    # exist (the LiDAR saw them beside the box) but none survive
    silhouette = np.zeros((H, W), bool)
    silhouette[int(H / 2 - 6.25):int(H / 2 + 6.25) + 1, int(W / 2 - 6.25):int(W / 2 + 6.25) + 1] = True
    wall_in_silhouette = np.zeros((H, W), bool)
    pix = np.floor(np.column_stack([F * wall[:, 1] / 20 + H / 2, F * wall[:, 0] / 20 + W / 2])).astype(int)
    ok = (pix[:, 0] >= 0) & (pix[:, 0] < H) & (pix[:, 1] >= 0) & (pix[:, 1] < W)
    wall_in_silhouette[pix[ok, 0], pix[ok, 1]] = True
    wall_in_silhouette &= silhouette
    assert wall_in_silhouette.sum() > 10  # the scene does leak wall returns into the box's image
    kept = np.isfinite(depth)
    assert not (kept & silhouette & ~is_box).any()
    # wall returns beside the box (5 pixels or more away from its silhouette: the gap rule looks
    # 4 columns to each side) are all kept
    grown = min_filter(np.where(silhouette, 0.0, 1.0), 9) == 0.0
    beside = np.zeros((H, W), bool)
    beside[pix[ok, 0], pix[ok, 1]] = True
    beside &= ~grown
    assert beside.sum() > 500
    assert kept[beside].all()
    np.testing.assert_allclose(depth[beside], 20.0, rtol=1e-6)
    np.testing.assert_allclose(depth[is_box], 8.0, rtol=1e-6)


def test_nearest_return_per_pixel_and_the_margin():
    cam = _camera()
    centre_far = [0.0, 0.0, 10.0]                 # pixel (24, 32)
    centre_near = [0.0, 0.0, 5.0]                 # the same pixel, nearer
    right = [2.5 * 9.5 / F, 0.0, 9.5]             # u = 34.5: pixel (24, 34), two columns right
    depth = lidar_depth(np.array([centre_far, right]), cam)
    assert depth[24, 32] == pytest.approx(10.0)   # 10 <= 1.1 x 9.5: within the margin, kept
    assert depth[24, 34] == pytest.approx(9.5) and np.isfinite(depth).sum() == 2
    pts = np.array([centre_far, centre_near, right])
    depth = lidar_depth(pts, cam)
    assert depth[24, 32] == pytest.approx(5.0)    # z-buffer: 5 in front of 10
    assert np.isnan(depth[24, 34])                # 9.5 > 1.1 x 5 within the 7 x 7 window: hidden
    assert lidar_depth(pts, cam, margin=1.0)[24, 34] == pytest.approx(9.5)
    assert lidar_depth(pts, cam, window=3)[24, 34] == pytest.approx(9.5)   # two columns: outside 3 x 3
    assert np.isnan(lidar_depth(pts, cam, window=(1, 5))[24, 34])          # a 1 x 5 window reaches it


def test_gap_rule_drops_a_return_between_near_scan_lines_but_keeps_a_ground_line():
    cam = _camera(intr=Intrinsics(64, 96, F, F, 32, 48))
    def at(row, z, col=32):  # a point projecting to the centre of pixel (row, col) at camera-z z
        return [(col + 0.5 - 32) * z / F, (row + 0.5 - 48) * z / F, z]
    near_lines = [at(20, 8.0, c) for c in range(28, 37, 2)] + [at(44, 8.0, c) for c in range(28, 37, 2)]
    far = at(32, 20.0)                                     # 12 rows from each near line
    d = lidar_depth(np.array(near_lines + [far]), cam)
    assert np.isnan(d[32, 32]) and np.isfinite(d).sum() == len(near_lines)
    assert lidar_depth(np.array(near_lines + [far]), cam, gap_reach=0)[32, 32] == pytest.approx(20.0)
    assert lidar_depth(np.array(near_lines + [far]), cam, gap_reach=8)[32, 32] == pytest.approx(20.0)
    # a farther ground line above a nearer one (nothing nearer above it): kept
    d = lidar_depth(np.array(near_lines[5:] + [far]), cam)
    assert d[32, 32] == pytest.approx(20.0)


def test_deterministic_and_rejects_bad_windows(rng):
    pts = rng.uniform([-10, -10, 1], [10, 10, 40], (5000, 3))
    a, b = lidar_depth(pts, _camera()), lidar_depth(pts, _camera())
    np.testing.assert_array_equal(a, b)
    for bad in (4, 0, (3, 2)):
        with pytest.raises(InputError, match="window"):
            lidar_depth(pts, _camera(), window=bad)
    with pytest.raises(InputError, match="margin"):
        lidar_depth(pts, _camera(), margin=-0.1)
    with pytest.raises(InputError, match="gap_reach"):
        lidar_depth(pts, _camera(), gap_reach=-1)
    empty = lidar_depth(np.zeros((0, 3)), _camera())
    assert np.isnan(empty).all()
