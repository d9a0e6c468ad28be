"""Plane-sweep stereo (`reconstruct.stereo.sweep`): the warp's pixel convention, each cost on an analytic
textured plane seen by two pinhole cameras, winner-take-all's refinement and confidence, and the
same bytes whatever the thread count."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from scube_sim.camera import Intrinsics
from scube_sim.errors import InputError
from scube_sim.reconstruct.stereo import (
    combine_costs,
    inverse_depth_hypotheses,
    sweep_cost,
    warp_to_reference,
    winner_take_all,
)
from scube_sim.transforms import invert_pose

W, H, F = 96, 64, 200.0
PLANE_Z = 10.0  # metres: the plane z = PLANE_Z of the world, which is the reference camera's frame
BASELINE = (1.0, 0.2, 0.0)  # the source camera's centre in the reference frame: 20 px, 4 px of motion
WINDOW = 7
INTR = Intrinsics(W, H, F, F, W / 2, H / 2)
DEPTHS = inverse_depth_hypotheses(4.0, 40.0, 128)  # PLANE_Z falls between two hypotheses


def _texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(..., ) plane coordinates in metres -> (3, ...) RGB in [0.1, 0.9]: seeded sums of sinusoids,
    wavelengths 0.3-1.5 m (6-30 pixels at the plane's distance), one mix per channel."""
    rng = np.random.default_rng(7)
    theta, lam, phase = rng.uniform(0, np.pi, 8), rng.uniform(0.3, 1.5, 8), rng.uniform(0, 2 * np.pi, 8)
    waves = np.stack([np.sin(2 * np.pi * (x * np.cos(t) + y * np.sin(t)) / s + p)
                      for t, s, p in zip(theta, lam, phase)])
    mix = rng.uniform(0.2, 1.0, (3, 8))
    return 0.5 + 0.4 * np.tensordot(mix / mix.sum(1, keepdims=True), waves, axes=1)


def _render(cam_to_world: np.ndarray, intr: Intrinsics = INTR) -> torch.Tensor:
    """(3, H, W) float32: each pixel centre's ray (pixel (u, v) spans [u, u + 1)) met with the
    plane, the texture read there (a point sample: no lens blur)."""
    v, u = np.meshgrid(np.arange(intr.height) + 0.5, np.arange(intr.width) + 0.5, indexing="ij")
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1)
    d = rays @ cam_to_world[:3, :3].T
    o = cam_to_world[:3, 3]
    s = (PLANE_Z - o[2]) / d[..., 2]
    return torch.from_numpy(_texture(o[0] + s * d[..., 0], o[1] + s * d[..., 1]).astype(np.float32))


