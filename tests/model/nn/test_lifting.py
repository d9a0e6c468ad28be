"""Depth-weighted lifting (paper Eq. 1) against hand-computed pinhole geometry."""

import math

import numpy as np
import pytest
import torch

from scube_sim.camera.model import Intrinsics
from scube_sim.model.nn.lifting import (
    LiftGrid,
    depth_bin_centres,
    depth_bin_edges,
    depth_focal_loss,
    depth_to_bin,
    feature_intrinsics,
    frustum_points,
    lift,
)

# camera at (1, 2, 3) in the chunk looking along +x: camera z -> chunk x, camera x -> -y, camera y -> -z
POSE = torch.tensor([[0.0, 0.0, 1.0, 1.0], [-1.0, 0.0, 0.0, 2.0], [0.0, -1.0, 0.0, 3.0], [0.0, 0.0, 0.0, 1.0]],
                    dtype=torch.float64)
K = torch.tensor([[2.0, 0.0, 3.0], [0.0, 2.0, 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64)  # 6 x 4 image


def test_bin_edges_have_linearly_growing_widths():
    e = depth_bin_edges(64, 0.1, 90.0)
    assert float(e[0]) == pytest.approx(0.1) and float(e[-1]) == pytest.approx(90.0)
    widths = torch.diff(e)
    steps = torch.diff(widths)
    torch.testing.assert_close(steps, torch.full_like(steps, float(steps[0])))  # constant increment
    assert float(widths[0]) == pytest.approx(89.9 * 2 / (64 * 65))
    c = depth_bin_centres(64)
    assert torch.equal(depth_to_bin(c, e), torch.arange(64))
    out = depth_to_bin(torch.tensor([0.0, 0.05, 90.0, math.inf, math.nan, 0.1]), e)
    assert out.tolist() == [-1, -1, -1, -1, -1, 0]


def test_a_pixels_feature_lands_in_the_voxel_of_its_depth_bin():
    h, w, c = 4, 6, 3
    depths = torch.tensor([2.0, 5.0, 9.0], dtype=torch.float64)
    pts = frustum_points(K, None, POSE, h, w, depths)[None]  # (1, 3, 4, 6, 3)
    grid = LiftGrid(origin=(0.0, -16.0, -16.0), voxel_size=0.5, dims=(24, 64, 64))
    feats = torch.zeros(1, c, h, w, dtype=torch.float64)
    weights = torch.zeros(1, 3, h, w, dtype=torch.float64)
    u, v, d = 4, 1, 1  # pixel (u, v), one-hot in bin d
    feats[0, :, v, u] = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    weights[0, d, v, u] = 1.0
    vol, hits = lift(feats, weights, pts, grid)
    # by hand: camera-frame point z * ((u + .5 - cx) / fx, (v + .5 - cy) / fy, 1) = 5 * (0.75, -0.25, 1)
    x_cam, y_cam, z = 5 * 0.75, 5 * -0.25, 5.0
    chunk = np.array([1.0 + z, 2.0 - x_cam, 3.0 - y_cam])  # (6, -1.75, 4.25)
    ijk = np.floor((chunk - np.array(grid.origin)) / grid.voxel_size).astype(int)
    assert ijk.tolist() == [12, 28, 40]
    nz = torch.nonzero(vol.abs().sum(0))
    assert nz.tolist() == [ijk.tolist()]
    torch.testing.assert_close(vol[:, 12, 28, 40], torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    # every (pixel, bin) point inside the box is counted once
    assert float(hits.sum()) == 3 * h * w


def test_weights_split_a_feature_between_bins_and_broadcast_fills_the_ray():
    h, w = 4, 6
    depths = torch.tensor([2.0, 5.0, 9.0], dtype=torch.float64)
    pts = frustum_points(K, None, POSE, h, w, depths)[None]
    grid = LiftGrid(origin=(0.0, -8.0, -8.0), voxel_size=0.5, dims=(24, 32, 32))
    feats = torch.zeros(1, 1, h, w, dtype=torch.float64)
    feats[0, 0, 2, 3] = 1.0
    weights = torch.zeros(1, 3, h, w, dtype=torch.float64)
    weights[0, :, 2, 3] = torch.tensor([0.2, 0.3, 0.5], dtype=torch.float64)
    vol, _ = lift(feats, weights, pts, grid)
    got = sorted(float(x) for x in vol[0][vol[0] != 0])
    assert got == pytest.approx([0.2, 0.3, 0.5])
    vol_b, _ = lift(feats, None, pts, grid)
    assert sorted(float(x) for x in vol_b[0][vol_b[0] != 0]) == [1.0, 1.0, 1.0]


def test_points_outside_the_box_and_invalid_pixels_are_dropped():
    h, w = 4, 6
    pts = frustum_points(K, None, POSE, h, w, torch.tensor([2.0, 50.0], dtype=torch.float64))[None]
    grid = LiftGrid(origin=(0.0, -8.0, -8.0), voxel_size=0.5, dims=(24, 32, 32))
    feats = torch.ones(1, 1, h, w, dtype=torch.float64)
    vol, hits = lift(feats, None, pts, grid)
    assert float(hits.sum()) == h * w  # the 50 m bin is past x = 12 m
    valid = torch.zeros(1, h, w, dtype=torch.bool)
    valid[0, 0, 0] = True
    vol, hits = lift(feats, None, pts, grid, valid)
    assert float(hits.sum()) == 1.0 and float(vol.sum()) == 1.0


def test_distorted_frustum_points_reproject_to_the_pixel_centres():
    intr = Intrinsics(40, 30, 30.0, 31.0, 20.3, 14.8, "opencv", [-0.25, 0.08, 0.001, -0.002, -0.01])
    Kd = torch.tensor(intr.K, dtype=torch.float64)
    dist = torch.tensor(intr.dist, dtype=torch.float64)
    pts = frustum_points(Kd, dist, torch.eye(4, dtype=torch.float64), 30, 40, torch.tensor([3.0, 7.0]))
    torch.testing.assert_close(pts[..., 2], torch.tensor([3.0, 7.0], dtype=torch.float64)[:, None, None].expand(2, 30, 40))
    uv, ok = intr.project(pts.reshape(-1, 3).numpy())
    assert np.all(ok)
    uu, vv = np.meshgrid(np.arange(40) + 0.5, np.arange(30) + 0.5)
    expect = np.stack([np.tile(uu.ravel(), 2), np.tile(vv.ravel(), 2)], 1)
    np.testing.assert_allclose(uv, expect, atol=1e-6)


def test_feature_intrinsics_keep_block_centres():
    kf = feature_intrinsics(K, 2)
    # feature pixel (1, 0) covers image pixels u in [2, 4): its centre u = 3 is image ray (3 - cx) / fx = 0
    assert float((1 + 0.5 - kf[0, 2]) / kf[0, 0]) == pytest.approx((3.0 - 3.0) / 2.0)


def test_lifting_is_differentiable_in_features_and_weights():
    h, w = 4, 6
    pts = frustum_points(K, None, POSE, h, w, torch.tensor([2.0, 5.0], dtype=torch.float64))[None]
    grid = LiftGrid(origin=(0.0, -8.0, -8.0), voxel_size=1.0, dims=(12, 16, 16))
    feats = torch.randn(1, 2, h, w, dtype=torch.float64, requires_grad=True)
    logits = torch.randn(1, 2, h, w, dtype=torch.float64, requires_grad=True)
    vol, _ = lift(feats, logits.softmax(1), pts, grid)
    (vol ** 2).sum().backward()
    assert feats.grad.abs().sum() > 0 and logits.grad.abs().sum() > 0


def test_depth_focal_loss():
    probs = torch.tensor([[0.7, 0.2, 0.1], [0.1, 0.1, 0.8]], dtype=torch.float64).T.reshape(1, 3, 1, 2)
    target = torch.tensor([[[0, 2]]])
    # gamma = 0 is the negative log-likelihood
    nll = -(math.log(0.7) + math.log(0.8)) / 2
    assert float(depth_focal_loss(probs, target, gamma=0.0)) == pytest.approx(nll)
    fl = -((0.3 ** 2) * math.log(0.7) + (0.2 ** 2) * math.log(0.8)) / 2
    assert float(depth_focal_loss(probs, target)) == pytest.approx(fl)
    assert float(depth_focal_loss(probs, torch.tensor([[[-1, 2]]]))) == pytest.approx(-(0.2 ** 2) * math.log(0.8))
    assert float(depth_focal_loss(probs, torch.full((1, 1, 2), -1))) == 0.0
