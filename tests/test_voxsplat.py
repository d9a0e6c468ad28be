"""scube_sim.voxsplat: activations against closed forms, the float64 origin, voxel keys, the .npz.

Expectations come from the module docstring (SCube's activations), scipy (sigmoid, quaternion
rotations, the SH constant) and plain numpy (np.unique / lexsort, numpy.load of the file).
The file-format tests check the current public behaviour only and avoid the exact version number.
"""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from scipy.special import expit

from scube_sim.voxsplat import (
    FORMAT_NAME,
    FORMAT_VERSION,
    NUM_RAW,
    OFFSET,
    OPACITY,
    QUAT,
    RGB,
    SCALE,
    SH_C0,
    Gaussians,
    VoxSplat,
    unique_voxels,
    voxel_keys,
)

PROPS = settings(max_examples=50, deadline=None)


def random_voxsplat(v=12, m=3, voxel_size=0.4, origin=(0.0, 0.0, 0.0), seed=0, logits=False, **kw):
    rng = np.random.default_rng(seed)
    ijk = rng.choice(np.arange(-50, 50), size=(v * 3,), replace=True).reshape(v, 3)
    ijk[:, 0] = np.arange(v) - v // 2  # rows distinct
    params = rng.normal(0.0, 1.0, (v, m, NUM_RAW)).astype(np.float32)
    valid = rng.random((v, m)) < 0.7
    labels = rng.integers(0, 20, v)
    return VoxSplat(ijk, params, voxel_size, np.asarray(origin, float), valid, labels,
                    rng.normal(size=(v, 5)).astype(np.float32) if logits else None, **kw)


def gaussians(n, seed=0, origin=(0.0, 0.0, 0.0), spread=2.0):
    rng = np.random.default_rng(seed)
    return Gaussians(
        means=rng.uniform(-spread, spread, (n, 3)),
        scales=rng.uniform(0.01, 0.3, (n, 3)),
        quats=Rotation.random(n, random_state=rng).as_quat()[:, [3, 0, 1, 2]],
        opacities=rng.uniform(0.05, 0.95, n),
        sh_dc=rng.normal(0, 1, (n, 3)).astype(np.float32),
        origin=np.asarray(origin, np.float64),
    )


# --- layout and constants ---------------------------------------------------------------------

def test_raw_layout_is_offset_opacity_scale_quat_rgb():
    idx = np.arange(NUM_RAW)
    assert NUM_RAW == 14
    assert list(idx[OFFSET]) == [0, 1, 2]
    assert list(idx[OPACITY]) == [3]
    assert list(idx[SCALE]) == [4, 5, 6]
    assert list(idx[QUAT]) == [7, 8, 9, 10]
    assert list(idx[RGB]) == [11, 12, 13]


def test_sh_c0_is_the_degree_zero_real_spherical_harmonic():
    assert SH_C0 == pytest.approx(0.5 / np.sqrt(np.pi), rel=1e-15)


# --- construction and validation --------------------------------------------------------------

def test_constructor_coerces_dtypes_and_defaults():
    vs = VoxSplat([[1, 2, 3], [4, 5, 6]], np.zeros((2, 3, NUM_RAW)), 1)
    assert vs.ijk.dtype == np.int32 and vs.ijk.shape == (2, 3)
    assert vs.params.dtype == np.float32 and vs.params.flags.c_contiguous
    assert vs.origin.dtype == np.float64 and vs.origin.shape == (3,)
    assert isinstance(vs.voxel_size, float)
    assert vs.valid.dtype == bool and vs.valid.shape == (2, 3) and vs.valid.all()
    assert vs.labels.dtype == np.int16 and vs.labels.shape == (2,) and not vs.labels.any()
    assert vs.logits is None
    assert vs.offset_range == 3.0
    assert (vs.num_voxels, vs.gaussians_per_voxel, vs.num_gaussians) == (2, 3, 6)
    vs2 = VoxSplat(np.zeros((2, 3)), np.zeros((2, 1, NUM_RAW)), 1.0, logits=np.ones((2, 4)))
    assert vs2.logits.dtype == np.float32 and vs2.logits.shape == (2, 4)


def test_num_gaussians_counts_valid_slots_only():
    valid = np.array([[True, False], [False, False], [True, True]])
    vs = VoxSplat(np.zeros((3, 3)), np.zeros((3, 2, NUM_RAW)), 0.5, valid=valid)
    assert vs.num_gaussians == 3
    assert "3 Gaussians" in repr(vs)