def _pose(centre=(0.0, 0.0, 0.0), yaw_deg: float = 0.0) -> np.ndarray:
    t = np.eye(4)
    a = np.deg2rad(yaw_deg)  # about the camera's y axis (down): a pan
    t[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    t[:3, 3] = centre
    return t


def _pair(src_pose: np.ndarray):
    ref_pose = _pose()
    return _render(ref_pose), _render(src_pose), invert_pose(src_pose) @ ref_pose


def _interior() -> np.ndarray:
    """(H, W) bool: reference pixels whose whole window sees the plane in both views, with a margin
    (the source sees the plane shifted by -F * baseline / PLANE_Z pixels)."""
    m = WINDOW // 2 + 2
    du, dv = (int(np.ceil(F * b / PLANE_Z)) for b in BASELINE[:2])
    inside = np.zeros((H, W), bool)
    inside[m + dv:H - m, m + du:W - m] = True
    return inside


# --- the warp -------------------------------------------------------------------------------------


def test_an_identity_warp_returns_the_source():
    src = _render(_pose())
    warped, valid = warp_to_reference(src, INTR.K, INTR.K, np.eye(4), DEPTHS[:5], (H, W))
    assert warped.shape == (5, 3, H, W) and valid.shape == (5, H, W)
    assert bool(valid.all())
    # up to the float32 rounding of grid_sample's normalised coordinates
    torch.testing.assert_close(warped, src[None].expand(5, -1, -1, -1), rtol=0, atol=1e-5)


def test_the_warp_keeps_the_half_pixel_convention_across_resolutions():
    # the source at twice the resolution: reference pixel i's centre i + 0.5 lands on source
    # coordinate 2 i + 1, halfway between source centres 2 i + 0.5 and 2 i + 1.5
    big = INTR.scaled(2.0)
    v, u = torch.meshgrid(torch.arange(big.height) + 0.5, torch.arange(big.width) + 0.5, indexing="ij")
    src = torch.stack([u, v]).to(torch.float32)  # each pixel holds its centre's coordinates
    warped, valid = warp_to_reference(src, big.K, INTR.K, np.eye(4), torch.tensor([7.0]), (H, W))
    assert bool(valid.all())
    v0, u0 = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    torch.testing.assert_close(warped[0, 0], 2 * u0.float(), rtol=0, atol=1e-4)
    torch.testing.assert_close(warped[0, 1], 2 * v0.float(), rtol=0, atol=1e-4)


def test_points_outside_the_source_are_invalid_and_cost_nan():
    ref, src, ref_to_src = _pair(_pose(BASELINE))
    depth = torch.tensor([PLANE_Z])
    _, valid = warp_to_reference(src, INTR.K, INTR.K, ref_to_src, depth, (H, W))
    shift = F * BASELINE[0] / PLANE_Z  # the source sees column u at u - 20
    assert not bool(valid[0, :, : int(shift) - 1].any()) and bool(valid[0, 10:, int(shift) + 1:].all())
    cost = sweep_cost(ref, src, INTR.K, INTR.K, ref_to_src, depth, cost="ad", window=WINDOW)
    assert torch.equal(torch.isnan(cost), ~valid)
    behind = sweep_cost(ref, src, INTR.K, INTR.K, invert_pose(_pose((0, 0, 20.0))), depth, cost="census")
    assert bool(torch.isnan(behind).all())  # the plane lies behind a source 20 m ahead


# --- each cost on the textured plane --------------------------------------------------------------


@pytest.mark.parametrize("cost", ["ad", "ncc", "census", "census_source"])
def test_each_cost_recovers_the_plane_within_half_a_percent(cost):
    ref, src, ref_to_src = _pair(_pose(BASELINE))
    volume = sweep_cost(ref, src, INTR.K, INTR.K, ref_to_src, DEPTHS, cost=cost, window=WINDOW)
    assert volume.shape == (len(DEPTHS), H, W)
    depth, _, conf = winner_take_all(volume, DEPTHS)
    inner = torch.from_numpy(_interior())
    rel = (depth[inner].double() - PLANE_Z).abs() / PLANE_Z
    # the plane's depth (the interior's median) within 0.5 %, nearly every pixel too; the census of
    # the source, warped by nearest sampling, snaps every pixel by the same fraction of a pixel
    # (a coherent bias of 0.3 % here), the others are unbiased
    assert float(rel.median()) < (0.005 if cost == "census_source" else 0.0025), (cost, float(rel.median()))
    assert float(rel.quantile(0.95)) < 0.005 and float(rel.max()) < 0.01, (cost, float(rel.max()))
    assert float(conf[inner].median()) > 0.3, cost


@pytest.mark.parametrize("yaw_deg", [0.0, 3.0])
def test_a_zero_baseline_pair_gives_low_confidence(yaw_deg):
    # no translation: every plane maps the source the same way, the cost curve is flat
    ref, src, ref_to_src = _pair(_pose(yaw_deg=yaw_deg))
    inner = torch.from_numpy(_interior())
    for cost in ("ad", "ncc", "census"):
        volume = sweep_cost(ref, src, INTR.K, INTR.K, ref_to_src, DEPTHS, cost=cost, window=WINDOW)
        _, _, conf = winner_take_all(volume, DEPTHS)
        assert float(conf[inner].max()) < 0.05, (cost, float(conf[inner].max()))


def test_two_sources_average_where_seen():
    ref, left, l_to = _pair(_pose(BASELINE))
    _, right, r_to = _pair(_pose((-BASELINE[0], -BASELINE[1], 0.0)))
    a = sweep_cost(ref, left, INTR.K, INTR.K, l_to, DEPTHS, cost="ncc")
    b = sweep_cost(ref, right, INTR.K, INTR.K, r_to, DEPTHS, cost="ncc")
    both = combine_costs([a, b])
    only_a = torch.isfinite(a) & torch.isnan(b)
    assert torch.equal(both[only_a], a[only_a])
    seen = torch.isfinite(a) & torch.isfinite(b)
    torch.testing.assert_close(both[seen], (a[seen] + b[seen]) / 2)
    depth, _, _ = winner_take_all(both, DEPTHS)
    inner = torch.from_numpy(_interior())
    assert float(((depth[inner] - PLANE_Z).abs() / PLANE_Z).max()) < 0.005


# --- winner takes all -----------------------------------------------------------------------------


def test_the_parabola_finds_a_vertex_between_hypotheses():
    inv = 1.0 / DEPTHS
    true_inv = 0.3 * inv[40] + 0.7 * inv[41]
    cost = ((inv - true_inv) ** 2).to(torch.float32)[:, None, None].expand(-1, 2, 3).clone()
    cost[:, 1, 2] = float("nan")  # a pixel no source sees
    depth, best, conf = winner_take_all(cost, DEPTHS)
    torch.testing.assert_close(depth[0, 0].double(), 1.0 / true_inv, rtol=1e-4, atol=0)
    assert torch.isnan(depth[1, 2]) and torch.isnan(best[1, 2]) and conf[1, 2] == 0
    assert float(conf[0, 0]) > 0.9


def test_two_equal_minima_give_zero_confidence():
    cost = torch.ones(len(DEPTHS), 1, 1)
    cost[20], cost[90] = 0.1, 0.1
    _, _, conf = winner_take_all(cost, DEPTHS)
    assert float(conf) == 0.0


def test_hypotheses_are_uniform_in_inverse_depth():
    d = inverse_depth_hypotheses(0.5, 90.0, 64)
    assert d.dtype == torch.float64 and d.shape == (64,)
    assert float(d[0]) == pytest.approx(0.5) and float(d[-1]) == pytest.approx(90.0)
    step = torch.diff(1.0 / d)
    torch.testing.assert_close(step, torch.full_like(step, float(step[0])))
    with pytest.raises(InputError):
        inverse_depth_hypotheses(5.0, 1.0, 10)


def test_the_bytes_do_not_depend_on_the_thread_count():
    ref, src, ref_to_src = _pair(_pose(BASELINE))
    before = torch.get_num_threads()
    runs = []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            out = []
            for cost in ("ad", "ncc", "census", "census_source"):
                volume = sweep_cost(ref, src, INTR.K, INTR.K, ref_to_src, DEPTHS, cost=cost, window=WINDOW)
                out += [volume, *winner_take_all(volume, DEPTHS)]
            runs.append([t.numpy().tobytes() for t in out])
    finally:
        torch.set_num_threads(before)
    assert runs[0] == runs[1]


def test_per_pixel_depth_maps_warp_as_planes():
    # constant depth maps warp exactly as the planes of those depths; a non-finite depth is invalid
    torch.manual_seed(1)
    src = torch.rand(3, 24, 32)
    k = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, 3] = [0.3, -0.1, 0.05]
    depths = torch.tensor([2.0, 5.0, 11.0], dtype=torch.float64)
    planes, valid = warp_to_reference(src, k, k, pose, depths, (24, 32), chunk=2)
    maps = depths[:, None, None].expand(3, 24, 32).clone()
    per_pixel, valid_pp = warp_to_reference(src, k, k, pose, maps, (24, 32), chunk=2)
    assert torch.equal(planes, per_pixel) and torch.equal(valid, valid_pp)
    maps[1, 3, 4] = float("nan")
    _, valid_nan = warp_to_reference(src, k, k, pose, maps, (24, 32))
    assert not valid_nan[1, 3, 4] and torch.equal(valid_nan[0], valid[0])


