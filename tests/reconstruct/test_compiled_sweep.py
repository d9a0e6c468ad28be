"""The compiled plane sweep (`reconstruct.stereo.compiled`, `_sweep.cpp`) against the torch reference
(`mvs._volume_reference`): an analytic textured plane seen by three sources, random images with
random poses and masks (any channel count, more sources than four, other windows), the same bytes
for any thread count and for the portable build, the core's choice (`SCUBE_SIM_CORE`), and
`stereo_depth` end to end. The compiled semi-global aggregation and winner-take-all against theirs
(`sgm.semi_global_reference`, `winner.winner_take_all_reference`): the same bytes.

Tolerance: the compiled sweep repeats the reference's arithmetic (torch's vectorised CPU kernels,
fused multiply-adds included), so on a CPU where torch runs those kernels the outputs are the same
bytes. Elsewhere a warped sample may differ in its last bit, which can flip a census bit now and
then: a cost moves by a few 1/48 of a bit share over the window. Hence the bounds: at most 1 % of
the volume's entries differ (NaN or not alike), by at most 0.1, NaN patterns differ on at most
0.1 %, and the winner-take-all hypothesis agrees on at least 99.5 % of the pixels. The
aggregation and the winner-take-all are single float32 / float64 operations in a fixed order (no
fused ones): the same bytes on any CPU.

The compiled sweep is required: where it does not import the tests fail, unless
SCUBE_SIM_ALLOW_NO_CORE=1 (a user who cannot build it), which skips them with the reason.
"""

from __future__ import annotations

import os
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from scube_sim.raytrace import compiled as tracer_compiled
from scube_sim.raytrace.compiled import CoreUnavailable, CoreUnavailableWarning
from scube_sim.reconstruct.config import StereoConfig
from scube_sim.reconstruct.stereo import compiled, mvs, stereo_depth
from scube_sim.reconstruct.stereo.sgm import semi_global_reference
from scube_sim.reconstruct.stereo.sweep import inverse_depth_hypotheses
from scube_sim.reconstruct.stereo.winner import winner_take_all, winner_take_all_reference
from scube_sim.transforms import invert_pose

ALLOW_NO_CORE = os.environ.get("SCUBE_SIM_ALLOW_NO_CORE", "") == "1"
MAX_DIFFERING = 0.01  # share of volume entries that may differ
MAX_DIFF = 0.1  # census share of bits: the largest difference of an entry both compute
MAX_NAN_MISMATCH = 0.001  # share of entries NaN in one and not the other
MIN_WTA_AGREEMENT = 0.995  # share of pixels whose winner-take-all hypothesis agrees


@pytest.fixture(autouse=True)
def _require_compiled():
    if compiled.available():
        return
    if ALLOW_NO_CORE:
        pytest.skip(f"SCUBE_SIM_ALLOW_NO_CORE=1 and the compiled stereo sweep is not built: {compiled.load_error()}")
    pytest.fail(f"the compiled stereo sweep is not built ({compiled.load_error()}): rebuild the package "
                "(pip install -e .) or set SCUBE_SIM_ALLOW_NO_CORE=1")


# --- scenes ------------------------------------------------------------------------------------------


def _rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return z @ y @ x


def _pose(centre, angles=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(4, 4) camera -> world of a camera at `centre` (metres) turned by `angles` (radians, x y z)."""
    t = np.eye(4)
    t[:3, :3] = _rotation(*angles)
    t[:3, 3] = centre
    return t


def _texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Plane coordinates (metres) -> (3, ...) RGB in [0.1, 0.9]: seeded sums of sinusoids."""
    rng = np.random.default_rng(3)
    theta, lam, phase = rng.uniform(0, np.pi, 8), rng.uniform(0.25, 1.2, 8), rng.uniform(0, 2 * np.pi, 8)
    waves = np.stack([np.sin(2 * np.pi * (x * np.cos(t) + y * np.sin(t)) / s + p)
                      for t, s, p in zip(theta, lam, phase)])
    mix = rng.uniform(0.2, 1.0, (3, 8))
    return 0.5 + 0.4 * np.tensordot(mix / mix.sum(1, keepdims=True), waves, axes=1)


def _plane_image(k: np.ndarray, cam_to_world: np.ndarray, hw: tuple[int, int], plane_z: float) -> torch.Tensor:
    """(3, h, w) float32 in [0, 1] (8-bit levels, as a camera's): the textured world plane z = plane_z
    seen by a pinhole camera K at `cam_to_world` (grey where a ray misses it)."""
    h, w = hw
    v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    rays = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], -1) @ cam_to_world[:3, :3].T
    o = cam_to_world[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (plane_z - o[2]) / rays[..., 2]
    hit = np.isfinite(s) & (s > 0)
    s = np.where(hit, s, 0.0)
    rgb = np.where(hit[None], _texture(o[0] + s * rays[..., 0], o[1] + s * rays[..., 1]), 0.5)
    return torch.from_numpy(np.round(np.clip(rgb, 0, 1) * 255).astype(np.float32) / 255.0)


def _k(f: float, hw: tuple[int, int]) -> np.ndarray:
    h, w = hw
    return np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])


