"""Stereo's gap filling (step 9, `fill_gaps`): an unsure band on a plane takes the plane's depth
(a plane's inverse depth is linear along any line of pixels), a depth step and sky stay unfilled,
and gaps wider than the bound stay holes."""

from __future__ import annotations

import numpy as np

from scube_sim.reconstruct.stereo.gaps import fill_gaps

H, W, F, CX, CY = 40, 60, 50.0, 30.0, 20.0


def plane_depth(normal, offset) -> np.ndarray:
    """(H, W) camera-z depth of the plane n . X = offset seen by a pinhole (F, CX, CY)."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = np.stack([(u - CX) / F, (v - CY) / F, np.ones_like(u)], -1)
    return (offset / (rays @ np.asarray(normal, float))).astype(np.float32)


def test_an_unsure_band_on_a_tilted_plane_takes_the_plane_s_depth():
    truth = plane_depth([0.3, -0.2, 1.0], 12.0)  # 9-16 m, sloping both ways
    conf = np.ones((H, W), np.float32)
    conf[10:18, 20:30] = 0  # a textureless patch, 8 rows x 10 columns
    depth = np.where(conf > 0, truth, np.nan).astype(np.float32)
    d, c = fill_gaps(depth, conf, max_gap_px=12, tol=0.2)
    hole = conf == 0
    np.testing.assert_allclose(d[hole], truth[hole], rtol=1e-5)
    assert np.all(c[hole] == np.float32(1.0))  # its ends' confidence
    assert np.array_equal(d[~hole], depth[~hole]) and np.array_equal(c[~hole], conf[~hole])


def test_a_depth_step_a_wide_gap_and_sky_stay_holes():
    near, far = plane_depth([0, 0, 1], 5.0), plane_depth([0, 0, 1], 30.0)
    truth = np.where(np.arange(W) < 25, near, far)  # a pole's edge at column 25
    conf = np.ones((H, W), np.float32)
    conf[:, 20:30] = 0  # the unsure band straddles the step: left end 5 m, right end 30 m
    conf[30:, :] = 0  # and the bottom rows are unsure with nothing below them
    depth = np.where(conf > 0, truth, np.nan).astype(np.float32)
    d, c = fill_gaps(depth, conf, max_gap_px=12, tol=0.03)
    assert np.isnan(d[:30, 20:30]).all() and (c[:30, 20:30] == 0).all()  # never across the step
    assert np.isnan(d[30:]).all()  # no confident pixel below: no column gap, and rows are all unsure
    # the same plane, a gap wider than the bound
    conf2 = np.ones((H, W), np.float32)
    conf2[:, 10:40] = 0  # 30 columns
    d2, _ = fill_gaps(np.where(conf2 > 0, far, np.nan).astype(np.float32), conf2, 12, 0.03)
    assert np.isnan(d2[:, 10:40]).all()
    # sky is never filled, even between two agreeing walls
    conf3 = np.ones((H, W), np.float32)
    conf3[5:10, 20:25] = 0
    sky = np.zeros((H, W), bool)
    sky[5:10, 20:25] = True
    d3, _ = fill_gaps(np.where(conf3 > 0, far, np.nan).astype(np.float32), conf3, 12, 0.03, ~sky)
    assert np.isnan(d3[sky]).all()


def test_stereo_fills_a_textureless_stripe_on_the_plane(monkeypatch):
    """Through `stereo_depth`: a 2 m uniform grey stripe painted on the textured plane 10 m away
    (24 px wide) leaves stereo unsure on most of it (measured: 41 % confident); `fill_gap_deg` 15
    (31 px) gives all of it the plane's depth (median 0.33 %, at most 2 % off)."""
    import tests.reconstruct.stereo.test_mvs as tm
    from scube_sim.reconstruct.stereo import stereo_depth
    from tests.reconstruct.stereo.test_sweep import _pose

    plain = tm._texture

    def striped(x, y, seed):
        rgb = plain(x, y, seed)
        return np.where((np.abs(x - 0.3) < 1.0)[..., None], 0.5, rgb)

    monkeypatch.setattr(tm, "_texture", striped)
    ref, gt = tm._shot("ref", _pose(), 0.0)
    left, _ = tm._shot("cam", _pose((-1.0, 0.2, 0.0)), -0.1)
    right, _ = tm._shot("cam", _pose((1.0, -0.1, 0.0)), 0.1)
    frames = tm._frames(ref, {-1: [left], 1: [right]})
    rows = slice(10, tm.H - 10)
    cols = (np.arange(tm.W) + 0.5 - tm.W / 2) / tm.F * tm.PLANE_Z  # each column's x on the plane
    stripe = np.zeros((tm.H, tm.W), bool)
    stripe[rows, np.abs(cols - 0.3) < 0.9] = True  # its inner columns
    plain_res = stereo_depth(frames, 0, tm.CFG)
    assert (plain_res.confidence[stripe] >= 0.5).mean() < 0.6  # mostly unsure without filling
    res = stereo_depth(frames, 0, tm.CFG.model_copy(update={"fill_gap_deg": 15.0}))
    assert (res.confidence[stripe] >= 0.5).mean() > 0.95
    rel = np.abs(res.depth[stripe] - gt[stripe]) / gt[stripe]
    assert np.nanmedian(rel) < 0.005 and np.nanmax(rel) < 0.025, (np.nanmedian(rel), np.nanmax(rel))
    sure = plain_res.confidence > 0
    assert np.array_equal(res.depth[sure], plain_res.depth[sure])  # confident pixels keep theirs