@pytest.mark.parametrize("params, ijk, needle", [
    (np.zeros((2, 3, 13)), np.zeros((2, 3)), "params"),
    (np.zeros((2, NUM_RAW)), np.zeros((2, 3)), "params"),
    (np.zeros((3, 1, NUM_RAW)), np.zeros((2, 3)), "ijk"),
])
def test_constructor_rejects_shape_mismatches(params, ijk, needle):
    with pytest.raises(ValueError, match=needle):
        VoxSplat(ijk, params, 0.5)


@pytest.mark.parametrize("size", [0.0, -0.1, np.nan, np.inf])
def test_constructor_rejects_bad_voxel_size(size):
    with pytest.raises(ValueError, match="voxel_size"):
        VoxSplat(np.zeros((1, 3)), np.zeros((1, 1, NUM_RAW)), size)


@pytest.mark.parametrize("origin", [[np.nan, 0, 0], [0, np.inf, 0]])
def test_constructor_rejects_nonfinite_origin(origin):
    with pytest.raises(ValueError, match="origin"):
        VoxSplat(np.zeros((1, 3)), np.zeros((1, 1, NUM_RAW)), 0.5, origin=origin)


@pytest.mark.parametrize("group, col", [("offset", 1), ("opacity", 3), ("scale", 6), ("quaternion", 9), ("rgb", 13)])
def test_check_finite_names_the_raw_group_voxel_and_slot(group, col):
    params = np.zeros((4, 3, NUM_RAW), np.float32)
    params[2, 1, col] = np.nan
    vs = VoxSplat(np.zeros((4, 3)), params, 0.5)
    with pytest.raises(ValueError) as err:
        vs.check_finite("scene.npz")
    msg = str(err.value)
    assert msg.startswith("scene.npz:") and f"raw {group}" in msg and "voxel 2" in msg and "slot 1" in msg


def test_check_finite_passes_extreme_but_finite_values():
    params = np.full((1, 1, NUM_RAW), 3e38, np.float32)
    VoxSplat(np.zeros((1, 3)), params, 0.5).check_finite()


@pytest.mark.parametrize("field", ["means", "scales", "quats", "opacities", "sh_dc"])
def test_gaussians_check_finite_names_the_field_and_index(field):
    g = gaussians(5)
    a = getattr(g, field)
    if a.ndim == 1:
        a[3] = np.inf
    else:
        a[3, 0] = np.nan
    with pytest.raises(ValueError) as err:
        g.check_finite("src")
    assert str(err.value).startswith("src:") and field in str(err.value) and "Gaussian 3" in str(err.value)


def test_gaussians_check_finite_origin():
    g = gaussians(2, origin=(0.0, np.nan, 0.0))
    with pytest.raises(ValueError, match="origin"):
        g.check_finite()


# --- activations (paper) against closed forms -------------------------------------------------

def test_voxel_centres_are_ijk_plus_half_times_voxel_size():
    vs = VoxSplat([[0, 0, 0], [-1, 2, -3], [1000, -1000, 7]], np.zeros((3, 1, NUM_RAW)), 0.2)
    expected = np.array([[0.1, 0.1, 0.1], [-0.1, 0.5, -0.5], [200.1, -199.9, 1.5]])
    np.testing.assert_allclose(vs.voxel_centers(), expected, rtol=0, atol=1e-12)
    assert vs.voxel_centers().dtype == np.float64


def test_zero_raw_values_give_the_documented_neutral_gaussian():
    p = np.zeros((1, 1, NUM_RAW), np.float32)
    vs = VoxSplat([[2, 3, 4]], p, 0.5)
    np.testing.assert_allclose(vs.means()[0, 0], [1.25, 1.75, 2.25])  # voxel centre
    assert vs.opacities()[0, 0] == 0.5
    np.testing.assert_array_equal(vs.scales()[0, 0], [1.0, 1.0, 1.0])  # exp(0) metres
    np.testing.assert_array_equal(vs.quats()[0, 0], [1, 0, 0, 0])  # zero quaternion -> identity
    np.testing.assert_array_equal(vs.rotations()[0, 0], np.eye(3))
    np.testing.assert_array_equal(vs.colors()[0, 0], [0.5, 0.5, 0.5])


