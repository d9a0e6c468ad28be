"""Evidence fusion (`model.geometry.fusion`): exact depth of an analytic plane lands in the voxels
on it; a later confident view carves a surface it sees through; low confidence gives no evidence;
unsure pixels make a surface only where two views agree, and carve nothing; bad input names the
image."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.errors import InputError
from scube_sim.model.geometry.fusion import DepthObservation, FusionConfig, fuse_depth
from tests.stereo.test_mvs import PLANE_Z, _shot
from tests.stereo.test_sweep import _pose

VS = 0.2


def _centres(grid) -> np.ndarray:
    return grid.origin + (grid.ijk + 0.5) * grid.voxel_size


def test_exact_depth_of_a_plane_fills_the_voxels_on_it():
    obs = []
    for centre in ((0.0, 0.0, 0.0), (1.0, 0.2, 0.0)):
        im, depth = _shot("cam", _pose(centre), 0.0)
        obs.append(DepthObservation(im, depth, np.ones_like(depth)))
    grid = fuse_depth(obs, FusionConfig(voxel_size=VS))
    z = _centres(grid)[:, 2]
    # the plane z = 10 is a voxel boundary: its points fall in the layer [10, 10.2)
    assert np.all(np.abs(z - (PLANE_Z + VS / 2)) < 1e-9)
    # the layer is covered where the cameras see it: 128 x 96 px at f 120 over 10 m is 10.7 x 8 m,
    # the second camera adds a 1 x 8 m strip: about 88 m^2 / 0.04 = 2200 voxels
    assert 2000 < len(grid.ijk) < 2500, len(grid.ijk)
    assert grid.carved.shape == (0, 3)  # nothing stands in front of the plane
    assert np.all(grid.hits >= 1) and np.all(grid.misses == 0)
    # every point lies in its own voxel
    inside = np.floor((grid.points - grid.origin) / VS).astype(np.int64)
    np.testing.assert_array_equal(inside, grid.ijk[grid.voxel])


def _wall(depth_m: float, confidence: float, centre=(0.0, 0.0, 0.0)):
    """A camera whose depth says a fronto-parallel wall at `depth_m` over its central quarter."""
    im, _ = _shot("cam", _pose(centre), 0.0)
    h, w = im.image.shape[:2]
    depth = np.full((h, w), np.nan, np.float32)
    conf = np.zeros((h, w), np.float32)
    depth[h // 4: 3 * h // 4, w // 4: 3 * w // 4] = depth_m
    conf[h // 4: 3 * h // 4, w // 4: 3 * w // 4] = confidence
    return DepthObservation(im, depth, conf)


def test_a_later_confident_view_carves_a_surface_it_sees_through():
    cfg = FusionConfig(voxel_size=VS)
    phantom = _wall(5.0, 0.6)
    alone = fuse_depth([phantom], cfg)
    assert len(alone.ijk) > 100 and np.all(np.abs(_centres(alone)[:, 2] - 5.1) < 1e-9)
    later = _wall(10.0, 0.9, centre=(0.3, 0.0, 0.0))
    both = fuse_depth([phantom, later], cfg)
    z = _centres(both)[:, 2]
    # the phantom's voxels the second view's rays cross (about 89 % of them: its view at 5 m is
    # shifted 0.3 m sideways) are carved; the others stay
    front = z < 9.0
    assert len(both.carved) > 0.8 * len(alone.ijk), (len(both.carved), len(alone.ijk))
    assert front.sum() < 0.2 * len(alone.ijk)
    assert (np.abs(z - 10.1) < 1e-9).sum() > 100  # the wall behind stands
    # one weaker miss does not outweigh a stronger hit
    weak = fuse_depth([_wall(5.0, 0.9), _wall(10.0, 0.5, centre=(0.3, 0.0, 0.0))], cfg)
    assert (np.abs(_centres(weak)[:, 2] - 5.1) < 1e-9).sum() > 0.8 * len(alone.ijk)


def test_pixels_below_the_confidence_floor_give_no_evidence():
    grid = fuse_depth([_wall(5.0, 0.49)], FusionConfig(voxel_size=VS, min_confidence=0.5))
    assert len(grid.ijk) == 0 and len(grid.points) == 0


def test_unsure_pixels_make_a_surface_only_where_two_views_agree():
    cfg = FusionConfig(voxel_size=VS, weak_confidence=0.2, weak_views=2)
    one = fuse_depth([_wall(5.0, 0.3)], cfg)
    assert len(one.ijk) == 0  # one unsure view alone: no surface
    two = fuse_depth([_wall(5.0, 0.3), _wall(5.0, 0.3, centre=(0.3, 0.0, 0.0))], cfg)
    z = _centres(two)[:, 2]
    # the two views overlap over about 89 % of the first one's wall (its 5.3 m x 4 m at 5 m is
    # shifted 0.3 m): only the voxels both hit are occupied, all on the wall's layer
    assert len(two.ijk) > 0.8 * len(fuse_depth([_wall(5.0, 0.9)], FusionConfig(voxel_size=VS)).ijk)
    assert np.all(np.abs(z - 5.1) < 1e-9)
    assert np.all(two.hits >= 2)
    # two views that disagree by a metre (a wrong match lands elsewhere in each) make nothing
    apart = fuse_depth([_wall(5.0, 0.3), _wall(6.0, 0.3, centre=(0.3, 0.0, 0.0))], cfg)
    assert len(apart.ijk) == 0
    # off (the default): the same two views give no evidence
    assert len(fuse_depth([_wall(5.0, 0.3), _wall(5.0, 0.3, centre=(0.3, 0.0, 0.0))],
                          FusionConfig(voxel_size=VS)).ijk) == 0


def test_unsure_pixels_carve_nothing():
    cfg = FusionConfig(voxel_size=VS, weak_confidence=0.2)
    sure = _wall(5.0, 0.6)
    # two unsure views agreeing on a wall behind the confident one: their rays cross it, yet it stays
    grid = fuse_depth([sure, _wall(10.0, 0.3, centre=(0.3, 0.0, 0.0)), _wall(10.0, 0.3, centre=(0.6, 0.0, 0.0))], cfg)
    alone = fuse_depth([sure], cfg)
    z = _centres(grid)[:, 2]
    assert (np.abs(z - 5.1) < 1e-9).sum() == len(alone.ijk)
    assert not np.any(grid.carved[:, 2] == 25)  # none of the wall's layer [5, 5.2) is carved
    assert (np.abs(z - 10.1) < 1e-9).sum() > 100  # and the wall behind, where both unsure views hit it
    # a confident view at 10 m through the same wall does carve it (as without unsure pixels)
    carved = fuse_depth([sure, _wall(10.0, 0.9, centre=(0.3, 0.0, 0.0))], cfg)
    assert len(carved.carved) > 0.8 * len(alone.ijk)


def test_bad_maps_are_refused_naming_the_image():
    obs = _wall(5.0, 0.9)
    with pytest.raises(InputError, match="'cam'.*depth"):
        fuse_depth([DepthObservation(obs.image, obs.depth[:-1], obs.confidence)])
    with pytest.raises(InputError, match="'cam'.*confidence"):
        fuse_depth([DepthObservation(obs.image, obs.depth, obs.confidence * 2)])


def test_the_surfels_of_a_fused_plane_trace_in_entry_mode_at_its_range():
    from scube_sim.model.geometry.fusion import evidence_voxsplat
    from scube_sim.raytrace.tracer import Tracer

    im, depth = _shot("cam", _pose(), 0.0)
    grid = fuse_depth([DepthObservation(im, depth, np.full_like(depth, 0.8))], FusionConfig(voxel_size=VS))
    vs = evidence_voxsplat(grid)
    assert vs.num_voxels == len(grid.ijk)
    np.testing.assert_allclose(vs.channels["confidence"].data, 1 / (1 + np.exp(-0.85 * 0.8)), rtol=1e-6)
    assert vs.channels["observed"].data.all()
    # rays from the camera at the plane z = 10 (away from the edges of its view)
    ang = np.deg2rad(np.linspace(-20, 20, 9))
    dirs = np.stack([np.sin(ang), np.zeros_like(ang), np.cos(ang)], 1)
    hits = Tracer(vs, mode="entry").trace_world(np.zeros((len(ang), 3)), dirs)
    assert hits.hit.all()
    expected = PLANE_Z / np.cos(ang)
    # flat surfels, each pixel's footprint closing the gaps between them: the entry shell (3 sigma
    # along the normal, sigma at its floor of 1 % of a voxel) sits at most 6 mm before the plane
    err = hits.t - expected
    assert np.all((err > -0.006 / np.cos(ang) - 1e-6) & (err <= 0)), err
