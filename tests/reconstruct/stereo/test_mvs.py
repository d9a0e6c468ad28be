"""Multi-view stereo over a `Frames` (`reconstruct.stereo.mvs`): an analytic textured plane (and a textured box
in front of it) seen by pinhole cameras at several instants: the plane's depth, what must give no
confident depth (no baseline, a camera looking away, moving objects with and without boxes), the
same bytes whatever the thread count, fisheye refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import binary_erosion

from scube_sim.boxes import Box
from scube_sim.camera import Intrinsics
from scube_sim.camera.frames import CameraImage, Frames
from scube_sim.errors import InputError
from scube_sim.reconstruct.config import StereoConfig
from scube_sim.reconstruct.stereo import moved_boxes, moved_pixels, stereo_depth
from tests.reconstruct.stereo.test_sweep import _pose  # one analytic rig for the stereo tests

W, H, F = 128, 96, 120.0
PLANE_Z = 10.0  # metres: the world plane z = PLANE_Z; the reference camera sits at the world origin
INTR = Intrinsics(W, H, F, F, W / 2, H / 2)
# 2-40 m in 64 planes: one hypothesis step moves a 1 m baseline's image by ~0.9 px (at full
# resolution: these small images are swept at scale 1, not the default half)
CFG = StereoConfig(hypotheses=64, near_m=2.0, far_m=40.0, sources=4, scale=1.0)
BOX_SIZE = np.array([2.4, 1.8, 1.0])  # metres, x/y/z
BOX_Z = 6.0  # the box's centre depth


def _texture(x: np.ndarray, y: np.ndarray, seed: int) -> np.ndarray:
    """Plane coordinates (metres) -> (..., 3) RGB in [0.1, 0.9]: seeded sums of sinusoids,
    wavelengths 0.3-1.5 m."""
    rng = np.random.default_rng(seed)
    theta, lam, phase = rng.uniform(0, np.pi, 8), rng.uniform(0.3, 1.5, 8), rng.uniform(0, 2 * np.pi, 8)
    waves = np.stack([np.sin(2 * np.pi * (x * np.cos(t) + y * np.sin(t)) / s + p)
                      for t, s, p in zip(theta, lam, phase)], -1)
    mix = rng.uniform(0.2, 1.0, (8, 3))
    return 0.5 + 0.4 * waves @ (mix / mix.sum(0, keepdims=True))


def _shot(name: str, cam_to_world: np.ndarray, t: float, box_centre=None, intr: Intrinsics = INTR):
    """A CameraImage of the plane (and the axis-aligned box at `box_centre`, its texture moving with
    it) and the camera-z depth (H, W) of what each pixel centre sees."""
    rays = intr.pixel_rays()  # through the lens model: a distorted camera images the scene distorted
    rays = rays / rays[..., 2:]
    d = rays @ cam_to_world[:3, :3].T
    o = cam_to_world[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (PLANE_Z - o[2]) / d[..., 2]
    s = np.where(s > 0, s, np.inf)
    with np.errstate(invalid="ignore"):  # rays that miss the plane: no texture, a mid grey
        rgb = _texture(o[0] + s * d[..., 0], o[1] + s * d[..., 1], 7)
    rgb = np.where(np.isfinite(s)[..., None], rgb, 0.5)
    if box_centre is not None:
        c = np.asarray(box_centre, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (c - BOX_SIZE / 2 - o) / d, (c + BOX_SIZE / 2 - o) / d
        tmin, tmax = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
        hit = (tmax >= tmin) & (tmin > 0) & (tmin < s)
        p = o + tmin[..., None] * d
        rgb = np.where(hit[..., None], _texture(p[..., 0] - c[0], p[..., 1] - c[1], 11), rgb)
        s = np.where(hit, tmin, s)
    depth = (s * rays[..., 2]).astype(np.float32)  # rays have z = 1 in the camera: depth = s
    img = np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)
    return CameraImage(name, img, intr, cam_to_world, t), depth


def _box(centre) -> Box:
    return Box(np.asarray(centre, float), BOX_SIZE, np.eye(3), instance=5, track_id="car-5")


def _frames(ref: CameraImage, context: dict[int, list[CameraImage]], boxes: dict[int, list[Box]] | None = None,
            others: list[CameraImage] = ()) -> Frames:
    boxes = boxes or {}
    ctx = [Frames(ims, np.eye(4), 0.1 * off, offset=off, boxes=boxes.get(off, [])) for off, ims in context.items()]
    return Frames([ref, *others], np.eye(4), 0.0, boxes=boxes.get(0, []), context=ctx)


def _plane_interior(margin: int = 6) -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[margin:H - margin, margin:W - margin] = True
    return m


def test_two_cameras_recover_the_plane():
    ref, gt = _shot("ref", _pose(), 0.0)
    src, _ = _shot("cam", _pose((1.0, 0.2, 0.0)), 0.1)
    res = stereo_depth(_frames(ref, {1: [src]}), 0, CFG)
    assert [v.offset for v in res.sources] == [1]
    assert res.depth.shape == (H, W) and res.depth.dtype == np.float32 and res.confidence.dtype == np.float32
    confident = res.confidence >= 0.5
    # the source sees the plane shifted left by F * 1 m / 10 m = 12 px: the reference's left 12 columns are unseen
    seen = _plane_interior() & (np.arange(W)[None] >= 12 + 6)
    assert confident[seen].mean() > 0.8, confident[seen].mean()
    rel = np.abs(res.depth[confident] - gt[confident]) / gt[confident]
    # within half a percent (the median well inside, 95 % of the pixels too); the few over it sit
    # at the image's border (a truncated window) and stay within 2 %
    assert np.median(rel) < 0.0025 and np.quantile(rel, 0.95) < 0.005, (np.median(rel), np.quantile(rel, 0.95))
    assert rel.max() < 0.02, rel.max()
    assert not confident[:, :10].any()  # unseen: no depth to be confident about


def test_two_sources_recover_the_plane_within_half_a_percent():
    ref, gt = _shot("ref", _pose(), 0.0)
    left, _ = _shot("cam", _pose((-1.0, 0.2, 0.0)), -0.1)
    right, _ = _shot("cam", _pose((1.0, -0.1, 0.0)), 0.1)
    res = stereo_depth(_frames(ref, {-1: [left], 1: [right]}), 0, CFG)
    confident = res.confidence >= 0.5
    inner = _plane_interior(8)
    assert confident[inner].mean() > 0.8
    rel = np.abs(res.depth[confident] - gt[confident]) / gt[confident]
    assert np.median(rel) < 0.0025 and np.quantile(rel, 0.95) < 0.005 and rel.max() < 0.02


@pytest.mark.parametrize("yaw_deg", [0.0, 3.0])
def test_a_zero_baseline_gives_no_confident_pixel(yaw_deg):
    ref, _ = _shot("ref", _pose(), 0.0)
    same, _ = _shot("cam", _pose(yaw_deg=yaw_deg), 0.1)  # a stopped ego
    res = stereo_depth(_frames(ref, {1: [same]}), 0, CFG)
    assert res.sources == []
    assert not (res.confidence > 0).any() and np.isnan(res.depth).all()


def test_a_camera_looking_away_is_not_used():
    ref, gt = _shot("ref", _pose(), 0.0)
    away, _ = _shot("back", _pose((1.0, 0.0, 0.0), yaw_deg=180.0), 0.1)
    res = stereo_depth(_frames(ref, {1: [away]}), 0, CFG)
    assert res.sources == [] and not (res.confidence > 0).any()
    good, _ = _shot("cam", _pose((1.0, 0.0, 0.0)), 0.1)
    res = stereo_depth(_frames(ref, {1: [away, good]}), 0, CFG)
    assert [v.image.name for v in res.sources] == ["cam"]


def test_a_fully_occluded_source_gives_no_confident_wrong_depth():
    # a box 2 m in front of the source fills its whole view: it never sees the plane
    ref, gt = _shot("ref", _pose(), 0.0)
    blocked, blocked_depth = _shot("cam", _pose((1.0, 0.2, 0.0)), 0.1, box_centre=(1.0, 0.2, 2.0))
    assert (blocked_depth < 2.0).all()
    alone = stereo_depth(_frames(ref, {1: [blocked]}), 0, CFG)
    assert [v.offset for v in alone.sources] == [1]
    # measured: 248 of 12288 pixels confidently wrong when a lone source needed the same peak as a
    # cross-checked one (the aggregation makes its chance matches look peaked), 0 now
    assert _confident_wrong(alone, gt, np.ones_like(gt, bool)) == 0
    # beside three sources that see the plane, it is outvoted: the plane keeps its depth
    good = [_shot("cam", _pose((dx, dy, 0.0)), 0.1 * o)[0]
            for o, dx, dy in ((-1, -1.0, 0.2), (2, 1.2, -0.3), (-2, -1.4, -0.2))]
    res = stereo_depth(_frames(ref, {1: [blocked], -1: [good[0]], 2: [good[1]], -2: [good[2]]}), 0, CFG)
    assert len(res.sources) == 4
    inner = _plane_interior(16)
    assert (res.confidence[inner] >= 0.5).mean() > 0.8, (res.confidence[inner] >= 0.5).mean()
    # away from the border: measured, 2 corner pixels whose window the image truncates are 6 % off
    assert _confident_wrong(res, gt, _plane_interior(CFG.window // 2)) == 0


def test_the_parallax_per_step_matches_the_pinhole_geometry():
    from scube_sim.reconstruct.stereo.mvs import _parallax
    from scube_sim.reconstruct.stereo.views import SourceView
    k = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])
    depth = torch.full((H, W), 10.0, dtype=torch.float32)
    depth[: H // 2] = 25.0
    inv_step = 0.01
    sideways = np.eye(4)
    sideways[0, 3] = -0.8  # the source 0.8 m to the right: a point moves f b di left per step
    ahead = np.eye(4)
    ahead[2, 3] = -2.0  # the source 2 m ahead along the optical axis
    views = [SourceView(None, 1, m, 1.0, 1.0, 1.0) for m in (sideways, ahead)]
    srcs = [(None, k, None, None)] * 2
    every = torch.ones((H, W), dtype=torch.bool)
    got = _parallax(depth, k, srcs, views[:1], [every], inv_step).numpy()
    np.testing.assert_allclose(got, F * 0.8 * inv_step, rtol=1e-5)  # whatever the depth
    got = _parallax(depth, k, srcs[1:], views[1:], [every], inv_step).numpy()
    v, u = np.mgrid[0:H, 0:W] + 0.5
    i = 1.0 / depth.numpy().astype(np.float64)
    zoom = 1.0 / (1.0 - 2.0 * (i + inv_step)) - 1.0 / (1.0 - 2.0 * i)  # u' - cx = (u - cx) / (1 - t i)
    np.testing.assert_allclose(got, np.hypot(u - W / 2, v - H / 2) * zoom, rtol=1e-4, atol=1e-6)
    assert got[H // 2, W // 2] < 0.02 * got[0, 0]  # next to the focus of expansion: almost none
    half = every.clone()
    half[:, : W // 2] = False  # the ahead source does not agree on the left half
    both = _parallax(depth, k, srcs, views, [every, half], inv_step).numpy()
    np.testing.assert_allclose(both[:, : W // 2], F * 0.8 * inv_step, rtol=1e-5)
    np.testing.assert_allclose(both[:, W // 2:], np.hypot(F * 0.8 * inv_step, got[:, W // 2:]), rtol=1e-4)


def test_driving_forward_recovers_the_plane_and_the_focus_of_expansion_is_not_confidently_wrong():
    # sources 1.5 and 3 m behind and ahead along the optical axis, as a forward-driving camera
    ref, gt = _shot("ref", _pose(), 0.0)
    ims = {o: [_shot("cam", _pose((0.05 * o, 0.0, 1.5 * o)), 0.1 * o)[0]] for o in (-2, -1, 1, 2)}
    res = stereo_depth(_frames(ref, ims), 0, CFG)
    assert len(res.sources) == 4
    confident = res.confidence >= 0.5
    assert confident[_plane_interior(16)].mean() > 0.8
    assert _confident_wrong(res, gt, np.ones_like(gt, bool)) == 0


def _moving_scene(offsets_and_boxes: dict[int, tuple], with_boxes: bool):
    """The reference (box at BOX_Z, centred in view) and one source per context offset, the cameras
    1 m apart per instant sideways, the box where `offsets_and_boxes` puts it."""
    ref_box = (0.0, 0.0, BOX_Z)
    ref, gt = _shot("ref", _pose(), 0.0, ref_box)
    ctx, boxes = {}, {0: [_box(ref_box)]}
    for off, centre in offsets_and_boxes.items():
        im, _ = _shot("cam", _pose((0.8 * off, 0.1 * off, 0.0)), 0.1 * off, centre)
        ctx[off] = [im]
        boxes[off] = [_box(centre)]
    _, box_only = _shot("ref", _pose(), 0.0, ref_box)
    on_box = np.abs(gt - (BOX_Z - BOX_SIZE[2] / 2)) < 1e-3
    return _frames(ref, ctx, boxes if with_boxes else None), gt, on_box


def _confident_wrong(res, gt, where, tol=0.05) -> int:
    confident = (res.confidence >= 0.5) & where
    return int((np.abs(res.depth[confident] - gt[confident]) > tol * gt[confident]).sum())


def test_a_moving_box_with_a_track_is_masked():
    # the car drives 1.5 m sideways per instant against the cameras' 0.8 m: static, it would sit elsewhere
    frames, gt, on_box = _moving_scene({-1: (-1.5, 0.0, BOX_Z), 1: (1.5, 0.0, BOX_Z)}, with_boxes=True)
    res = stereo_depth(frames, 0, CFG)
    assert _confident_wrong(res, gt, on_box) == 0
    assert not (res.confidence[on_box] > 0).any()  # no same-instant source: masked out entirely
    plane = ~on_box & _plane_interior(10)
    assert (res.confidence[plane] >= 0.5).mean() > 0.5  # the static plane keeps its depth around it
    assert _confident_wrong(res, gt, plane) <= 0.01 * plane.sum()


def test_a_moving_box_swept_in_its_own_frame_gets_its_depth():
    # the same car: in its own frame each source camera stood 0.7 m beside where the reference did
    frames, gt, on_box = _moving_scene({-1: (-1.5, 0.0, BOX_Z), 1: (1.5, 0.0, BOX_Z)}, with_boxes=True)
    res = stereo_depth(frames, 0, CFG.model_copy(update={"movers": True}))
    inner = on_box & _plane_interior(10)
    assert (res.confidence[inner] >= 0.5).mean() > 0.8
    # right inside the face; on its top edge (2 rows: the relative motion runs along it, the
    # window straddles the plane behind) 25 of its 2080 pixels are 7-16 % too deep
    assert _confident_wrong(res, gt, binary_erosion(on_box, iterations=2)) == 0
    assert _confident_wrong(res, gt, on_box) <= 0.015 * on_box.sum()
    # the plane around it keeps the static sweep's answer, bit for bit
    static = stereo_depth(frames, 0, CFG)
    box_px = moved_pixels(frames.images[0], frames.boxes, frames.context[0].boxes, CFG)
    np.testing.assert_array_equal(res.depth[~box_px], static.depth[~box_px])
    # a box too small in the image to sweep (mover_min_px) leaves the static answer everywhere
    tiny = stereo_depth(frames, 0, CFG.model_copy(update={"movers": True, "mover_min_px": 10 ** 6}))
    np.testing.assert_array_equal(tiny.confidence, static.confidence)


def test_a_moving_object_without_a_box_is_not_confidently_wrong():
    # three instants, the object moves across the cameras' (sideways) path: no depth explains two views
    frames, gt, on_box = _moving_scene({-2: (0.3, -0.8, BOX_Z), -1: (-0.2, 0.7, BOX_Z), 1: (0.4, -0.6, BOX_Z)},
                                       with_boxes=False)
    res = stereo_depth(frames, 0, CFG)
    assert len(res.sources) == 3
    # the agreement and peak terms reject it: of the 2080 object pixels, 10 stay confident and wrong
    # with the default semi-global aggregation (5 without it: 4 on its silhouette's edge, where the
    # window straddles the plane behind, the background's depth; 1 inside, where two sources agree
    # by chance)
    assert _confident_wrong(res, gt, on_box) <= 0.005 * on_box.sum(), _confident_wrong(res, gt, on_box)


def test_weak_pixels_stay_below_the_fusion_threshold_and_leave_the_confident_ones_alone():
    """`weak_agreement`: the moving object's low-agreement pixels get at most `weak_cap` (the fusion
    then needs a second view hitting the same voxel), never the confidence that would make them a
    surface alone; pixels confident without it keep their depth and confidence."""
    frames, gt, on_box = _moving_scene({-2: (0.3, -0.8, BOX_Z), -1: (-0.2, 0.7, BOX_Z), 1: (0.4, -0.6, BOX_Z)},
                                       with_boxes=False)
    plain = stereo_depth(frames, 0, CFG)
    weak = stereo_depth(frames, 0, CFG.model_copy(update={"weak_agreement": 0.25, "weak_cap": 0.45}))
    added = (weak.confidence > 0) & (plain.confidence == 0)
    assert added.sum() > 0.05 * on_box.sum()  # the object's disagreeing pixels are now weak ...
    assert np.all(weak.confidence[added] <= 0.45)  # ... and weak only
    assert _confident_wrong(weak, gt, on_box) == _confident_wrong(plain, gt, on_box)
    sure = plain.confidence >= 0.5
    assert np.array_equal(weak.confidence[sure], plain.confidence[sure])
    assert np.array_equal(weak.depth[sure], plain.depth[sure])


def test_the_bytes_do_not_depend_on_the_thread_count():
    cfg = CFG.model_copy(update={"hypotheses": 16, "near_m": 5.0, "far_m": 20.0})  # small: 2 threads may be slow
    ref, _ = _shot("ref", _pose(), 0.0, (0.0, 0.0, BOX_Z))
    left, _ = _shot("cam", _pose((-1.0, 0.2, 0.0)), -0.1, (0.3, 0.0, BOX_Z))
    right, _ = _shot("cam", _pose((1.0, -0.1, 0.0)), 0.1, (0.0, 0.0, BOX_Z))
    frames = _frames(ref, {-1: [left], 1: [right]})
    before = torch.get_num_threads()
    runs = []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            res = stereo_depth(frames, 0, cfg)
            runs.append([res.depth.tobytes(), res.confidence.tobytes()])
    finally:
        torch.set_num_threads(before)
    assert runs[0] == runs[1]


def test_opencv_images_are_undistorted_and_fisheye_refused():
    ref, gt = _shot("ref", _pose(), 0.0)
    src, _ = _shot("cam", _pose((1.0, 0.2, 0.0)), 0.1)
    fish = Intrinsics(W, H, F, F, W / 2, H / 2, "fisheye", (0.0, 0.0, 0.0, 0.0))
    bad = CameraImage("FISH_CAM", ref.image, fish, ref.cam_to_world, 0.0)
    with pytest.raises(InputError, match="FISH_CAM"):
        stereo_depth(_frames(bad, {1: [src]}), 0, CFG)
    # a barrel-distorted reference and source: undistorted to pinhole, the depth comes back per original pixel
    lens = Intrinsics(W, H, F, F, W / 2, H / 2, "opencv", (-0.15, 0.02, 0.001, -0.001, 0.0))
    ref_d, gt_d = _shot("ref", _pose(), 0.0, intr=lens)
    src_d, _ = _shot("cam", _pose((1.0, 0.2, 0.0)), 0.1, intr=lens)
    res = stereo_depth(_frames(ref_d, {1: [src_d]}), 0, CFG)
    confident = res.confidence >= 0.5
    assert confident[_plane_interior(8) & (np.arange(W)[None] >= 24)].mean() > 0.7
    rel = np.abs(res.depth[confident] - gt_d[confident]) / gt_d[confident]
    assert np.median(rel) < 0.005 and np.quantile(rel, 0.99) < 0.02


def test_sky_gets_no_depth():
    ref, _ = _shot("ref", _pose(), 0.0)
    src, _ = _shot("cam", _pose((1.0, 0.2, 0.0)), 0.1)
    ref.sky = np.zeros((H, W), bool)
    ref.sky[:20] = True
    res = stereo_depth(_frames(ref, {1: [src]}), 0, CFG)
    assert np.isnan(res.depth[:20]).all() and not (res.confidence[:20] > 0).any()
    assert (res.confidence[30:] >= 0.5).mean() > 0.5


def test_the_default_half_scale_recovers_the_plane():
    # a sweep at half resolution (the default scale): the plane's depth within 1 %, nothing confidently wrong
    ref, gt = _shot("ref", _pose(), 0.0)
    left, _ = _shot("cam", _pose((-1.0, 0.2, 0.0)), -0.1)
    right, _ = _shot("cam", _pose((1.0, -0.1, 0.0)), 0.1)
    frames = _frames(ref, {-1: [left], 1: [right]})
    inner = _plane_interior(12)
    res = stereo_depth(frames, 0, CFG.model_copy(update={"scale": 0.5}))
    confident = res.confidence >= 0.5
    assert confident[inner].mean() > 0.6, confident[inner].mean()
    rel = np.abs(res.depth[confident] - gt[confident]) / gt[confident]
    assert np.median(rel) < 0.01 and rel.max() < 0.05, (np.median(rel), rel.max())


@pytest.mark.parametrize("paths", [4, 8])
def test_semi_global_aggregation_keeps_the_plane(paths):
    ref, gt = _shot("ref", _pose(), 0.0)
    left, _ = _shot("cam", _pose((-1.0, 0.2, 0.0)), -0.1)
    right, _ = _shot("cam", _pose((1.0, -0.1, 0.0)), 0.1)
    res = stereo_depth(_frames(ref, {-1: [left], 1: [right]}), 0, CFG.model_copy(update={"sgm_paths": paths}))
    confident = res.confidence >= 0.5
    assert confident[_plane_interior(8)].mean() > 0.8
    rel = np.abs(res.depth[confident] - gt[confident]) / gt[confident]
    assert np.median(rel) < 0.0025 and np.quantile(rel, 0.95) < 0.005 and rel.max() < 0.02


@pytest.mark.parametrize("update, key", [({"near_m": 50.0}, "near_m"), ({"window": 6}, "window"),
                                         ({"sgm_paths": 4, "sgm_p1": 0.5, "sgm_p2": 0.1}, "sgm_p1")])
def test_inconsistent_settings_are_refused_by_name(update, key):
    ref, _ = _shot("ref", _pose(), 0.0)
    src, _ = _shot("cam", _pose((1.0, 0.2, 0.0)), 0.1)
    with pytest.raises(InputError, match=key):
        stereo_depth(_frames(ref, {1: [src]}), 0, CFG.model_copy(update=update))


def test_moved_pixels_cover_the_box_of_an_object_that_moved_and_nothing_for_one_that_stood():
    centre = (0.0, 0.0, BOX_Z)
    ref, gt = _shot("ref", _pose(), 0.0, centre)
    on_box = np.abs(gt - (BOX_Z - BOX_SIZE[2] / 2)) < 0.01  # the box's front face
    here = [_box(centre)]
    assert on_box.sum() > 500
    assert not moved_pixels(ref, here, [_box(centre)]).any()
    mask = moved_pixels(ref, here, [_box((1.0, 0.0, BOX_Z))])
    # the whole face, and the 0.3 m margin around it, not much more
    assert mask[on_box].all() and mask.sum() < 2.5 * on_box.sum()
    # the boxes of what moved, at both instants; nothing for what stood
    there = [_box((3.0, 0.0, BOX_Z))]
    moved_here, moved_there = moved_boxes(here, there)
    assert moved_here == here and moved_there == there
    assert moved_boxes(here, [_box(centre)]) == ([], [])
    # an object with no identity counts as moved (nothing says it stood still)
    anon = Box(np.asarray(centre, float), BOX_SIZE, np.eye(3))
    assert moved_pixels(ref, [anon], [anon])[on_box].all()


def test_a_camera_too_large_for_the_memory_is_refused_from_its_size(monkeypatch):
    """Before any cost volume is made, its size (pixels x hypotheses, and per source) is weighed
    against the memory the process may use: one line naming the camera, the size and what to do."""
    from scube_sim import memory

    ref, _ = _shot("ref", _pose(), 0.0)
    src, _ = _shot("cam", _pose((1.0, 0.2, 0.0)), 0.1)
    monkeypatch.setattr(memory, "available_bytes", lambda: 20 * 2**20)  # 20 MB free
    with pytest.raises(InputError) as err:
        stereo_depth(_frames(ref, {1: [src]}), 0, CFG.model_copy(update={"hypotheses": 4096}))
    msg = str(err.value)
    assert msg.startswith(f"stereo of camera 'ref' ({W}x{H} pixels at scale 1, 4096 hypotheses, 1 sources) needs about")
    assert "20.0 MB is available; convert with fewer cameras" in msg and "\n" not in msg
    assert stereo_depth(_frames(ref, {1: [src]}), 0, CFG).sources  # the same camera fits at 64 hypotheses


def test_box_mask_equals_a_slab_test_on_every_pixel():
    """The box mask tests only the pixels around a box's projected corners where the box lies in
    front of the camera: the same pixels as an independent ray-box test on every pixel, for boxes
    in front, straddling the camera, behind it and outside the image."""
    from scube_sim.reconstruct.stereo.movers import box_mask
    from scube_sim.transforms import pose_from_xyz_rpy

    rng = np.random.default_rng(7)
    h, w = 48, 64
    for _ in range(60):
        cam = pose_from_xyz_rpy(rng.uniform(-3, 3, 3), np.radians(rng.uniform(-180, 180, 3)))
        k = np.array([[rng.uniform(40, 120), 0, w / 2], [0, rng.uniform(40, 120), h / 2], [0, 0, 1.0]])
        boxes = [Box(center=cam[:3, 3] + rng.uniform(-8, 8, 3), size=rng.uniform(0.5, 4, 3),
                     rotation=pose_from_xyz_rpy([0, 0, 0], [0, 0, rng.uniform(-3, 3)])[:3, :3], label=1)
                 for _ in range(3)]
        got = box_mask(boxes, cam, k, (h, w), 0.1, 0)
        v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
        d = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], -1) @ cam[:3, :3].T
        want = np.zeros((h, w), bool)
        for b in boxes:  # the slab test in the box frame, every pixel, t > 0
            o = b.rotation.T @ (cam[:3, 3] - b.center)
            db = d @ b.rotation
            half = b.size / 2 + 0.1
            with np.errstate(divide="ignore", invalid="ignore"):
                ta, tb = (-half - o) / db, (half - o) / db
            near, far = np.nanmax(np.minimum(ta, tb), -1), np.nanmin(np.maximum(ta, tb), -1)
            want |= (far >= np.maximum(near, 0.0)) & (far > 0)
        assert np.array_equal(np.zeros((h, w), bool) if got is None else got.numpy(), want)