@pytest.mark.parametrize("offset_range", [3.0, 1.5])
def test_means_are_r_tanh_offset_plus_centre_with_r_offset_range_voxels(offset_range):
    vs = random_voxsplat(offset_range=offset_range, voxel_size=0.25)
    raw = vs.params[..., 0:3].astype(np.float64)
    centres = (vs.ijk[:, None, :].astype(np.float64) + 0.5) * 0.25
    expected = offset_range * 0.25 * np.tanh(raw) + centres
    out = vs.means()
    assert out.shape == (vs.num_voxels, vs.gaussians_per_voxel, 3) and out.dtype == np.float64
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-13)


def test_default_offset_range_is_three_voxels_and_bounds_the_mean():
    p = np.zeros((1, 2, NUM_RAW), np.float32)
    p[0, 0, OFFSET] = 1e4
    p[0, 1, OFFSET] = -1e4
    vs = VoxSplat([[0, 0, 0]], p, 0.1)
    m = vs.means()[0]
    assert np.all(np.isfinite(m))
    np.testing.assert_allclose(m[0], [0.05 + 0.3] * 3, atol=1e-15)
    np.testing.assert_allclose(m[1], [0.05 - 0.3] * 3, atol=1e-15)


def test_opacity_is_sigmoid_of_raw_against_scipy():
    raw = np.linspace(-30, 30, 61, dtype=np.float32)
    p = np.zeros((1, raw.size, NUM_RAW), np.float32)
    p[0, :, 3] = raw
    op = VoxSplat([[0, 0, 0]], p, 1.0).opacities()[0]
    assert op.dtype == np.float64
    np.testing.assert_allclose(op, expit(raw.astype(np.float64)), rtol=1e-12, atol=1e-300)


def test_scale_is_exp_of_raw_in_metres():
    raw = np.array([-5.0, -1.0, 0.0, 0.5, 2.0, 9.0], np.float32)
    p = np.zeros((2, 1, NUM_RAW), np.float32)
    p[0, 0, SCALE] = raw[:3]
    p[1, 0, SCALE] = raw[3:]
    s = VoxSplat(np.zeros((2, 3)), p, 1.0).scales()
    assert s.dtype == np.float64
    np.testing.assert_allclose(s.reshape(-1), np.exp(raw.astype(np.float64)), rtol=1e-14)


def test_rotation_is_quat2rot_of_normalised_q_against_scipy():
    rng = np.random.default_rng(3)
    p = np.zeros((4, 5, NUM_RAW), np.float32)
    q = rng.normal(size=(4, 5, 4)).astype(np.float32) * 7.0  # any norm
    p[..., QUAT] = q
    vs = VoxSplat(np.zeros((4, 3)), p, 1.0)
    unit = q.astype(np.float64) / np.linalg.norm(q.astype(np.float64), axis=-1, keepdims=True)
    np.testing.assert_allclose(vs.quats(), unit, atol=1e-12)
    ref = Rotation.from_quat(unit.reshape(-1, 4)[:, [1, 2, 3, 0]]).as_matrix().reshape(4, 5, 3, 3)
    np.testing.assert_allclose(vs.rotations(), ref, atol=1e-12)


def test_colour_is_clipped_sh_dc_term():
    rgb = np.array([-10.0, -1.0, 0.0, 1.0, 1.7724538, 10.0], np.float32)  # 1.7724538 = sqrt(pi): 0.5 + 0.5
    p = np.zeros((2, 1, NUM_RAW), np.float32)
    p[0, 0, RGB] = rgb[:3]
    p[1, 0, RGB] = rgb[3:]
    c = VoxSplat(np.zeros((2, 3)), p, 1.0).colors()
    assert c.dtype == np.float32
    expected = np.clip(0.5 + rgb / (2 * np.sqrt(np.pi)), 0, 1)
    np.testing.assert_allclose(c.reshape(-1), expected, atol=1e-6)
    assert c.min() >= 0.0 and c.max() <= 1.0


