"""scube_sim.fit.fit_voxsplat against closed-form moments of planar patches.

Closed forms used (all float64):
- a uniform w x h rectangle has covariance diag(w^2, h^2, 0) / 12 in its own axes; a grid of cell
  centres plus each cell's own covariance (the `patch_cov` argument) reproduces it exactly (law
  of total variance);
- a uniform triangle with vertices v_i and centroid c has covariance 1/12 sum (v_i - c)(v_i - c)^T,
  which random area-uniform samples confirm independently;
- a fitted Gaussian's covariance is R diag(s^2) R^T with the thin axis (column 0) along the normal,
  where s_0 is clamped to `min_scale` for an exactly planar patch.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.special import expit

from scube_sim.fit import FitOptions, fit_voxsplat
from scube_sim.voxsplat import VoxSplat

ROT = Rotation.from_euler("ZYX", [35.0, -20.0, 50.0], degrees=True).as_matrix()


def cov6(c):
    """(F, 3, 3) -> (F, 6) in the (xx, xy, xz, yy, yz, zz) order of `patch_cov`."""
    c = np.asarray(c).reshape(-1, 3, 3)
    return np.stack([c[:, 0, 0], c[:, 0, 1], c[:, 0, 2], c[:, 1, 1], c[:, 1, 2], c[:, 2, 2]], 1)


def rectangle(w, h, nx, ny, rot=np.eye(3), centre=(0.0, 0.0, 0.0)):
    """Cell centres of an nx x ny grid on a w x h rectangle in the plane spanned by rot's first
    two columns (normal = rot[:, 2]), with per-cell area weights and per-cell covariance."""
    hx, hy = w / nx, h / ny
    x = (np.arange(nx) + 0.5) * hx - w / 2
    y = (np.arange(ny) + 0.5) * hy - h / 2
    gx, gy = np.meshgrid(x, y, indexing="ij")
    local = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    pts = local @ rot.T + np.asarray(centre, float)
    cell = rot @ np.diag([hx * hx / 12, hy * hy / 12, 0.0]) @ rot.T
    weights = np.full(pts.shape[0], hx * hy)
    return pts, weights, (cov6(cell), np.zeros(pts.shape[0], np.int64))


def triangle_cov(v):
    c = v.mean(0)
    d = v - c
    return d.T @ d / 12.0


def uniform_in_triangle(v, n, rng):
    u, s = rng.random(n), rng.random(n)
    flip = u + s > 1
    u[flip], s[flip] = 1 - u[flip], 1 - s[flip]
    return v[0] + u[:, None] * (v[1] - v[0]) + s[:, None] * (v[2] - v[0])


def fitted_cov(vs: VoxSplat):
    """(V, M, 3, 3) covariances R diag(s^2) R^T of the fitted Gaussians."""
    r, s = vs.rotations(), vs.scales()
    return np.einsum("...ij,...j,...kj->...ik", r, s * s, r)


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


# --- one Gaussian per voxel: closed-form moments ----------------------------------------------

def test_rectangle_fit_matches_closed_form_moments_exactly_with_patch_cov():
    centre = np.array([2.1, 1.9, 2.05])  # inside voxel (0, 0, 0) of a 4 m grid
    pts, w, pc = rectangle(1.2, 0.5, 24, 10, ROT, centre)
    vs = fit_voxsplat(pts, 4.0, weights=w, patch_cov=pc, fit=FitOptions(gaussians_per_voxel=1))
    assert vs.num_voxels == 1 and vs.gaussians_per_voxel == 1 and vs.num_gaussians == 1
    np.testing.assert_array_equal(vs.ijk, [[0, 0, 0]])
    np.testing.assert_allclose(vs.means()[0, 0], centre, rtol=0, atol=1e-6)
    s = vs.scales()[0, 0]
    min_scale = 0.01 * 4.0  # documented default: 1 % of the voxel
    np.testing.assert_allclose(s, [min_scale, 0.5 / np.sqrt(12), 1.2 / np.sqrt(12)], rtol=1e-6)
    r = vs.rotations()[0, 0]
    # thin axis along the normal, the largest along the long side (up to sign)
    assert abs(r[:, 0] @ ROT[:, 2]) == pytest.approx(1.0, abs=1e-6)
    assert abs(r[:, 2] @ ROT[:, 0]) == pytest.approx(1.0, abs=1e-6)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-6)
    expected = ROT @ np.diag([1.2 ** 2 / 12, 0.5 ** 2 / 12, min_scale ** 2]) @ ROT.T  # normal = ROT[:, 2]
    np.testing.assert_allclose(fitted_cov(vs)[0, 0], expected, rtol=0, atol=2e-7)


def test_rectangle_grid_without_patch_cov_has_the_discrete_variance():
    # Cell centres alone: variance (w^2 / 12) (1 - 1 / n^2), a closed form of the discrete grid.
    pts, _, _ = rectangle(0.9, 0.3, 9, 3, centre=(0.5, 0.5, 0.5))
    vs = fit_voxsplat(pts, 1.0, fit=FitOptions(gaussians_per_voxel=1))
    s = np.sort(vs.scales()[0, 0])
    np.testing.assert_allclose(s[1:], [np.sqrt(0.09 / 12 * (1 - 1 / 9)), np.sqrt(0.81 / 12 * (1 - 1 / 81))],
                               rtol=1e-6)


def test_random_triangle_samples_fit_the_closed_form_triangle_moments():
    rng = np.random.default_rng(0)
    v = np.array([[0.4, 0.3, 1.0], [2.9, 0.8, 1.6], [1.2, 3.1, 2.5]])
    pts = uniform_in_triangle(v, 100_000, rng)
    vs = fit_voxsplat(pts, 4.0, fit=FitOptions(gaussians_per_voxel=1))
    c = v.mean(0)
    closed = triangle_cov(v)
    # the closed form itself, against the sample moments (numpy), and the fit against both
    np.testing.assert_allclose(np.cov(pts.T, bias=True), closed, rtol=0, atol=0.01 * np.abs(closed).max())
    np.testing.assert_allclose(vs.means()[0, 0], c, rtol=0, atol=0.01)
    n = unit(np.cross(v[1] - v[0], v[2] - v[0]))
    r, s = vs.rotations()[0, 0], vs.scales()[0, 0]
    assert abs(r[:, 0] @ n) == pytest.approx(1.0, abs=1e-6)
    assert s[0] == pytest.approx(0.04, rel=1e-6)  # exactly planar: clamped to min_scale
    in_plane = fitted_cov(vs)[0, 0] - s[0] ** 2 * np.outer(r[:, 0], r[:, 0])
    np.testing.assert_allclose(in_plane, closed, rtol=0, atol=0.015 * np.abs(closed).max())
    evals = np.linalg.eigvalsh(closed)
    np.testing.assert_allclose(s[1:] ** 2, evals[1:], rtol=0.02)


def test_triangle_from_four_midpoint_subtriangles_is_exact():
    # Midpoint subdivision: 4 similar sub-triangles of 1/4 area, each with 1/4 of the linear size.
    v = np.array([[0.2, 0.1, 0.3], [0.9, 0.2, 0.5], [0.3, 0.8, 0.7]])
    m01, m12, m20 = (v[0] + v[1]) / 2, (v[1] + v[2]) / 2, (v[2] + v[0]) / 2
    subs = np.array([[v[0], m01, m20], [m01, v[1], m12], [m20, m12, v[2]], [m01, m12, m20]])
    pts = subs.mean(1)
    table = cov6(np.stack([triangle_cov(t) for t in subs]))
    vs = fit_voxsplat(pts, 1.0, weights=np.ones(4), patch_cov=(table, np.arange(4)),
                      fit=FitOptions(gaussians_per_voxel=1))
    np.testing.assert_allclose(vs.means()[0, 0], v.mean(0), rtol=0, atol=1e-7)
    r, s = vs.rotations()[0, 0], vs.scales()[0, 0]
    in_plane = fitted_cov(vs)[0, 0] - s[0] ** 2 * np.outer(r[:, 0], r[:, 0])
    np.testing.assert_allclose(in_plane, triangle_cov(v), rtol=0, atol=1e-8)
    # one point at the centroid carrying the whole triangle's covariance gives the same
    one = fit_voxsplat(v.mean(0)[None], 1.0, patch_cov=(cov6(triangle_cov(v)), np.array([0])),
                       fit=FitOptions(gaussians_per_voxel=1))
    np.testing.assert_allclose(fitted_cov(one)[0, 0], fitted_cov(vs)[0, 0], rtol=0, atol=1e-8)


def test_weights_give_the_weighted_mean_and_covariance():
    p = np.array([[0.1, 0.2, 0.5], [0.7, 0.2, 0.5], [0.1, 0.8, 0.5]])
    w = np.array([1.0, 3.0, 2.0])
    vs = fit_voxsplat(p, 1.0, weights=w, fit=FitOptions(gaussians_per_voxel=1))
    mean = (w[:, None] * p).sum(0) / w.sum()
    np.testing.assert_allclose(vs.means()[0, 0], mean, rtol=0, atol=1e-7)
    d = p - mean
    cov = (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0) / w.sum()
    r, s = vs.rotations()[0, 0], vs.scales()[0, 0]
    np.testing.assert_allclose(fitted_cov(vs)[0, 0] - s[0] ** 2 * np.outer(r[:, 0], r[:, 0]), cov,
                               rtol=0, atol=1e-7)
    np.testing.assert_allclose(np.abs(r[:, 0]), [0, 0, 1], atol=1e-6)


def test_a_single_point_gives_an_isotropic_min_scale_gaussian_at_the_point():
    p = np.array([[1.3, -0.4, 7.9]])
    vs = fit_voxsplat(p, 0.5, fit=FitOptions(gaussians_per_voxel=1, min_scale=0.02))
    np.testing.assert_array_equal(vs.ijk, [[2, -1, 15]])
    np.testing.assert_allclose(vs.means()[0, 0], p[0], rtol=0, atol=1e-7)
    np.testing.assert_allclose(vs.scales()[0, 0], [0.02] * 3, rtol=1e-6)


# --- bisection into M clusters ------------------------------------------------------------------

def test_planar_rectangle_splits_two_by_two_into_quarter_moments():
    w, h = 0.8, 0.6
    centre = np.array([0.5, 0.5, 0.5])
    pts, wt, pc = rectangle(w, h, 40, 30, centre=centre)
    vs = fit_voxsplat(pts, 1.0, weights=wt, patch_cov=pc, fit=FitOptions(gaussians_per_voxel=4))
    assert vs.gaussians_per_voxel == 4 and vs.valid.all()
    means = vs.means()[0]
    order = np.lexsort((means[:, 1], means[:, 0]))
    expected = centre + np.array([[-w / 4, -h / 4, 0], [-w / 4, h / 4, 0], [w / 4, -h / 4, 0], [w / 4, h / 4, 0]])
    np.testing.assert_allclose(means[order], expected, rtol=0, atol=1e-6)
    s = np.sort(vs.scales()[0], axis=1)
    np.testing.assert_allclose(s, np.tile([0.01, (h / 2) / np.sqrt(12), (w / 2) / np.sqrt(12)], (4, 1)), rtol=1e-6)
    r = vs.rotations()[0]
    np.testing.assert_allclose(np.abs(r[:, 2, 0]), 1.0, atol=1e-6)  # normal = z
    # documented coverage: every cell corner of a quarter is inside its Gaussian's 3-sigma ellipse
    cov = fitted_cov(vs)[0]
    for g in range(4):
        q = means[g]
        sel = (np.sign(pts[:, 0] - centre[0]) == np.sign(q[0] - centre[0])) & \
              (np.sign(pts[:, 1] - centre[1]) == np.sign(q[1] - centre[1]))
        corners = np.concatenate([pts[sel] + [dx, dy, 0] for dx in (-0.01, 0.01) for dy in (-0.01, 0.01)])
        d = corners - q
        maha = np.sqrt(np.einsum("ni,ij,nj->n", d, np.linalg.inv(cov[g]), d))
        assert maha.max() < 3.0
    # law of total variance over the four equal-area quarters recovers the whole rectangle
    flat = cov - 0.01 ** 2 * np.einsum("gi,gj->gij", r[:, :, 0], r[:, :, 0])
    d = means - means.mean(0)
    total = (flat + np.einsum("gi,gj->gij", d, d)).mean(0)
    np.testing.assert_allclose(total, np.diag([w * w / 12, h * h / 12, 0.0]), rtol=0, atol=1e-7)


def test_m2_splits_along_the_long_axis():
    centre = np.array([0.5, 0.5, 0.5])
    pts, wt, pc = rectangle(0.3, 0.8, 6, 16, centre=centre)
    vs = fit_voxsplat(pts, 1.0, weights=wt, patch_cov=pc, fit=FitOptions(gaussians_per_voxel=2))
    means = vs.means()[0]
    np.testing.assert_allclose(np.sort(means[:, 1]), [0.3, 0.7], atol=1e-6)
    np.testing.assert_allclose(means[:, 0], 0.5, atol=1e-6)
    np.testing.assert_allclose(np.sort(vs.scales()[0], axis=1)[:, 1:],
                               np.tile([0.3 / np.sqrt(12), 0.4 / np.sqrt(12)], (2, 1)), rtol=1e-6)


def test_eight_clusters_of_a_triangle_are_distinct_flat_gaussians_in_its_plane():
    rng = np.random.default_rng(1)
    v = np.array([[0.1, 0.2, 0.3], [1.8, 0.4, 0.9], [0.6, 1.7, 1.4]])
    pts = uniform_in_triangle(v, 4000, rng)
    vs = fit_voxsplat(pts, 2.0, fit=FitOptions(gaussians_per_voxel=8, min_scale=1e-9))
    assert vs.num_gaussians == 8
    n = unit(np.cross(v[1] - v[0], v[2] - v[0]))
    m = vs.means()[0]
    np.testing.assert_allclose((m - v[0]) @ n, 0.0, atol=1e-6)
    assert np.unique(np.round(m, 6), axis=0).shape[0] == 8
    np.testing.assert_allclose(m.mean(0), pts.mean(0), atol=0.05)  # roughly equal-size clusters
    r = vs.rotations()[0]
    np.testing.assert_allclose(np.abs(r[:, :, 0] @ n), 1.0, atol=1e-5)


def test_empty_clusters_become_invalid_transparent_identity_slots():
    p = np.array([[0.25, 0.25, 0.25], [1.5, 0.5, 0.5], [1.6, 0.5, 0.5]])
    vs = fit_voxsplat(p, 1.0, fit=FitOptions(gaussians_per_voxel=4))
    assert vs.num_voxels == 2
    counts = {tuple(ijk): int(n) for ijk, n in zip(vs.ijk.tolist(), vs.valid.sum(1))}
    assert counts == {(0, 0, 0): 1, (1, 0, 0): 2}
    inv = ~vs.valid
    assert np.all(vs.opacities()[inv] < 1e-12)
    np.testing.assert_array_equal(vs.quats()[inv], np.tile([1.0, 0, 0, 0], (int(inv.sum()), 1)))
    assert np.all(np.isfinite(vs.params))


def test_order_of_the_points_does_not_change_the_fit():
    rng = np.random.default_rng(2)
    v = np.array([[0.1, 0.2, 0.3], [1.8, 0.4, 0.9], [0.6, 1.7, 1.4]])
    pts = uniform_in_triangle(v, 3000, rng)
    a = fit_voxsplat(pts, 1.0, fit=FitOptions(gaussians_per_voxel=4))
    b = fit_voxsplat(pts[rng.permutation(len(pts))], 1.0, fit=FitOptions(gaussians_per_voxel=4))
    np.testing.assert_array_equal(a.ijk, b.ijk)
    np.testing.assert_array_equal(a.valid.sum(1), b.valid.sum(1))
    for vi in range(a.num_voxels):
        ma, mb = a.means()[vi][a.valid[vi]], b.means()[vi][b.valid[vi]]
        oa, ob = np.lexsort(ma.T[::-1]), np.lexsort(mb.T[::-1])
        np.testing.assert_allclose(ma[oa], mb[ob], atol=1e-6)
        ca, cb = fitted_cov(a)[vi][a.valid[vi]], fitted_cov(b)[vi][b.valid[vi]]
        np.testing.assert_allclose(ca[oa], cb[ob], atol=1e-6)


# --- voxels, frames, attributes ---------------------------------------------------------------

def test_points_are_binned_by_floor_and_each_voxel_fits_its_own_part():
    pts, wt, pc = rectangle(1.0, 0.4, 50, 20, centre=(1.0, 0.5, 0.5))  # straddles x = 1
    vs = fit_voxsplat(pts, 1.0, weights=wt, patch_cov=pc, fit=FitOptions(gaussians_per_voxel=1))
    assert sorted(map(tuple, vs.ijk.tolist())) == [(0, 0, 0), (1, 0, 0)]
    for ijk, mean, s in zip(vs.ijk, vs.means()[:, 0], np.sort(vs.scales()[:, 0], axis=1)):
        np.testing.assert_allclose(mean, [0.75 if ijk[0] == 0 else 1.25, 0.5, 0.5], atol=1e-6)
        np.testing.assert_allclose(s, [0.01, 0.4 / np.sqrt(12), 0.5 / np.sqrt(12)], rtol=1e-6)
    assert np.unique(vs.ijk, axis=0).shape[0] == vs.num_voxels


def test_origin_is_carried_and_world_means_are_points_plus_origin():
    origin = np.array([4.0e5, 5.5e6, -12.0])
    pts, wt, pc = rectangle(0.4, 0.2, 8, 4, ROT, centre=(0.5, 0.5, 0.5))
    vs = fit_voxsplat(pts, 1.0, weights=wt, patch_cov=pc, origin=origin, fit=FitOptions(gaussians_per_voxel=1))
    assert vs.origin.dtype == np.float64
    np.testing.assert_array_equal(vs.origin, origin)
    np.testing.assert_allclose(vs.world_means()[0], origin + [0.5, 0.5, 0.5], rtol=0, atol=1e-6)


def test_moments_stay_accurate_for_points_far_from_the_local_origin():
    # Local coordinates of ~5e5 m: an uncentred E[x^2] - E[x]^2 would lose ~1e-4 m^2 here.
    far = np.array([5.0e5 + 0.5, 3.0e5 + 0.5, 0.5])
    pts, wt, pc = rectangle(0.6, 0.3, 30, 15, ROT, centre=far)
    vs = fit_voxsplat(pts, 1.0, weights=wt, patch_cov=pc, fit=FitOptions(gaussians_per_voxel=1))
    np.testing.assert_array_equal(vs.ijk, [[500000, 300000, 0]])
    np.testing.assert_allclose(vs.means()[0, 0], far, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.sort(vs.scales()[0, 0]), [0.01, 0.3 / np.sqrt(12), 0.6 / np.sqrt(12)], rtol=1e-6)
    assert abs(vs.rotations()[0, 0][:, 0] @ ROT[:, 2]) == pytest.approx(1.0, abs=1e-6)


def test_scales_are_positive_rotations_proper_and_opacity_as_requested():
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 3, (2000, 3))
    vs = fit_voxsplat(pts, 1.0, fit=FitOptions(gaussians_per_voxel=4, opacity=0.9))
    sel = vs.valid
    assert np.all(vs.scales()[sel] > 0)
    assert np.all(vs.scales()[sel] >= 0.01 * (1 - 1e-6))
    np.testing.assert_allclose(np.linalg.det(vs.rotations()[sel]), 1.0, atol=1e-5)
    np.testing.assert_allclose(vs.opacities()[sel], 0.9, rtol=1e-6)
    np.testing.assert_allclose(expit(vs.params[..., 3][sel].astype(float)), 0.9, rtol=1e-6)
    # means stay within their voxel's reach (offset range 3 voxels), here within the voxel itself
    centres = vs.voxel_centers()[:, None, :].repeat(4, 1)
    assert np.all(np.abs(vs.means() - centres)[sel] <= 0.5 + 1e-6)
    vs.check_finite()


def test_min_scale_floors_every_axis_and_max_normal_scale_caps_the_thin_one():
    rng = np.random.default_rng(4)
    n = 5000
    pts = np.c_[rng.uniform(0.2, 0.8, n), rng.uniform(0.3, 0.7, n), 0.5 + rng.normal(0, 0.05, n)]
    free = np.sort(fit_voxsplat(pts, 1.0, fit=FitOptions(gaussians_per_voxel=1)).scales()[0, 0])
    assert free[0] == pytest.approx(0.05, rel=0.05)  # the noise shows without a cap
    capped = fit_voxsplat(pts, 1.0, fit=FitOptions(gaussians_per_voxel=1, max_normal_scale=0.01))
    s = np.sort(capped.scales()[0, 0])
    assert s[0] == pytest.approx(0.01, rel=1e-6)
    np.testing.assert_allclose(s[1:], free[1:], rtol=1e-6)  # in-plane axes untouched
    assert abs(capped.rotations()[0, 0][2, 0]) == pytest.approx(1.0, abs=1e-3)
    floored = fit_voxsplat(pts, 1.0, fit=FitOptions(gaussians_per_voxel=1, min_scale=0.5))
    np.testing.assert_allclose(floored.scales()[0, 0], [0.5, 0.5, 0.5], rtol=1e-6)


def test_colours_are_the_weighted_mean_colour_of_each_cluster():
    p = np.array([[0.2, 0.5, 0.5], [0.3, 0.5, 0.5], [1.5, 0.5, 0.5]])
    c = np.array([[1.0, 0.0, 0.2], [0.0, 1.0, 0.6], [0.25, 0.5, 0.75]])
    w = np.array([1.0, 3.0, 1.0])
    vs = fit_voxsplat(p, 1.0, colors=c, weights=w, fit=FitOptions(gaussians_per_voxel=1))
    got = {tuple(ijk): col for ijk, col in zip(vs.ijk.tolist(), vs.colors()[:, 0])}
    np.testing.assert_allclose(got[(0, 0, 0)], [0.25, 0.75, 0.5], atol=1e-6)
    np.testing.assert_allclose(got[(1, 0, 0)], [0.25, 0.5, 0.75], atol=1e-6)
    # no colours given: the neutral SH term (grey)
    grey = fit_voxsplat(p, 1.0, fit=FitOptions(gaussians_per_voxel=1))
    np.testing.assert_allclose(grey.colors()[:, 0], 0.5, atol=1e-7)


def test_voxel_label_is_the_majority_with_ties_to_the_smaller_id_and_weighted_by_area():
    p = np.array([[0.1, 0.1, 0.1], [0.2, 0.1, 0.1], [0.3, 0.1, 0.1],   # voxel 0: 5, 5, 9 -> 5
                  [1.1, 0.1, 0.1], [1.2, 0.1, 0.1],                      # voxel 1: 8, 4 tie -> 4
                  [2.1, 0.1, 0.1], [2.2, 0.1, 0.1], [2.3, 0.1, 0.1]])    # voxel 2: 6, 6, 3 (w 5) -> 3
    labels = np.array([5, 5, 9, 8, 4, 6, 6, 3])
    w = np.array([1, 1, 1, 1, 1, 1, 1, 5.0])
    vs = fit_voxsplat(p, 1.0, labels=labels, weights=w, fit=FitOptions(gaussians_per_voxel=1))
    got = {ijk[0]: int(lb) for ijk, lb in zip(vs.ijk.tolist(), vs.labels)}
    assert got == {0: 5, 1: 4, 2: 3}
    assert vs.labels.dtype == np.int16
    assert fit_voxsplat(p, 1.0, fit=FitOptions(gaussians_per_voxel=1)).labels.tolist() == [0, 0, 0]


def test_min_points_drops_sparse_voxels_and_keeps_attributes_aligned():
    p = np.array([[0.1, 0.5, 0.5], [0.9, 0.5, 0.5],                        # voxel 0: 2 points
                  [1.2, 0.5, 0.5], [1.4, 0.5, 0.5], [1.6, 0.5, 0.5],         # voxel 1: 3 points
                  [2.5, 0.5, 0.5]])                                          # voxel 2: 1 point
    labels = np.array([1, 1, 7, 7, 2, 3])
    colors = np.array([[1.0, 1, 1], [1, 1, 1], [0.2, 0.4, 0.6], [0.2, 0.4, 0.6], [0.2, 0.4, 0.6], [0, 0, 0]])
    pc = (cov6(np.eye(3) * 1e-4)[[0, 0, 0, 0, 0, 0]] * np.arange(1, 7)[:, None], np.arange(6))
    vs = fit_voxsplat(p, 1.0, labels=labels, colors=colors, patch_cov=pc,
                      fit=FitOptions(gaussians_per_voxel=1, min_points=3))
    np.testing.assert_array_equal(vs.ijk, [[1, 0, 0]])
    assert vs.labels.tolist() == [7]
    np.testing.assert_allclose(vs.colors()[0, 0], [0.2, 0.4, 0.6], atol=1e-6)
    np.testing.assert_allclose(vs.means()[0, 0], [1.4, 0.5, 0.5], atol=1e-7)
    # the spread of x plus the mean patch covariance of points 3..5 (1e-4 * (3 + 4 + 5) / 3)
    extra = 1e-4 * 4.0
    var_x = np.var([1.2, 1.4, 1.6]) + extra
    np.testing.assert_allclose(np.sort(vs.scales()[0, 0] ** 2), [extra, extra, var_x], rtol=1e-5)


@pytest.mark.parametrize("m", [0, 3, 6, -4])
def test_gaussians_per_voxel_must_be_a_power_of_two(m):
    with pytest.raises(ValueError, match="power of two"):
        fit_voxsplat(np.zeros((3, 3)), 1.0, fit=FitOptions(gaussians_per_voxel=m))


@pytest.mark.parametrize("size", [0.0, -1.0, np.nan])
def test_voxel_size_must_be_positive(size):
    with pytest.raises(ValueError, match="voxel_size"):
        fit_voxsplat(np.zeros((3, 3)), size)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_points_are_rejected(bad):
    p = np.zeros((4, 3))
    p[2, 1] = bad
    with pytest.raises(ValueError, match="NaN or Inf"):
        fit_voxsplat(p, 1.0)


def test_fit_is_deterministic_and_round_trips_through_the_file(tmp_path):
    rng = np.random.default_rng(5)
    pts = uniform_in_triangle(np.array([[0.0, 0, 0], [3, 0.5, 1], [1, 2.5, 2]]), 2000, rng)
    a = fit_voxsplat(pts, 0.5)
    b = fit_voxsplat(pts.copy(), 0.5)
    assert a.params.tobytes() == b.params.tobytes()
    back = VoxSplat.load(a.save(tmp_path / "fit.npz"))
    assert back.params.tobytes() == a.params.tobytes()
    np.testing.assert_array_equal(back.ijk, a.ijk)
