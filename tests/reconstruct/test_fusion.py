"""Evidence fusion (`reconstruct.fusion`): exact depth of an analytic plane lands in the voxels
on it; a later confident view carves a surface it sees through; low confidence gives no evidence;
unsure pixels make a surface only where two views agree, and carve nothing; bad input names the
image; the compiled carving walk counts the voxels a ray crosses as the NumPy walk does, to the bit."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.boxes import Box
from scube_sim.errors import InputError
from scube_sim.raytrace import compiled
from scube_sim.reconstruct.config import FusionConfig
from scube_sim.reconstruct.fusion import DepthObservation, _misses, fuse_depth
from scube_sim.voxsplat import voxel_keys
from tests.raytrace.engines import require_compiled
from tests.reconstruct.stereo.test_mvs import PLANE_Z, _shot
from tests.reconstruct.stereo.test_sweep import _pose

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


def test_rays_carve_nothing_inside_the_boxes_they_are_told_to_leave():
    # the later view's rays pass where a moving object stands at the instant fused: its box, the
    # right half of the phantom's layer (x >= 0), is left alone; the left half is carved as before
    cfg = FusionConfig(voxel_size=VS)
    phantom, later = _wall(5.0, 0.6), _wall(10.0, 0.9, centre=(0.3, 0.0, 0.0))
    box = Box(np.array([5.0, 0.0, 5.1]), np.array([10.0, 20.0, 0.4]), np.eye(3))

    def layer(grid, right: bool) -> int:
        c = _centres(grid)
        return int(((np.abs(c[:, 2] - 5.1) < 1e-9) & ((c[:, 0] >= 0) == right)).sum())

    alone = fuse_depth([phantom], cfg)
    carved = fuse_depth([phantom, later], cfg)
    kept = fuse_depth([phantom, DepthObservation(later.image, later.depth, later.confidence, (box,))], cfg)
    assert layer(alone, True) > 50 and layer(carved, False) < 0.3 * layer(alone, False)
    assert layer(kept, True) == layer(alone, True)
    assert layer(kept, False) == layer(carved, False)
    assert (np.abs(_centres(kept)[:, 2] - 10.1) < 1e-9).sum() > 100  # the wall behind stands


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
    from scube_sim.raytrace.tracer import Tracer
    from scube_sim.reconstruct.surfels import evidence_voxsplat

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


def test_ground_points_snapped_onto_the_height_field_trace_at_the_plane_and_a_kerb_keeps_its_step():
    from scube_sim.raytrace.tracer import Tracer
    from scube_sim.reconstruct.config import GROUND_LABEL
    from scube_sim.reconstruct.ground import flat_height_field
    from scube_sim.reconstruct.surfels import evidence_voxsplat, snap_ground

    im, depth = _shot("cam", _pose(), 0.0)
    h, w = depth.shape
    # stereo-like noise, +-12 cm at 10 m, over the plane; the image's left quarter a step 0.35 m
    # beyond it (a kerb in this frame, whose "up" is the camera's z), measured exactly. The voxels
    # start 0.1 m off the plane: it lies mid-layer, the noise reaching the layers either side
    noisy = depth * (1 + np.random.default_rng(0).uniform(-0.012, 0.012, depth.shape)).astype(np.float32)
    kerb = np.zeros((h, w), bool)
    kerb[:, : w // 4] = True
    noisy[kerb] = depth[kerb] * (PLANE_Z + 0.35) / PLANE_Z
    grid = fuse_depth([DepthObservation(im, noisy, np.full_like(depth, 0.8))], FusionConfig(voxel_size=VS),
                      origin=np.array([0.0, 0.0, 0.1]))
    layers = set(np.round(_centres(grid)[:, 2], 6))
    assert {PLANE_Z - VS, PLANE_Z, PLANE_Z + VS} <= layers  # the noise spread the plane over 3 layers
    field = flat_height_field((-20.0, 20.0, -20.0, 20.0), cell=1.0, z=PLANE_Z)
    snapped, moved = snap_ground(grid, np.full(len(grid.points), GROUND_LABEL), field, 0.2)
    on_kerb = grid.points[:, 2] > PLANE_Z + 0.25
    np.testing.assert_array_equal(moved, ~on_kerb)
    assert 0.2 < on_kerb.mean() < 0.3
    np.testing.assert_allclose(snapped.points[~on_kerb, 2], PLANE_Z, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(snapped.points[on_kerb], grid.points[on_kerb])
    np.testing.assert_array_equal(snapped.points[:, :2], grid.points[:, :2])
    assert np.all(snapped.patch[~on_kerb][:, [2, 4, 5]] == 0)
    trace = lambda p: p[:, 0] + p[:, 3] + p[:, 5]  # noqa: E731
    np.testing.assert_allclose(trace(snapped.patch[~on_kerb]), trace(grid.patch[~on_kerb]), rtol=1e-5)
    # points that left their voxels are still observed, with their voxels' confidence
    vs = evidence_voxsplat(snapped)
    centres_z = 0.1 + (vs.ijk[:, 2] + 0.5) * VS
    assert set(np.round(centres_z, 6)) == {PLANE_Z, PLANE_Z + 0.4}
    assert vs.channels["observed"].data.all()
    np.testing.assert_allclose(vs.channels["confidence"].data, 1 / (1 + np.exp(-0.85 * 0.8)), rtol=1e-6)
    # rays over the plane hit it within the entry shell (as exact depth does), not the noise's
    # +-12 cm; rays into the kerb hit its step
    ang = np.deg2rad(np.array([-24.0, -22.0, -5.0, 0.0, 10.0, 20.0]))
    dirs = np.stack([np.sin(ang), np.zeros_like(ang), np.cos(ang)], 1)
    expected = np.where(ang < np.deg2rad(-16), PLANE_Z + 0.35, PLANE_Z) / np.cos(ang)
    hits = Tracer(vs, mode="entry").trace_world(np.zeros((len(ang), 3)), dirs)
    assert hits.hit.all()
    err = hits.t - expected
    assert np.all((err > -0.006 / np.cos(ang) - 1e-6) & (err <= 1e-6)), err
    # unsnapped, the noise shows: ranges centimetres off, or a ray slipping between tilted surfels
    raw = Tracer(evidence_voxsplat(grid), mode="entry").trace_world(np.zeros((len(ang), 3)), dirs)
    assert not raw.hit[2:].all() or np.abs(raw.t - expected)[2:].max() > 0.02, raw.t - expected


def _core(name: str) -> str:
    if name == "compiled":
        require_compiled()  # skips only where SCUBE_SIM_ALLOW_NO_CORE=1 and the core is not built
    return name


@pytest.mark.parametrize("core", ["reference", "compiled"])
def test_a_ray_misses_the_voxels_it_crosses_short_of_the_band_and_their_mean_confidence(core):
    """Rays along +x from (0, 0.1, 0.1) to points at 2.0 m (band max(1.5 voxels, 5 %) = 0.3 m:
    they carve x in [0, 1.7) m, voxels 0-8 of 0.2 m); candidates on the row and one beside it.
    Voxels 0-8 are missed by both rays (mean confidence (0.4 + 0.8) / 2); voxel 10 lies in the
    band, the one beside the row on no ray."""
    cfg = FusionConfig()
    cand = np.sort(voxel_keys(np.array([[i, 0, 0] for i in range(12)] + [[3, 1, 0]])))
    pts = np.array([[2.0, 0.1, 0.1], [2.0, 0.1, 0.1]])
    idx, conf = _misses(pts, np.array([2.0, 2.0]), np.array([0.4, 0.8], np.float32), np.array([0.0, 0.1, 0.1]),
                        cand, np.zeros(3), cfg, core=_core(core))
    want = np.sort(voxel_keys(np.array([[i, 0, 0] for i in range(9)])))
    assert np.array_equal(cand[idx], want)
    assert np.allclose(conf, 0.6)


@pytest.mark.parametrize("seed", range(2))
def test_the_compiled_carving_walk_gives_the_numpy_walks_bytes_for_any_thread_count(seed):
    """Random rays from a camera into a random sparse grid, batches of 97 rays (sums across
    batches in the reference's order): the same voxels and the same float64 mean confidence."""
    _core("compiled")
    rng = np.random.default_rng(seed)
    cfg = FusionConfig(chunk_rays=97)
    origin = rng.uniform(-3, 3, 3)
    cam = origin + rng.uniform(5, 15, 3)
    pts = origin + rng.uniform(0, 30, (2000, 3))
    depth = np.linalg.norm(pts - cam, axis=1) * rng.uniform(0.5, 1.0, 2000)
    conf = rng.uniform(0.5, 1.0, 2000).astype(np.float32)
    ijk = np.unique(rng.integers(0, 150, (40000, 3)), axis=0)
    cand = np.sort(voxel_keys(ijk))
    want = _misses(pts, depth, conf, cam, cand, origin, cfg, core="reference")
    assert len(want[0]) > 1000
    got = _misses(pts, depth, conf, cam, cand, origin, cfg, core="compiled")
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    for threads in (1, 3):
        got = _misses(pts, depth, conf, cam, cand, origin, cfg, core="compiled", threads=threads)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


def test_the_carving_walk_by_an_unknown_core_name_or_an_unbuilt_core_is_refused(monkeypatch):
    args = (np.ones((1, 3)), np.ones(1), np.ones(1, np.float32), np.zeros(3), np.zeros(1, np.int64), np.zeros(3),
            FusionConfig())
    with pytest.raises(InputError, match="core"):
        _misses(*args, core="gpu")
    monkeypatch.setattr(compiled, "_core", None)
    with pytest.raises(compiled.CoreUnavailable, match="not built"):
        _misses(*args, core="compiled")