@pytest.mark.parametrize("big", [1e4, -1e4, 3e38, -3e38])
def test_extreme_raw_values_give_finite_activations_without_warnings(big):
    p = np.full((2, 2, NUM_RAW), big, np.float32)
    vs = VoxSplat(np.zeros((2, 3)), p, 0.5)
    with np.errstate(all="raise"):
        outs = [vs.means(), vs.scales(), vs.quats(), vs.rotations(), vs.opacities(), vs.colors()]
    for a in outs:
        assert np.all(np.isfinite(a))
    op = vs.opacities()
    assert np.all((op >= 0) & (op <= 1))
    assert np.allclose(op, 1.0 if big > 0 else 0.0, atol=1e-20)
    s = vs.scales()
    assert np.all(s > 0)
    # clamped to a finite physical range: no float overflow to inf, no underflow to 0
    assert s.max() <= 1e4 * (1 + 1e-12) and s.min() >= 1e-9 * (1 - 1e-12)
    np.testing.assert_allclose(np.linalg.norm(vs.quats(), axis=-1), 1.0, atol=1e-12)
    r = vs.rotations()
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)


def test_nan_raw_quaternion_activates_to_identity():
    p = np.zeros((1, 1, NUM_RAW), np.float32)
    p[0, 0, QUAT] = [np.nan, 1, 0, 0]
    vs = VoxSplat([[0, 0, 0]], p, 1.0)
    np.testing.assert_array_equal(vs.quats()[0, 0], [1, 0, 0, 0])


# --- flat Gaussians ---------------------------------------------------------------------------

def test_gaussians_are_the_valid_slots_in_voxel_major_order():
    vs = random_voxsplat(seed=4)
    g = vs.gaussians()
    vi, si = np.nonzero(vs.valid)
    assert len(g) == vs.num_gaussians == vi.size
    np.testing.assert_array_equal(g.voxel, vi)
    np.testing.assert_array_equal(g.slot, si)
    assert g.voxel.dtype == np.int64 and g.slot.dtype == np.int16
    np.testing.assert_array_equal(g.means, vs.means()[vi, si])
    np.testing.assert_array_equal(g.scales, vs.scales()[vi, si])
    np.testing.assert_array_equal(g.quats, vs.quats()[vi, si])
    np.testing.assert_array_equal(g.opacities, vs.opacities()[vi, si])
    np.testing.assert_array_equal(g.sh_dc, vs.params[vi, si, 11:14])
    assert g.sh_dc.dtype == np.float32
    np.testing.assert_array_equal(g.origin, vs.origin)
    np.testing.assert_allclose(g.colors, np.clip(0.5 + SH_C0 * g.sh_dc, 0, 1), atol=1e-7)
    np.testing.assert_allclose(g.rotations(), vs.rotations()[vi, si], atol=1e-15)


@pytest.mark.parametrize("floor", [0.0, 0.3, 0.7, 1.1])
def test_gaussians_above_an_opacity_floor_are_the_subset_of_all_valid_ones(floor):
    # One gather of the kept slots against every valid slot activated, then masked.
    vs = random_voxsplat(v=40, m=4, seed=6)
    every = vs.gaussians()
    keep = every.opacities >= floor
    want, got = every.subset(keep), vs.gaussians(min_opacity=floor)
    assert len(got) == int(keep.sum())
    for name in ("means", "scales", "quats", "opacities", "sh_dc", "voxel", "slot", "origin"):
        a, b = getattr(want, name), getattr(got, name)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
        assert b.flags.c_contiguous and b.flags.writeable, name  # the tracer's own arrays


def test_gaussians_subset_keeps_all_fields_aligned():
    g = random_voxsplat(seed=5).gaussians()
    idx = np.array([4, 0, 2])
    sub = g.subset(idx)
    assert len(sub) == 3
    for name in ("means", "scales", "quats", "opacities", "sh_dc", "voxel", "slot"):
        np.testing.assert_array_equal(getattr(sub, name), getattr(g, name)[idx])
    mask = g.opacities > 0.5
    assert len(g.subset(mask)) == int(mask.sum())
    sub.origin[0] = 99.0
    assert g.origin[0] != 99.0  # an independent copy


