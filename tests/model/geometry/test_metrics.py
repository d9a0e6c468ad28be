"""The geometry stage's metrics against answers worked out by hand: IoU of overlapping boxes,
mIoU of a hand-built confusion (summed over samples), voxel Chamfer of shifted walls and single
voxels, empty grids, and the visibility split with analytic and distorted cameras."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from scube_sim.camera.model import Intrinsics
from scube_sim.errors import InputError
from scube_sim.labels import NUM_LABELS, label_id
from scube_sim.model.geometry.metrics import (
    chamfer_voxels,
    geometry_sample_metrics,
    semantic_confusion,
    semantic_iou,
    summarise,
    visible_voxels,
    voxel_iou,
)

CAR, ROAD, BUILDING = label_id("car"), label_id("road"), label_id("building")
E = NUM_LABELS  # the 'empty' row / column of a confusion


def box(lo, hi) -> np.ndarray:
    """(V, 3) int64 voxels of the box [lo, hi) (per axis)."""
    axes = [np.arange(a, b) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.int64)


def row(xs) -> np.ndarray:
    """Voxels (x, 0, 0) for x in xs."""
    return np.array([[x, 0, 0] for x in xs], np.int64).reshape(-1, 3)


EMPTY = np.zeros((0, 3), np.int64)


# --- IoU -----------------------------------------------------------------------------------------------


def test_iou_of_two_overlapping_boxes():
    # P = [0,4)x[0,3)x[0,2): 24 voxels; G = [2,6)x[1,3)x[0,2): 16; P ∩ G = [2,4)x[1,3)x[0,2): 8;
    # union 24 + 16 - 8 = 32: IoU 8 / 32.
    p, g = box((0, 0, 0), (4, 3, 2)), box((2, 1, 0), (6, 3, 2))
    assert voxel_iou(p, g) == pytest.approx(0.25)
    assert voxel_iou(torch.from_numpy(p), torch.from_numpy(g).int()) == pytest.approx(0.25)
    # Duplicates and order do not matter: the grids are sets.
    assert voxel_iou(np.concatenate([p, p[::-1]]), g[::-1]) == pytest.approx(0.25)
    assert voxel_iou(p, p) == 1.0
    # A region predicate (x < 3) cuts both: P' = 3*3*2 = 18 voxels, G' = x=2 only: 1*2*2 = 4, all
    # inside P': IoU 4 / 18.
    assert voxel_iou(p, g, region=lambda ijk: ijk[:, 0] < 3) == pytest.approx(4 / 18)
    # The same as per-voxel masks, (pred mask, gt mask).
    assert voxel_iou(p, g, region=(p[:, 0] < 3, torch.from_numpy(g[:, 0] < 3))) == pytest.approx(4 / 18)


def test_iou_of_empty_grids():
    assert math.isnan(voxel_iou(EMPTY, EMPTY))  # empty union: undefined, skipped by `summarise`
    assert voxel_iou(EMPTY, row([0])) == 0.0
    assert voxel_iou(row([0]), np.zeros((0,), np.int64)) == 0.0
    assert math.isnan(voxel_iou(row([0]), row([5]), region=lambda ijk: ijk[:, 0] > 9))
    with pytest.raises(InputError):
        voxel_iou(np.zeros((3, 2), np.int64), row([0]))
    with pytest.raises(InputError):
        voxel_iou(row([0, 1]), row([0]), region=(np.array([True]), np.array([True])))


# --- semantics -----------------------------------------------------------------------------------------

# Sample A. G: x=0 car, 1 car, 2 road, 3 road. P: x=0 car, 1 road, 2 road, 4 car, 5 building.
# Confusion [true, pred]: car->car 1 (x0), car->road 1 (x1), road->road 1 (x2), road->empty 1 (x3,
# gt only: a FN of road), empty->car 1 (x4, pred only: a FP of car), empty->building 1 (x5).
A_GT, A_GT_LAB = row([0, 1, 2, 3]), np.array([CAR, CAR, ROAD, ROAD])
A_P, A_P_LAB = row([0, 1, 2, 4, 5]), np.array([CAR, ROAD, ROAD, CAR, BUILDING])


def test_confusion_counts_pred_only_as_fp_and_gt_only_as_fn():
    conf = semantic_confusion(A_P, A_P_LAB, A_GT, A_GT_LAB)
    want = np.zeros((E + 1, E + 1), np.int64)
    want[CAR, CAR] = want[CAR, ROAD] = want[ROAD, ROAD] = want[ROAD, E] = want[E, CAR] = want[E, BUILDING] = 1
    np.testing.assert_array_equal(conf, want)
    # The input order does not matter; torch works the same.
    perm = np.array([4, 2, 0, 3, 1])
    np.testing.assert_array_equal(semantic_confusion(torch.from_numpy(A_P[perm]), torch.from_numpy(A_P_LAB[perm]),
                                                     torch.from_numpy(A_GT), torch.from_numpy(A_GT_LAB)), want)


def test_miou_of_hand_built_confusion():
    # car: TP 1, FP 1 (x4), FN 1 (x1) -> 1/3. road: TP 1, FP 1 (x1), FN 1 (x3) -> 1/3.
    # building: TP 0, FP 1 -> 0. Other labels absent on both sides: not averaged. mIoU = 2/9.
    miou, per = semantic_iou(semantic_confusion(A_P, A_P_LAB, A_GT, A_GT_LAB))
    assert miou == pytest.approx(2 / 9)
    assert per == pytest.approx({"car": 1 / 3, "road": 1 / 3, "building": 0.0})
    # Nothing present: nan and no labels.
    miou, per = semantic_iou(semantic_confusion(EMPTY, [], EMPTY, []))
    assert math.isnan(miou) and per == {}


def test_confusion_rejects_bad_labels_and_duplicates():
    with pytest.raises(InputError):
        semantic_confusion(row([0]), [NUM_LABELS], row([0]), [CAR])
    with pytest.raises(InputError):
        semantic_confusion(row([0]), [CAR, CAR], row([0]), [CAR])
    with pytest.raises(InputError):  # a voxel listed twice: which label?
        semantic_confusion(row([0, 0]), [CAR, ROAD], row([0]), [CAR])


# --- Chamfer -------------------------------------------------------------------------------------------


def test_chamfer_of_shifted_wall_and_single_voxels():
    # A one-voxel-thick wall (x = 0, y in [0,5), z in [0,4)) against the same wall at x = 1: every
    # voxel's nearest neighbour on the other side is its twin, 1 voxel away: 0.5 * (1 + 1) = 1.
    wall = box((0, 0, 0), (1, 5, 4))
    assert chamfer_voxels(wall + [1, 0, 0], wall) == pytest.approx(1.0)
    assert chamfer_voxels(torch.from_numpy(wall + [2, 0, 0]), torch.from_numpy(wall)) == pytest.approx(2.0)
    # Single voxels (0,0,0) and (3,4,0): |(3, 4, 0)| = 5 both ways.
    assert chamfer_voxels(row([0]), np.array([[3, 4, 0]])) == pytest.approx(5.0)
    # A box 4 long in x shifted by 1: 3 of 4 layers coincide, one layer on each side is 1 away:
    # 0.5 * (1/4 + 1/4) = 1/4.
    b = box((0, 0, 0), (4, 3, 2))
    assert chamfer_voxels(b + [1, 0, 0], b) == pytest.approx(0.25)
    # Asymmetric: P = {x0}, G = {x0, x2}: P->G mean 0, G->P mean (0 + 2) / 2 = 1: 0.5.
    assert chamfer_voxels(row([0]), row([0, 2])) == pytest.approx(0.5)
    assert chamfer_voxels(row([0, 2]), row([0])) == pytest.approx(0.5)


def test_chamfer_of_empty_grids():
    assert chamfer_voxels(EMPTY, EMPTY) == 0.0
    assert chamfer_voxels(EMPTY, row([0])) == math.inf
    assert chamfer_voxels(row([0]), EMPTY) == math.inf


@pytest.mark.parametrize("seed, low, high", [(0, -5, 12), (1, 0, 4), (2, -3, 30)])
def test_chamfer_is_the_brute_force_mean_of_nearest_distances(seed, low, high):
    """Random grids with repeated and shared voxels (the shared ones skip the nearest-site query)
    against every pairwise distance in float64."""
    from scube_sim.model.geometry.metrics import _nearest_distance_sum

    rng = np.random.default_rng(seed)
    g = rng.integers(low, high, (300, 3))
    p = np.concatenate([g[:150], rng.integers(low, high, (200, 3)), g[:20]])  # shared, new, repeated
    up, ug = (np.unique(x, axis=0).astype(np.float64) for x in (p, g))
    d = np.linalg.norm(up[:, None] - ug[None], axis=-1)
    expected = 0.5 * (d.min(1).mean() + d.min(0).mean())
    assert chamfer_voxels(p, g) == pytest.approx(expected, rel=1e-12)
    assert chamfer_voxels(g, g[::-1]) == 0.0
    # Both exact routes to the nearest site, whichever `chamfer_voxels` picks for a size.
    far = np.unique(p, axis=0)
    brute = np.linalg.norm(far[:, None] - ug[None], axis=-1).min(1).sum()
    for method in ("tree", "edt"):
        assert _nearest_distance_sum(np.unique(g, axis=0), far, method) == pytest.approx(brute, rel=1e-12)



def test_chamfer_auto_route_splits_near_and_far_queries_exactly(monkeypatch):
    """The 'auto' route's mix (a bounded tree query for near voxels, the distance transform for the
    rest), forced at a small size, against every pairwise distance."""
    import scube_sim.model.geometry.metrics as gm

    monkeypatch.setattr(gm, "_EDT_MIN_FAR", 10)
    rng = np.random.default_rng(7)
    sites = np.unique(rng.integers(0, 12, (80, 3)), axis=0)
    queries = np.unique(np.concatenate([rng.integers(0, 12, (60, 3)), rng.integers(20, 40, (60, 3))]), axis=0)
    d = np.linalg.norm(queries[:, None].astype(np.float64) - sites[None], axis=-1).min(1)
    assert (d <= gm._NEAR).sum() >= 10 and (d > gm._NEAR).sum() >= 10  # both routes are taken
    assert gm._nearest_distance_sum(sites, queries) == pytest.approx(d.sum(), rel=1e-12)


# --- visibility ----------------------------------------------------------------------------------------

# Camera frame OpenCV (x right, y down, z forward); the columns of R are the camera axes in the chunk
# frame (x forward, y left, z up). Looking down +x: right = -y, down = -z. Looking down -x: right = +y.
R_PLUS_X = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
R_MINUS_X = np.array([[0.0, 0, -1], [1, 0, 0], [0, -1, 0]])
W, H, F, CX, CY = 40, 30, 20.0, 20.0, 15.0  # image 40 x 30, fx = fy = 20, principal point (20, 15)
PAD_H, PAD_W = 32, 48  # the depth maps' padded size


def pose(r, t) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = r, t
    return out


def cameras(poses, depths):
    """Pinhole cameras (W x H) at `poses`, each with a constant depth map (its image only; 0 in the
    padding), as the keyword arguments of `visible_voxels`."""
    n = len(poses)
    depth = np.zeros((n, PAD_H, PAD_W), np.float32)
    for c, d in enumerate(depths):
        depth[c, :H, :W] = d
    k = np.array([[F, 0, CX], [0, F, CY], [0, 0, 1]], np.float32)
    return {"intrinsics": np.repeat(k[None], n, 0), "distortion": np.zeros((n, 5), np.float32),
            "cam_to_chunk": np.stack(poses).astype(np.float32), "depth": depth,
            "image_size": np.tile([H, W], (n, 1))}


# voxel_size 1 and origin -0.5: voxel ijk's centre is ijk itself. Camera 0 at the chunk origin
# looking down +x at a wall 10 m away: a centre (x, y, z) projects to u = 20 * (-y / x) + 20,
# v = 20 * (-z / x) + 15 at camera depth x; visible if x <= 10 + sqrt(3)/2.
ORIGIN = np.full(3, -0.5)
CASES = [  # (ijk, visible from camera 0)
    ((5, 0, 0), True),    # in front of the wall
    ((10, 0, 0), True),   # on it
    ((11, 0, 0), False),  # behind it: 11 > 10.866
    ((-3, 0, 0), False),  # behind the camera
    ((5, -4, 0), True),   # u = 36
    ((5, 5, 0), True),    # u = 0 exactly: the first column
    ((5, -5, 0), False),  # u = 40 exactly: past the last column [39, 40)
    ((5, 6, 0), False),   # u = -4: left of the image
    ((5, -6, 0), False),  # u = 44: in the padded depth array, outside the image
    ((5, 0, 4), False),   # v = 15 - 16 = -1: above the image
    ((5, 0, -3), True),   # v = 27
]


@pytest.mark.parametrize("as_torch", [False, True])
def test_visibility_of_a_wall_seen_by_a_pinhole_camera(as_torch):
    ijk = np.array([c[0] for c in CASES], np.int64)
    cams = cameras([pose(R_PLUS_X, (0, 0, 0))], [10.0])
    if as_torch:
        cams = {k: torch.from_numpy(np.asarray(v)) for k, v in cams.items()}
        ijk, origin = torch.from_numpy(ijk), torch.from_numpy(ORIGIN)
    else:
        origin = ORIGIN
    vis = visible_voxels(ijk, 1.0, origin, **cams)
    assert vis.dtype == bool
    np.testing.assert_array_equal(vis, [c[1] for c in CASES])


def test_visibility_margin_sky_and_padding():
    ijk = row([10, 11])
    # The wall at 9.6 m: the voxel centred at 10 m is 0.4 m behind it, within the default margin
    # (half the diagonal, 0.866 m) but not within margin 0.
    cams = cameras([pose(R_PLUS_X, (0, 0, 0))], [9.6])
    np.testing.assert_array_equal(visible_voxels(ijk, 1.0, ORIGIN, **cams), [True, False])
    np.testing.assert_array_equal(visible_voxels(ijk, 1.0, ORIGIN, **cams, margin=0.0), [False, False])
    np.testing.assert_array_equal(visible_voxels(ijk, 1.0, ORIGIN, **cams, margin=1.5), [True, True])
    # At most depth + margin: a centre exactly on the wall with margin 0 is seen.
    np.testing.assert_array_equal(visible_voxels(ijk, 1.0, ORIGIN, **cameras([pose(R_PLUS_X, (0, 0, 0))], [10.0]),
                                                 margin=0.0), [True, False])
    # Sky (inf) over columns u >= 30: (50, -35, 0) projects to u = 34 and is seen however far;
    # (50, 0, 0), u = 20, is behind the wall.
    cams["depth"][0, :H, 30:W] = np.inf
    np.testing.assert_array_equal(visible_voxels(np.array([[50, -35, 0], [50, 0, 0]]), 1.0, ORIGIN, **cams),
                                  [True, False])
    # A depth-0 pixel never sees, even within the margin of 0: (1, 0, 0) and (5, 0, 0) project to
    # (20, 15).
    cams["depth"][0, 13:18, 18:23] = 0.0
    assert not visible_voxels(row([1, 5]), 1.0, ORIGIN, **cams, margin=1.5).any()
    # image_size bounds the image, not the padded array: with the depth written into the padding
    # too, (5, -5, 0) at u = 40 and (5, -6, 0) at u = 44 stay unseen; (5, -4, 0) at u = 36 is seen.
    cams["depth"][0] = 10.0
    np.testing.assert_array_equal(visible_voxels(np.array([[5, -5, 0], [5, -6, 0], [5, -4, 0]]), 1.0, ORIGIN, **cams),
                                  [False, False, True])
    assert visible_voxels(np.zeros((0, 3), np.int64), 1.0, ORIGIN, **cams).shape == (0,)
    with pytest.raises(InputError):
        visible_voxels(ijk, 1.0, ORIGIN, **{**cams, "image_size": np.array([[H, PAD_W + 1]])})


def test_visibility_from_any_of_two_cameras():
    # Camera 0 at the origin looking down +x at a wall 10 m away; camera 1 at x = 20 looking down
    # -x at a wall 5 m away (at x = 15). x = 5: 5 m from camera 0 (seen); x = 11: 11 m from camera
    # 0 and 9 m from camera 1, behind both walls (unseen); x = 16: 4 m from camera 1 (seen); x = 25:
    # behind camera 1, 25 m from camera 0 (unseen).
    cams = cameras([pose(R_PLUS_X, (0, 0, 0)), pose(R_MINUS_X, (20, 0, 0))], [10.0, 5.0])
    np.testing.assert_array_equal(visible_voxels(row([5, 11, 16, 25]), 1.0, ORIGIN, **cams),
                                  [True, False, True, False])


DIST = np.array([-0.12, 0.02, 0.0012, -0.0021, 0.0])  # [k1, k2, p1, p2, k3]: barrel, ~9 px at the corners


def distorted_camera():
    k = np.array([[31.0, 0, 33.3], [0, 30.0, 23.7], [0, 0, 1]])
    r = Rotation.from_euler("xyz", [4, -7, 11], degrees=True).as_matrix() @ R_PLUS_X
    return k, pose(r, (-1.3, 0.4, 0.9))


def test_distorted_camera_through_pixel_rays():
    # Independent of `Intrinsics.project`: a point on the ray through pixel (u, v)'s centre (the
    # lens undistorted by `Intrinsics.pixel_rays`) at camera depth D is a voxel centre (the origin
    # chosen so); the depth map is D at (u, v) alone. It is seen at depth D, not at D + 0.2 (past
    # the margin 0.0866 of voxel size 0.1). Corner pixels, where the lens moves points by pixels.
    k, c2w = distorted_camera()
    w, h = 64, 48
    rays = Intrinsics(w, h, k[0, 0], k[1, 1], k[0, 2], k[1, 2], "opencv", DIST).pixel_rays()
    vs, d = 0.1, 8.0
    for u, v, far in [(1, 1, True), (62, 2, True), (3, 45, True), (60, 44, True), (33, 23, False), (10, 30, False)]:
        depth = np.zeros((1, h, w))
        depth[0, v, u] = d
        cams = {"intrinsics": k[None], "distortion": DIST[None], "cam_to_chunk": c2w[None], "depth": depth,
                "image_size": np.array([[h, w]])}
        for z, want in ((d, True), (d + 0.2, False)):
            p = c2w[:3, :3] @ (rays[v, u] * z / rays[v, u, 2]) + c2w[:3, 3]
            assert visible_voxels(row([0]), vs, p - 0.5 * vs, **cams)[0] == want, (u, v, z)
        if far:  # the test has power: without the distortion the point would fall on another pixel
            x = rays[v, u] / rays[v, u, 2]
            assert (int(k[0, 0] * x[0] + k[0, 2]), int(k[1, 1] * x[1] + k[1, 2])) != (u, v)


def test_distorted_camera_agrees_with_camera_model():
    # Random voxels and a random depth map (with sky and padding zeros), against projecting each
    # centre with `camera.model.Intrinsics` (built from K's fx, fy, cx, cy: the items' K already puts
    # pixel centres at + 0.5) and a general inverse of the pose.
    rng = np.random.default_rng(0)
    k, c2w = distorted_camera()
    w, h = 64, 48
    vs, origin = 0.25, np.array([-2.0, -6.0, -2.5])
    ijk = rng.integers(0, [100, 48, 20], size=(4000, 3))
    depth = rng.uniform(2.0, 16.0, size=(1, h + 3, w + 5))
    depth[0, h:], depth[0, :, w:] = 0.0, 0.0  # padding
    depth[0, :h, :w][rng.random((h, w)) < 0.1] = np.inf
    depth[0, :h, :w][rng.random((h, w)) < 0.05] = 0.0
    cams = {"intrinsics": torch.from_numpy(k[None]).float(), "distortion": torch.from_numpy(DIST[None]).float(),
            "cam_to_chunk": torch.from_numpy(c2w[None]), "depth": torch.from_numpy(depth).float(),
            "image_size": torch.tensor([[h, w]])}
    got = visible_voxels(torch.from_numpy(ijk), vs, origin, **cams)

    k32 = k.astype(np.float32)  # what the function reads from the float32 tensors
    intr = Intrinsics(w, h, k32[0, 0], k32[1, 1], k32[0, 2], k32[1, 2], "opencv", DIST.astype(np.float32))
    centres = origin + (ijk + 0.5) * vs
    p_cam = (np.linalg.inv(c2w) @ np.c_[centres, np.ones(len(centres))].T).T[:, :3]
    uv, z = intr.project(p_cam)
    want = np.zeros(len(ijk), bool)
    d32 = depth.astype(np.float32)[0]
    for i, ((u, v), zi) in enumerate(zip(uv, z)):
        if np.isfinite(u) and 0 <= u < w and 0 <= v < h:
            dd = d32[int(v), int(u)]
            want[i] = dd > 0 and zi <= dd + math.sqrt(3) / 2 * vs
    assert 200 < want.sum() < len(ijk) - 200  # both outcomes well represented
    np.testing.assert_array_equal(got, want)
    # The lens matters here: the same camera without distortion splits differently.
    plain = visible_voxels(ijk, vs, origin, **{**cams, "distortion": torch.zeros(1, 5)})
    assert (plain != want).sum() > 50


# --- per sample and over the set ------------------------------------------------------------------------


def test_sample_metrics_split_by_visibility():
    # Sample A with x < 2 visible (the same rule on both grids).
    m = geometry_sample_metrics(A_P, A_P_LAB, A_GT, A_GT_LAB, NUM_LABELS, A_P[:, 0] < 2, A_GT[:, 0] < 2)
    # All: P ∩ G = {0, 1, 2}, P ∪ G = {0..5}: IoU 1/2. Chamfer: P->G distances 0, 0, 0, 1 (x4 to x3),
    # 2 (x5 to x3): mean 3/5; G->P 0, 0, 0, 1: mean 1/4; 0.5 * (0.6 + 0.25) = 0.425. mIoU 2/9.
    assert m["iou"] == pytest.approx(0.5)
    assert m["chamfer"] == pytest.approx(0.425)
    assert m["miou"] == pytest.approx(2 / 9)
    # Visible: P = {x0 car, x1 road}, G = {x0 car, x1 car}: IoU 1, Chamfer 0; car: TP 1, FN 1 ->
    # 1/2, road: FP 1 -> 0: mIoU 1/4.
    assert (m["iou_visible"], m["chamfer_visible"]) == (1.0, 0.0)
    assert m["miou_visible"] == pytest.approx(0.25)
    # Invisible: P = {x2 road, x4 car, x5 building}, G = {x2 road, x3 road}: IoU 1/4; Chamfer
    # P->G 0, 1, 2 (mean 1), G->P 0, 1 (mean 1/2): 0.75; road 1/2, car 0, building 0: mIoU 1/6.
    assert m["iou_invisible"] == pytest.approx(0.25)
    assert m["chamfer_invisible"] == pytest.approx(0.75)
    assert m["miou_invisible"] == pytest.approx(1 / 6)
    assert (m["num_pred"], m["num_gt"], m["num_pred_visible"], m["num_gt_visible"]) == (5, 4, 2, 2)
    # The splits partition the confusion; its occupied block over the total is the IoU.
    np.testing.assert_array_equal(m["confusion_visible"] + m["confusion_invisible"], m["confusion"])
    assert m["confusion"][:E, :E].sum() / m["confusion"].sum() == pytest.approx(m["iou"])
    # torch in, the same out.
    t = geometry_sample_metrics(*(torch.from_numpy(np.asarray(x)) for x in (A_P, A_P_LAB, A_GT, A_GT_LAB)),
                                NUM_LABELS, torch.from_numpy(A_P[:, 0] < 2), torch.from_numpy(A_GT[:, 0] < 2))
    assert {k: v for k, v in t.items() if "confusion" not in k} == pytest.approx(
        {k: v for k, v in m.items() if "confusion" not in k})


def test_summary_sums_confusions_and_takes_chamfer_quantiles():
    a = geometry_sample_metrics(A_P, A_P_LAB, A_GT, A_GT_LAB, NUM_LABELS, A_P[:, 0] < 2, A_GT[:, 0] < 2)
    # Sample B: one car voxel, predicted right, visible. Its invisible split is empty on both sides:
    # IoU nan (skipped), Chamfer 0.
    b = geometry_sample_metrics(row([0]), [CAR], row([0]), [CAR], NUM_LABELS, np.array([True]), np.array([True]))
    assert math.isnan(b["iou_invisible"]) and b["chamfer_invisible"] == 0.0
    s = summarise([a, b])
    assert s["num_samples"] == 2.0
    assert s["iou"] == pytest.approx((0.5 + 1.0) / 2)
    assert s["iou_visible"] == pytest.approx(1.0)
    assert s["iou_invisible"] == pytest.approx(0.25)  # B's nan skipped
    # Summed confusion: car TP 2, FP 1, FN 1 -> 1/2; road 1/3; building 0: mIoU 5/18 (the mean of
    # the per-sample mIoUs, (2/9 + 1) / 2 = 11/18, is not the dataset mIoU).
    assert s["miou"] == pytest.approx(5 / 18)
    assert (s["label_iou_car"], s["label_iou_road"], s["label_iou_building"]) == pytest.approx((0.5, 1 / 3, 0.0))
    # Visible: car->car 2, car->road 1: car 2/3, road 0: mIoU 1/3. Invisible: A's alone, 1/6.
    assert s["miou_visible"] == pytest.approx(1 / 3)
    assert s["miou_invisible"] == pytest.approx(1 / 6)
    # Chamfer over samples [0.425, 0]: linear quantiles q * 0.425.
    assert s["chamfer_mean"] == pytest.approx(0.2125)
    for q in (50, 60, 70, 80, 90):
        assert s[f"chamfer_q{q}"] == pytest.approx(q / 100 * 0.425)
        assert s[f"chamfer_invisible_q{q}"] == pytest.approx(q / 100 * 0.75)
        assert s[f"chamfer_visible_q{q}"] == 0.0
    assert s["gt_visible_fraction"] == pytest.approx(3 / 5)
    assert all(isinstance(v, float) for v in s.values())
    json.dumps(s)
    with pytest.raises(InputError):
        summarise([])


def test_summary_quantiles_match_numpy_and_survive_empty_predictions():
    wall = box((0, 0, 0), (1, 4, 4))
    lab = np.full(len(wall), ROAD)
    vis = np.ones(len(wall), bool)

    def sample(shift=None):
        p = EMPTY if shift is None else wall + [shift, 0, 0]
        return geometry_sample_metrics(p, lab[:len(p)], wall, lab, NUM_LABELS, vis[:len(p)], vis)

    # Chamfers 1, 3, 0, 2, 4 (walls shifted by that many voxels): numpy's linear quantiles.
    s = summarise([sample(x) for x in (1, 3, 0, 2, 4)], quantiles=(0.5, 0.75, 0.9))
    want = np.quantile([1.0, 3.0, 0.0, 2.0, 4.0], [0.5, 0.75, 0.9])
    assert [s["chamfer_q50"], s["chamfer_q75"], s["chamfer_q90"]] == pytest.approx(want.tolist())
    # Chamfers 1, 2, inf (an empty prediction): q50 is the middle sample, 2; q60 interpolates
    # towards inf: inf (not the nan of inf - inf); the mean is inf.
    s = summarise([sample(1), sample(2), sample()])
    assert s["chamfer_q50"] == pytest.approx(2.0)
    assert s["chamfer_q60"] == math.inf and s["chamfer_mean"] == math.inf
    assert s["iou"] == pytest.approx(0.0)  # every shifted wall misses entirely