def test_the_census_cost_counts_only_neighbours_on_the_image_and_valid():
    # the sliced census against a direct count with explicit shifts (NaN off the image)
    from scube_sim.reconstruct.stereo.sweep import cost_census, grey
    torch.manual_seed(2)
    ref, warped = torch.rand(3, 9, 11), torch.rand(2, 3, 9, 11)
    valid = torch.rand(2, 9, 11) > 0.3
    r, s = grey(ref), grey(warped)
    rp = torch.nn.functional.pad(r, (1, 1, 1, 1), value=float("nan"))
    sp = torch.nn.functional.pad(s, (1, 1, 1, 1), value=float("nan"))
    vp = torch.nn.functional.pad(valid, (1, 1, 1, 1), value=False)
    differ = torch.zeros(2, 9, 11)
    counted = torch.zeros(2, 9, 11)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == dx == 0:
                continue
            ok = vp[:, 1 + dy:10 + dy, 1 + dx:12 + dx]
            br = rp[1 + dy:10 + dy, 1 + dx:12 + dx] < r
            bs = sp[:, 1 + dy:10 + dy, 1 + dx:12 + dx] < s
            differ += ((br[None] != bs) & ok).float()
            counted += ok.float()
    per_pixel = differ / counted.clamp_min(1.0)
    ok = valid & (counted > 0)
    expect = torch.nn.functional.avg_pool2d(torch.where(ok, per_pixel, 0.0)[:, None], 3, 1, 1)[:, 0] / \
        torch.nn.functional.avg_pool2d(ok.float()[:, None], 3, 1, 1)[:, 0].clamp_min(1e-12)
    got = cost_census(ref, warped, valid, 3)
    assert torch.equal(torch.isnan(got), ~ok)
    assert torch.allclose(got[ok], expect[ok], atol=1e-6)