def test_world_means_use_the_float64_origin_far_from_zero():
    origin = np.array([1.0e6, -2.0e6, 350.25])
    p = np.zeros((2, 2, NUM_RAW), np.float32)
    p[0, 1, OFFSET] = [0.01, -0.02, 0.0]
    p[1, 0, OFFSET] = [0.5, 0.5, -0.5]
    vs = VoxSplat([[0, 0, 0], [3, -2, 1]], p, 0.1, origin=origin, valid=[[True, True], [True, False]])
    r = 0.3
    raw = p[..., 0:3].astype(np.float64)
    expected = np.array([
        origin + 0.05 + r * np.tanh(raw[0, 0]),
        origin + 0.05 + r * np.tanh(raw[0, 1]),
        origin + np.array([0.35, -0.15, 0.15]) + r * np.tanh(raw[1, 0]),
    ])
    w = vs.world_means()
    assert w.dtype == np.float64
    np.testing.assert_allclose(w, expected, rtol=0, atol=1e-9)
    # 3 mm apart at 2000 km stays 3 mm apart (float32 there resolves only 0.25 m)
    d = w[1] - w[0]
    np.testing.assert_allclose(d, r * (np.tanh(raw[0, 1]) - np.tanh(raw[0, 0])), rtol=0, atol=1e-9)
    assert np.abs(d).max() < 0.01 and np.abs(d).max() > 0.001


# --- from_gaussians ---------------------------------------------------------------------------

def match_by_opacity(a: Gaussians, b: Gaussians):
    """Index pairs matching Gaussians by their (distinct) opacities."""
    return np.argsort(a.opacities), np.argsort(b.opacities)


def test_from_gaussians_round_trips_the_activated_values():
    g = gaussians(300, seed=6)
    vs = VoxSplat.from_gaussians(g, 0.5)
    out = vs.gaussians()
    assert len(out) == 300
    ia, ib = match_by_opacity(g, out)
    np.testing.assert_allclose(out.opacities[ib], g.opacities[ia], rtol=1e-5)
    np.testing.assert_allclose(out.means[ib] + out.origin, g.means[ia] + g.origin, rtol=0, atol=2e-6)
    np.testing.assert_allclose(out.scales[ib], g.scales[ia], rtol=1e-6)
    np.testing.assert_allclose(out.quats[ib], g.quats[ia], atol=1e-6)
    np.testing.assert_array_equal(out.sh_dc[ib], g.sh_dc[ia])
    # each Gaussian sits in the voxel that contains its centre (floor of local / size)
    expected_ijk = np.floor((g.means[ia] + g.origin - vs.origin) / 0.5).astype(int)
    np.testing.assert_array_equal(vs.ijk[out.voxel[ib]], expected_ijk)
    assert np.all(np.abs(out.means - vs.voxel_centers()[out.voxel]) <= 0.25 + 1e-9)


def test_from_gaussians_voxels_are_unique_and_m_is_the_largest_count():
    g = gaussians(200, seed=7, spread=1.0)
    vs = VoxSplat.from_gaussians(g, 0.7)
    assert np.unique(vs.ijk, axis=0).shape[0] == vs.num_voxels
    world = g.means + g.origin
    cells, counts = np.unique(np.floor((world - vs.origin) / 0.7).astype(int), axis=0, return_counts=True)
    assert vs.num_voxels == cells.shape[0]
    assert vs.gaussians_per_voxel == counts.max()
    np.testing.assert_array_equal(np.sort(vs.valid.sum(1)), np.sort(counts))


def test_from_gaussians_default_origin_is_voxel_aligned_near_the_data_centre():
    g = gaussians(50, seed=8, origin=(5.0e5, 4.0e6, 12.0))
    vs = VoxSplat.from_gaussians(g, 0.2)
    k = vs.origin / 0.2
    np.testing.assert_allclose(k, np.round(k), rtol=0, atol=1e-6)
    world = g.means + g.origin
    mid = 0.5 * (world.min(0) + world.max(0))
    assert np.all(np.abs(vs.origin - mid) <= 0.1 + 1e-6)
    # local coordinates stay small even though the world ones are ~4000 km
    assert np.abs(vs.gaussians().means).max() < 3.0


def test_from_gaussians_explicit_origin_and_far_world_coordinates_are_exact():
    base = np.array([1.0e6, 1.0e6, 100.0])
    g = Gaussians(means=np.array([[0.0, 0.0, 0.0], [0.001, 0.0, 0.0], [0.0, 0.002, 0.0]]),
                  scales=np.full((3, 3), 0.05), quats=np.tile([1.0, 0, 0, 0], (3, 1)),
                  opacities=np.array([0.9, 0.8, 0.7]), sh_dc=np.zeros((3, 3), np.float32), origin=base)
    vs = VoxSplat.from_gaussians(g, 0.1, origin=base - 0.05)
    np.testing.assert_array_equal(vs.origin, base - 0.05)
    w = vs.world_means()
    order = np.argsort(-vs.gaussians().opacities)
    np.testing.assert_allclose(w[order] - base, g.means, rtol=0, atol=1e-6)