def _plane_case():
    """Reference at the origin looking along +z at the plane z = 8 m; three sources beside it."""
    hw = (64, 96)
    k = _k(90.0, hw)
    ref_pose = np.eye(4)
    ref = _plane_image(k, ref_pose, hw, 8.0)
    srcs, views = [], []
    for centre, angles in (((0.6, 0.0, 0.0), (0.0, -0.03, 0.0)), ((-0.5, 0.25, 0.0), (0.01, 0.04, 0.0)),
                           ((0.2, -0.3, 0.4), (0.0, 0.0, 0.02))):
        pose = _pose(centre, angles)
        srcs.append((_plane_image(k, pose, hw, 8.0), k, None, None))
        views.append(SimpleNamespace(ref_to_src=invert_pose(pose) @ ref_pose))
    cfg = StereoConfig(hypotheses=48, near_m=3.0, far_m=30.0, scale=1.0)
    hyps = inverse_depth_hypotheses(cfg.near_m, cfg.far_m, cfg.hypotheses)
    return ref, k, torch.ones(hw, dtype=torch.bool), hw, srcs, views, hyps, cfg


def _noise_image(rng, channels: int, hw: tuple[int, int]) -> torch.Tensor:
    """(C, h, w) float32 in [0, 1]: smoothed noise on 8-bit levels, flat patches included (ties)."""
    x = gaussian_filter(rng.random((channels, *hw)), (0, 1.2, 1.2))
    x = (x - x.min()) / (x.max() - x.min() + 1e-9)
    x[:, : hw[0] // 6, : hw[1] // 5] = 0.5  # a flat patch: every census comparison ties
    return torch.from_numpy(np.round(x * 255).astype(np.float32) / 255.0)


def _random_case(seed: int, n_sources: int, channels: int = 3, window: int = 7):
    """Random images, sizes, poses and masks: reference-side masks, source-side masks and unusable
    reference pixels on some of the sources."""
    rng = np.random.default_rng(seed)
    hw = (40, 56)
    k_ref = _k(60.0, hw)
    ref = _noise_image(rng, channels, hw)
    ref_ok = torch.ones(hw, dtype=torch.bool)
    ref_ok[:, -5:] = False
    srcs, views = [], []
    for s in range(n_sources):
        shw = (int(rng.integers(32, 48)), int(rng.integers(44, 64)))
        k_src = _k(float(rng.uniform(50, 70)), shw)
        pose = _pose(rng.normal(0, 0.5, 3), rng.normal(0, 0.05, 3))
        ref_mask = src_mask = None
        if s % 3 == 1:
            ref_mask = torch.from_numpy(gaussian_filter(rng.random(hw), 3) > 0.52)
        if s % 3 == 2:
            src_mask = torch.from_numpy((gaussian_filter(rng.random(shw), 3) > 0.52).astype(np.float32))[None]
        srcs.append((_noise_image(rng, channels, shw), k_src, ref_mask, src_mask))
        views.append(SimpleNamespace(ref_to_src=invert_pose(pose)))
    cfg = StereoConfig(hypotheses=24, near_m=1.5, far_m=25.0, scale=1.0, window=window, chunk=5)
    hyps = inverse_depth_hypotheses(cfg.near_m, cfg.far_m, cfg.hypotheses)
    return ref, k_ref, ref_ok, hw, srcs, views, hyps, cfg


# --- comparison --------------------------------------------------------------------------------------


def _agreement(a: np.ndarray, b: np.ndarray) -> dict:
    """Share of differing entries (NaN alike counts as equal), the largest difference where both are
    finite, and the share of entries NaN in one only."""
    same = (a == b) | (np.isnan(a) & np.isnan(b))
    both = np.isfinite(a) & np.isfinite(b)
    diff = float(np.abs(a[both] - b[both]).max()) if both.any() else 0.0
    return {"differing": float(1 - same.mean()), "max_diff": diff,
            "nan_mismatch": float((np.isnan(a) != np.isnan(b)).mean())}


def _check_close(out, ref, hyps) -> None:
    vol_c, vol_r = out[0].numpy(), ref[0].numpy()
    assert vol_c.shape == vol_r.shape and vol_c.dtype == np.float32
    stats = _agreement(vol_c, vol_r)
    assert stats["differing"] <= MAX_DIFFERING and stats["max_diff"] <= MAX_DIFF, stats
    assert stats["nan_mismatch"] <= MAX_NAN_MISMATCH, stats
    for name, a_list, b_list in zip(("best", "arg", "worst"), out[1:], ref[1:]):
        for a, b in zip(a_list, b_list, strict=True):
            assert a.dtype == b.dtype and a.shape == b.shape, name
            assert (a.numpy() != b.numpy()).mean() <= MAX_DIFFERING, name
    inf = torch.tensor(float("inf"))
    win_c = torch.where(torch.isnan(out[0]), inf, out[0]).argmin(0)
    win_r = torch.where(torch.isnan(ref[0]), inf, ref[0]).argmin(0)
    assert (win_c == win_r).float().mean() >= MIN_WTA_AGREEMENT
    d_c, _, _ = winner_take_all(out[0], hyps)
    d_r, _, _ = winner_take_all(ref[0], hyps)
    alike = (d_c == d_r) | (torch.isnan(d_c) & torch.isnan(d_r))
    assert alike.float().mean() >= MIN_WTA_AGREEMENT


def _bytes(out) -> list[bytes]:
    return [out[0].numpy().tobytes()] + [t.numpy().tobytes() for part in out[1:] for t in part]


# --- tests -------------------------------------------------------------------------------------------


def test_the_plane_seen_by_three_sources_matches_the_reference_and_recovers_its_depth():
    case = _plane_case()
    out = compiled.volume(*case, None)
    ref = mvs._volume_reference(*case, None)
    _check_close(out, ref, case[6])
    # not two alike failures: the compiled volume finds the plane at 8 m inside the image
    depth, _, _ = winner_take_all(out[0], case[6])
    inner = depth[12:-12, 16:-16].numpy()
    assert np.nanmedian(np.abs(inner - 8.0) / 8.0) < 0.01


@pytest.mark.parametrize("seed, n_sources, channels, window", [
    (0, 2, 3, 7), (1, 6, 3, 7), (2, 3, 1, 5), (3, 5, 2, 9), (4, 3, 5, 3),
])
def test_random_views_and_masks_match_the_reference(seed, n_sources, channels, window):
    case = _random_case(seed, n_sources, channels, window)
    out = compiled.volume(*case, None)
    ref = mvs._volume_reference(*case, None)
    _check_close(out, ref, case[6])
    assert torch.isfinite(out[0]).any()  # the sources see part of the reference


def test_the_bytes_do_not_depend_on_the_thread_count_or_the_build():
    case = _random_case(5, 4)
    first = _bytes(compiled.volume(*case, None, threads=1))
    for threads in (2, 3):
        assert _bytes(compiled.volume(*case, None, threads=threads)) == first, threads
    assert _bytes(compiled.volume(*case, None, threads=2, portable=True)) == first
    case7 = _random_case(6, 7)  # more than four sources: the general robust mean
    first = _bytes(compiled.volume(*case7, None, threads=1))
    assert _bytes(compiled.volume(*case7, None, threads=3)) == first
    assert _bytes(compiled.volume(*case7, None, threads=1, portable=True)) == first


def test_the_core_follows_scube_sim_core(monkeypatch):
    from scube_sim.reconstruct.stereo import sgm

    case = _plane_case()
    cost = _quantised_volume(3, (8, 6, 7))
    calls = []
    for name in ("volume", "semi_global", "winner_take_all"):
        real = getattr(compiled, name)
        monkeypatch.setattr(compiled, name,
                            lambda *a, _real=real, _name=name, **k: calls.append(_name) or _real(*a, **k))

    def run_all():
        mvs._volume(*case, None)
        sgm.semi_global(cost, 0.03, 0.2)
        winner_take_all(cost, case[6][:8])

    monkeypatch.delenv("SCUBE_SIM_CORE", raising=False)
    assert compiled.default_core_name() == "compiled"
    run_all()
    assert calls == ["volume", "semi_global", "winner_take_all"]
    monkeypatch.setenv("SCUBE_SIM_CORE", "reference")
    assert compiled.default_core_name() == "reference"
    run_all()
    assert len(calls) == 3
    monkeypatch.setenv("SCUBE_SIM_CORE", "compiled")
    monkeypatch.setattr(compiled, "_sweep", None)
    with pytest.raises(CoreUnavailable):
        compiled.default_core_name()
    # not built, not asked for by name: the torch path, said once
    monkeypatch.delenv("SCUBE_SIM_CORE")
    monkeypatch.setattr(tracer_compiled, "_WARNED", set())
    with pytest.warns(CoreUnavailableWarning, match="stereo"):
        assert compiled.default_core_name() == "reference"


def test_stereo_depth_end_to_end_matches_the_reference(monkeypatch):
    from tests.reconstruct.stereo.test_mvs import CFG, _frames, _shot
    from tests.reconstruct.stereo.test_sweep import _pose as _yaw_pose

    ref, _ = _shot("ref", _yaw_pose(), 0.0)
    others = [_shot("cam", _yaw_pose((0.8, 0.1, 0.0)), 0.0)[0]]
    context = {1: [_shot("ref", _yaw_pose((0.3, 0.0, 0.5)), 0.1)[0]],
               -1: [_shot("ref", _yaw_pose((-0.4, 0.1, -0.5)), -0.1)[0]]}
    frames = _frames(ref, context, others=others)
    cfg = CFG.model_copy(update={"hypotheses": 48})
    monkeypatch.setenv("SCUBE_SIM_CORE", "compiled")
    fast = stereo_depth(frames, 0, cfg)
    monkeypatch.setenv("SCUBE_SIM_CORE", "reference")
    slow = stereo_depth(frames, 0, cfg)
    assert len(fast.sources) == len(slow.sources) >= 2
    for a, b in ((fast.depth, slow.depth), (fast.confidence, slow.confidence)):
        alike = (a == b) | (np.isnan(a) & np.isnan(b))
        assert alike.mean() >= MIN_WTA_AGREEMENT, alike.mean()
    assert (fast.confidence >= 0.5).mean() > 0.3  # it measured the plane


def _quantised_volume(seed: int, shape: tuple[int, int, int]) -> torch.Tensor:
    """(D, h, w) float32 costs on census steps (1/48: ties and plateaus), NaN entries scattered, a
    corner NaN at every hypothesis, a flat pixel."""
    rng = np.random.default_rng(seed)
    c = (np.round(rng.random(shape) * 48) / 48).astype(np.float32)
    c[rng.random(shape) < 0.1] = np.nan
    c[:, :2, :3] = np.nan
    c[:, -1, -1] = 0.25
    return torch.from_numpy(c)


@pytest.mark.parametrize("shape, paths", [((24, 20, 33), 4), ((24, 20, 33), 8), ((9, 31, 12), 8), ((3, 5, 4), 4)])
def test_semi_global_matches_the_reference_bytes(shape, paths):
    cost = _quantised_volume(1, shape)
    ref = semi_global_reference(cost, 0.03, 0.2, paths=paths, fill=0.5)
    out = compiled.semi_global(cost, 0.03, 0.2, paths=paths, fill=0.5, threads=1)
    assert out.dtype == torch.float32 and out.shape == cost.shape
    assert torch.equal(torch.isnan(out), torch.isnan(cost))
    assert out.numpy().tobytes() == ref.numpy().tobytes()
    for threads, portable in ((2, False), (3, False), (2, True)):
        again = compiled.semi_global(cost, 0.03, 0.2, paths=paths, fill=0.5, threads=threads, portable=portable)
        assert again.numpy().tobytes() == out.numpy().tobytes()


@pytest.mark.parametrize("shape", [(32, 18, 27), (2, 4, 5), (5, 9, 3)])
def test_winner_take_all_matches_the_reference_bytes(shape):
    cost = _quantised_volume(2, shape)
    depths = inverse_depth_hypotheses(2.0, 90.0, shape[0])
    ref = winner_take_all_reference(cost, depths)
    out = compiled.winner_take_all(cost, depths, threads=1)
    inf = torch.tensor(float("inf"))
    assert torch.equal(out[3], torch.where(torch.isnan(cost), inf, cost).argmin(0))
    for a, b in zip(out[:3], ref):
        assert a.dtype == b.dtype and a.numpy().tobytes() == b.numpy().tobytes()
    for threads, portable in ((2, False), (3, False), (2, True)):
        again = compiled.winner_take_all(cost, depths, threads=threads, portable=portable)
        assert [t.numpy().tobytes() for t in again] == [t.numpy().tobytes() for t in out]
    assert [t.numpy().tobytes() for t in winner_take_all(cost, depths)] == [t.numpy().tobytes() for t in out[:3]]