def test_weak_pixels_in_a_band_are_filled_and_are_no_ends():
    """With weak pixels (`StereoConfig.weak_agreement`), a pixel at or below `sure_above` is unsure:
    it neither ends a run nor keeps its own depth where confident ends agree around it."""
    truth = plane_depth([0.3, -0.2, 1.0], 12.0)
    conf = np.ones((H, W), np.float32)
    conf[10:18, 20:30] = 0
    conf[12:14, 24:26] = 0.4  # weak pixels inside the band, their depth a wrong match
    depth = np.where(conf > 0, truth, np.nan).astype(np.float32)
    depth[12:14, 24:26] = 40.0
    d, c = fill_gaps(depth, conf, max_gap_px=12, tol=0.2, sure_above=0.45)
    hole = conf < 1
    np.testing.assert_allclose(d[hole], truth[hole], rtol=1e-5)
    assert np.all(c[hole] == np.float32(1.0))
    # the default (sure_above 0): the weak pixels are ends and keep their wrong depth
    d0, _ = fill_gaps(depth, conf, max_gap_px=12, tol=0.2)
    assert np.all(d0[12:14, 24:26] == 40.0)


def test_an_oblique_plane_s_band_fills_only_where_its_ends_lie_in_line():
    """A band on a plane seen obliquely: its ends' depths differ by more than the tolerance (6.6 %
    along rows, 3.6 % along columns, against 3 %), so the ends alone leave it a hole; with
    `coplanar` the line through the ends also meets the confident pixels beyond them, and the band
    takes the plane's depth. Across a depth step (a pole before a wall) the line misses the pixels
    beyond the ends, and the band stays a hole."""
    truth = plane_depth([0.3, -0.2, 1.0], 12.0)
    conf = np.ones((H, W), np.float32)
    conf[10:18, 20:30] = 0
    depth = np.where(conf > 0, truth, np.nan).astype(np.float32)
    hole = conf == 0
    d0, _ = fill_gaps(depth, conf, max_gap_px=12, tol=0.03)
    assert np.isnan(d0[hole]).all()
    d, c = fill_gaps(depth, conf, max_gap_px=12, tol=0.03, coplanar=0.5)
    np.testing.assert_allclose(d[hole], truth[hole], rtol=1e-5)
    assert np.all(c[hole] == np.float32(1.0))
    assert np.array_equal(d[~hole], depth[~hole]) and np.array_equal(c[~hole], conf[~hole])
    # the line must reach sure pixels beyond both ends: a band from top to bottom (no column
    # gaps) 2 pixels from the image's left edge has none 5 pixels beyond its left end
    edge = np.ones((H, W), np.float32)
    edge[:, 2:12] = 0
    de, _ = fill_gaps(np.where(edge > 0, truth, np.nan).astype(np.float32), edge, 12, 0.03, coplanar=0.5)
    assert np.isnan(de[:, 2:12]).all()
    # a pole's edge at column 25 before a wall: 5 m ends left, 30 m right, nothing in line
    step = np.where(np.arange(W) < 25, plane_depth([0, 0, 1], 5.0), plane_depth([0, 0, 1], 30.0))
    cs = np.ones((H, W), np.float32)
    cs[:, 20:30] = 0
    ds, _ = fill_gaps(np.where(cs > 0, step, np.nan).astype(np.float32), cs, 12, 0.03, coplanar=0.5)
    assert np.isnan(ds[:, 20:30]).all()