def test_from_gaussians_max_per_voxel_drops_the_faintest():
    g = Gaussians(means=np.full((5, 3), 0.05) + np.arange(5)[:, None] * 0.001,
                  scales=np.full((5, 3), 0.01), quats=np.tile([1.0, 0, 0, 0], (5, 1)),
                  opacities=np.array([0.3, 0.9, 0.1, 0.6, 0.5]), sh_dc=np.zeros((5, 3), np.float32))
    vs = VoxSplat.from_gaussians(g, 0.1, max_per_voxel=2, origin=np.zeros(3))
    assert vs.num_voxels == 1 and vs.gaussians_per_voxel == 2
    np.testing.assert_allclose(np.sort(vs.gaussians().opacities), [0.6, 0.9], rtol=1e-6)


def test_from_gaussians_empty_slots_are_invalid_transparent_identity():
    g = Gaussians(means=np.array([[0.05, 0.05, 0.05], [0.06, 0.05, 0.05], [0.35, 0.05, 0.05]]),
                  scales=np.full((3, 3), 0.01), quats=np.tile([0.0, 0, 0, 1.0], (3, 1)),
                  opacities=np.array([0.5, 0.6, 0.7]), sh_dc=np.zeros((3, 3), np.float32))
    vs = VoxSplat.from_gaussians(g, 0.1, origin=np.zeros(3))
    assert vs.gaussians_per_voxel == 2 and vs.num_voxels == 2 and vs.num_gaussians == 3
    v, s = np.argwhere(~vs.valid)[0]
    assert vs.opacities()[v, s] < 1e-12
    np.testing.assert_array_equal(vs.quats()[v, s], [1, 0, 0, 0])


def test_from_gaussians_voxel_label_is_the_most_frequent():
    g = Gaussians(means=np.array([[0.01, 0.01, 0.01], [0.02, 0.01, 0.01], [0.03, 0.01, 0.01], [1.5, 0.0, 0.0]]),
                  scales=np.full((4, 3), 0.01), quats=np.tile([1.0, 0, 0, 0], (4, 1)),
                  opacities=np.array([0.5, 0.6, 0.7, 0.8]), sh_dc=np.zeros((4, 3), np.float32))
    vs = VoxSplat.from_gaussians(g, 1.0, labels=np.array([7, 3, 7, 11]), origin=np.zeros(3))
    lab = {tuple(ijk): int(lb) for ijk, lb in zip(vs.ijk.tolist(), vs.labels)}
    assert lab == {(0, 0, 0): 7, (1, 0, 0): 11}
    assert vs.labels.dtype == np.int16


def test_from_gaussians_rejects_nan_and_bad_voxel_size():
    g = gaussians(4)
    g.means[2, 1] = np.nan
    with pytest.raises(ValueError, match="means"):
        VoxSplat.from_gaussians(g, 0.5)
    for size in (0.0, -1.0):
        with pytest.raises(ValueError, match="voxel_size"):
            VoxSplat.from_gaussians(gaussians(4), size)


def test_from_gaussians_of_nothing_is_an_empty_scaffold():
    g = Gaussians(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0), np.zeros((0, 3), np.float32))
    vs = VoxSplat.from_gaussians(g, 0.5)
    assert vs.num_voxels == 0 and vs.num_gaussians == 0 and len(vs.gaussians()) == 0


# --- voxel keys -------------------------------------------------------------------------------

ijk_rows = st.lists(st.tuples(*[st.integers(-(1 << 20) + 1, (1 << 20) - 1)] * 3), min_size=1, max_size=40)


@PROPS
@given(ijk_rows)
def test_voxel_keys_sort_like_ijk_and_are_injective(rows):
    ijk = np.array(rows, np.int64)
    keys = voxel_keys(ijk)
    assert keys.dtype == np.int64 and keys.shape == (len(rows),)
    # equal keys <=> equal rows
    _, inv_rows = np.unique(ijk, axis=0, return_inverse=True)
    _, inv_keys = np.unique(keys, return_inverse=True)
    np.testing.assert_array_equal(inv_rows.reshape(-1), inv_keys.reshape(-1))
    # order of keys == lexicographic (i, j, k) order
    lex = np.lexsort((ijk[:, 2], ijk[:, 1], ijk[:, 0]))
    assert np.all(np.diff(keys[lex]) >= 0)


@PROPS
@given(st.lists(st.tuples(*[st.integers(-6, 6)] * 3), min_size=1, max_size=60))
def test_unique_voxels_agrees_with_numpy_unique_axis0(rows):
    ijk = np.array(rows, np.int64)
    uniq, inv, counts = unique_voxels(ijk)
    ref, ref_inv, ref_counts = np.unique(ijk, axis=0, return_inverse=True, return_counts=True)
    np.testing.assert_array_equal(uniq, ref)
    np.testing.assert_array_equal(inv, ref_inv.reshape(-1))
    np.testing.assert_array_equal(counts, ref_counts)
    np.testing.assert_array_equal(uniq[inv], ijk)
    assert inv.ndim == 1


def test_voxel_keys_extreme_indices_and_limit():
    edge = (1 << 20) - 1
    ijk = np.array([[edge, -edge, 0], [-edge, edge, edge], [0, 0, -edge]])
    uniq, inv, _ = unique_voxels(ijk)
    np.testing.assert_array_equal(uniq[inv], ijk)
    for bad in ([1 << 20, 0, 0], [0, -(1 << 20), 0], [0, 0, 1 << 30]):
        with pytest.raises(ValueError, match="2\\^20"):
            voxel_keys(np.array([bad]))


def test_unique_voxels_of_no_points():
    uniq, inv, counts = unique_voxels(np.zeros((0, 3)))
    assert uniq.shape == (0, 3) and inv.shape == (0,) and counts.shape == (0,)


# --- file format ------------------------------------------------------------------------------

REQUIRED_KEYS = {"format", "version", "ijk", "params", "valid", "labels", "voxel_size", "origin",
                 "offset_range", "metadata"}


def assert_same_voxsplat(a: VoxSplat, b: VoxSplat):
    for name in ("ijk", "params", "valid", "labels", "origin"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)
        assert x.tobytes() == y.tobytes(), name  # bit-exact, including -0.0 and NaN payloads
    assert a.voxel_size == b.voxel_size and a.offset_range == b.offset_range
    assert a.metadata == b.metadata
    if a.logits is None:
        assert b.logits is None
    else:
        assert a.logits.tobytes() == b.logits.tobytes() and a.logits.shape == b.logits.shape


@pytest.mark.parametrize("logits", [False, True])
def test_save_load_round_trip_is_bit_exact(tmp_path, logits):
    vs = random_voxsplat(seed=9, logits=logits, origin=(1.0e6 + 0.123456789, -2.5e6, 0.1), offset_range=2.5,
                         voxel_size=0.15)
    vs.params[0, 0, 0] = -0.0
    vs.params[1, 0, 3] = np.float32(1e-45)  # a subnormal
    vs.metadata = {"source": "unit-test", "n": 3, "nested": {"a": [1, 2.5]}}
    path = vs.save(tmp_path / "scene.npz")
    assert path == tmp_path / "scene.npz" and path.is_file()
    back = VoxSplat.load(path)
    assert_same_voxsplat(vs, back)
    # the world coordinates far from zero come back exactly
    np.testing.assert_array_equal(back.world_means(), vs.world_means())


def test_saved_file_is_a_plain_npz_with_the_documented_keys(tmp_path):
    vs = random_voxsplat(v=7, m=2, seed=10, origin=(3.0e5, 1.0, -2.0), logits=True)
    vs.metadata = {"k": "v"}
    path = vs.save(tmp_path / "a.npz")
    assert zipfile.is_zipfile(path)
    with np.load(path, allow_pickle=False) as z:  # no pickled objects inside
        assert REQUIRED_KEYS <= set(z.files)
        assert str(z["format"]) == FORMAT_NAME == "scube_sim.voxsplat"
        ver = z["version"]
        assert ver.shape == () and np.issubdtype(ver.dtype, np.integer)
        assert 1 <= int(ver) <= FORMAT_VERSION
        assert z["ijk"].dtype == np.int32 and z["ijk"].shape == (7, 3)
        assert z["params"].dtype == np.float32 and z["params"].shape == (7, 2, NUM_RAW)
        assert z["valid"].dtype == bool and z["valid"].shape == (7, 2)
        assert z["labels"].dtype == np.int16 and z["labels"].shape == (7,)
        assert z["origin"].dtype == np.float64 and z["origin"].shape == (3,)
        assert z["voxel_size"].shape == () and float(z["voxel_size"]) == vs.voxel_size
        assert z["offset_range"].shape == () and float(z["offset_range"]) == 3.0
        assert json.loads(str(z["metadata"])) == {"k": "v"}
        assert z["logits"].dtype == np.float32 and z["logits"].shape == (7, 5)
        np.testing.assert_array_equal(z["params"], vs.params)
        np.testing.assert_array_equal(z["origin"], vs.origin)
        np.testing.assert_array_equal(z["ijk"], vs.ijk)


def test_saved_file_without_logits_has_no_logits_key(tmp_path):
    path = random_voxsplat(seed=11).save(tmp_path / "b.npz")
    with np.load(path) as z:
        assert "logits" not in z.files
    assert VoxSplat.load(path).logits is None


def test_save_is_atomic_creates_folders_and_overwrites(tmp_path):
    target = tmp_path / "deep" / "er" / "s.npz"
    random_voxsplat(seed=12).save(target)
    second = random_voxsplat(seed=13, v=3)
    second.save(target)
    assert VoxSplat.load(target).num_voxels == 3
    assert sorted(p.name for p in target.parent.iterdir()) == ["s.npz"]  # no temporary left behind


def test_empty_voxsplat_round_trips(tmp_path):
    vs = VoxSplat(np.zeros((0, 3)), np.zeros((0, 4, NUM_RAW)), 0.3)
    back = VoxSplat.load(vs.save(tmp_path / "e.npz"))
    assert back.num_voxels == 0 and back.gaussians_per_voxel == 4
    assert_same_voxsplat(vs, back)


def _rewrite(src, dst, drop=(), **override):
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files if k not in drop}
    arrays.update(override)
    np.savez(dst, **arrays)
    return dst


def test_load_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.npz"):
        VoxSplat.load(tmp_path / "nope.npz")


def test_load_not_an_npz_names_the_file(tmp_path):
    bad = tmp_path / "junk.npz"
    bad.write_bytes(b"this is not a zip file")
    with pytest.raises(ValueError, match="junk.npz"):
        VoxSplat.load(bad)


def test_load_wrong_format_name(tmp_path):
    src = random_voxsplat(seed=14).save(tmp_path / "a.npz")
    dst = _rewrite(src, tmp_path / "b.npz", format=np.array("something.else"))
    with pytest.raises(ValueError, match="format"):
        VoxSplat.load(dst)


@pytest.mark.parametrize("key", ["format", "version", "ijk", "params", "origin", "metadata"])
def test_load_missing_key_names_file_and_key(tmp_path, key):
    src = random_voxsplat(seed=15).save(tmp_path / "a.npz")
    dst = _rewrite(src, tmp_path / "b.npz", drop=(key,))
    with pytest.raises(ValueError) as err:
        VoxSplat.load(dst)
    assert "b.npz" in str(err.value) and repr(key) in str(err.value)


def test_load_rejects_a_newer_version(tmp_path):
    src = random_voxsplat(seed=16).save(tmp_path / "a.npz")
    dst = _rewrite(src, tmp_path / "b.npz", version=np.array(FORMAT_VERSION + 1, np.int32))
    with pytest.raises(ValueError, match="newer"):
        VoxSplat.load(dst)


def test_load_rejects_nan_params_naming_the_file(tmp_path):
    vs = random_voxsplat(seed=17)
    vs.params[3, 1, 5] = np.nan
    path = vs.save(tmp_path / "nan.npz")
    with pytest.raises(ValueError) as err:
        VoxSplat.load(path)
    assert "nan.npz" in str(err.value) and "scale" in str(err.value)


def test_load_rejects_inconsistent_shapes_naming_the_file(tmp_path):
    src = random_voxsplat(seed=18, v=5).save(tmp_path / "a.npz")
    dst = _rewrite(src, tmp_path / "b.npz", ijk=np.zeros((4, 3), np.int32))
    with pytest.raises(ValueError) as err:
        VoxSplat.load(dst)
    assert "b.npz" in str(err.value) and "ijk" in str(err.value)
