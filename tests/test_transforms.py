"""scube_sim.transforms against independent oracles: scipy's Rotation/Slerp, closed forms, identities.

Conventions under test (module docstring): quaternions are scalar-first wxyz (scipy is xyzw),
poses are float64 (4, 4) `T_parent_child`, Euler angles are roll/pitch/yaw with
R = Rz(yaw) Ry(pitch) Rx(roll), which is scipy's intrinsic 'ZYX' with angles (yaw, pitch, roll).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from scube_sim.transforms import (
    check_pose,
    euler_to_rotmat,
    interpolate_poses,
    invert_pose,
    make_pose,
    normalize_quat,
    pose_from_xyz_rpy,
    quat_multiply,
    quat_to_rotmat,
    rotate_vectors,
    rotmat_to_euler,
    rotmat_to_quat,
    slerp,
    transform_points,
)

PROPS = settings(max_examples=50, deadline=None)


def wxyz(xyzw):
    return np.roll(np.asarray(xyzw, np.float64), 1, axis=-1)


def xyzw(q):
    return np.roll(np.asarray(q, np.float64), -1, axis=-1)


def same_rotation(qa, qb, atol=1e-12):
    """Unit quaternions equal up to the double cover (q and -q are the same rotation)."""
    qa, qb = np.asarray(qa), np.asarray(qb)
    return np.allclose(qa, qb, atol=atol) or np.allclose(qa, -qb, atol=atol)


def angle_between(ra, rb):
    """Geodesic angle (radians) between two rotation matrices."""
    return float(np.linalg.norm(Rotation.from_matrix(ra.T @ rb).as_rotvec()))


def random_rotations(n, seed):
    return Rotation.random(n, random_state=np.random.default_rng(seed))


def rigid(rot: Rotation, t) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rot.as_matrix()
    out[:3, 3] = t
    return out


# hypothesis: non-degenerate quaternions of any norm, angles anywhere
_comp = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)
quats_any_norm = st.tuples(_comp, _comp, _comp, _comp).map(np.array).filter(
    lambda q: np.linalg.norm(q) > 1e-3)
angle = st.floats(-np.pi, np.pi, allow_nan=False)
pitch_ok = st.floats(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3, allow_nan=False)


# --- normalize_quat ---------------------------------------------------------------------------

def test_normalize_quat_gives_unit_float64_with_same_direction():
    q = np.array([[2.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0], [0.0, 0.0, -3.0, 4.0]], np.float32)
    out = normalize_quat(q)
    assert out.dtype == np.float64 and out.shape == (3, 4)
    np.testing.assert_allclose(out, [[1, 0, 0, 0], [0.5, 0.5, 0.5, 0.5], [0, 0, -0.6, 0.8]], atol=1e-15)


@pytest.mark.parametrize("bad", [
    [0.0, 0.0, 0.0, 0.0],
    [1e-14, 0.0, 0.0, 0.0],
    [0.0, -1e-13, 0.0, 0.0],
    [np.nan, 0.0, 0.0, 0.0],
    [1.0, np.nan, 0.0, 0.0],
    [np.inf, 0.0, 0.0, 0.0],
    [0.0, 0.0, -np.inf, 1.0],
])
def test_normalize_quat_zero_or_nonfinite_becomes_identity(bad):
    np.testing.assert_array_equal(normalize_quat(np.array(bad)), [1.0, 0.0, 0.0, 0.0])


def test_normalize_quat_bad_rows_in_a_batch_only_affect_themselves():
    q = np.array([[0.0, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0], [np.nan] * 4, [0.0, 0.0, 0.0, -5.0]])
    np.testing.assert_array_equal(normalize_quat(q), [[1, 0, 0, 0], [0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, -1]])
    # higher-rank batches keep their shape
    q3 = np.zeros((2, 3, 4))
    q3[1, 2] = [0, 0, 3, 4]
    out = normalize_quat(q3)
    assert out.shape == (2, 3, 4)
    np.testing.assert_array_equal(out[0, 0], [1, 0, 0, 0])
    np.testing.assert_allclose(out[1, 2], [0, 0, 0.6, 0.8], atol=1e-15)


def test_normalize_quat_small_but_nonzero_norm_is_normalised_not_reset():
    out = normalize_quat(np.array([0.0, 3e-10, 4e-10, 0.0]))
    np.testing.assert_allclose(out, [0.0, 0.6, 0.8, 0.0], atol=1e-12)


def test_zero_quaternion_maps_to_identity_rotation():
    np.testing.assert_array_equal(quat_to_rotmat(np.zeros(4)), np.eye(3))


# --- quaternion <-> matrix against scipy --------------------------------------------------------

def test_quat_to_rotmat_matches_scipy_batch():
    rots = random_rotations(200, 0)
    q = wxyz(rots.as_quat())
    scale = np.random.default_rng(1).uniform(0.1, 10.0, (200, 1))  # any norm
    out = quat_to_rotmat(q * scale)
    assert out.shape == (200, 3, 3) and out.dtype == np.float64
    np.testing.assert_allclose(out, rots.as_matrix(), atol=1e-13)


def test_quat_to_rotmat_single_and_nd_shapes():
    rots = random_rotations(6, 2)
    q = wxyz(rots.as_quat())
    np.testing.assert_allclose(quat_to_rotmat(q[0]), rots[0].as_matrix(), atol=1e-13)
    assert quat_to_rotmat(q[0]).shape == (3, 3)
    out = quat_to_rotmat(q.reshape(2, 3, 4))
    assert out.shape == (2, 3, 3, 3)
    np.testing.assert_allclose(out.reshape(6, 3, 3), rots.as_matrix(), atol=1e-13)


@pytest.mark.parametrize("q, axis, deg", [
    ([0.0, 1.0, 0.0, 0.0], [1, 0, 0], 180.0),
    ([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)], [0, 0, 1], 90.0),
    ([np.cos(np.pi / 8), 0.0, np.sin(np.pi / 8), 0.0], [0, 1, 0], 45.0),
])
def test_quat_to_rotmat_closed_form_axis_angle(q, axis, deg):
    expected = Rotation.from_rotvec(np.deg2rad(deg) * np.asarray(axis, float)).as_matrix()
    np.testing.assert_allclose(quat_to_rotmat(np.array(q)), expected, atol=1e-15)


def test_quat_90deg_about_z_maps_x_forward_to_y_left():
    r = quat_to_rotmat(np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]))
    np.testing.assert_allclose(r @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)


def test_rotmat_to_quat_matches_scipy_with_nonnegative_w():
    rots = random_rotations(300, 3)
    q = rotmat_to_quat(rots.as_matrix())
    assert q.shape == (300, 4) and q.dtype == np.float64
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-14)
    ref = wxyz(rots.as_quat())
    ref *= np.where(ref[:, :1] < 0, -1.0, 1.0)
    np.testing.assert_allclose(q, ref, atol=1e-12)


def test_rotmat_to_quat_single_matrix_shape():
    r = Rotation.from_euler("xyz", [10, 20, 30], degrees=True)
    q = rotmat_to_quat(r.as_matrix())
    assert q.shape == (4,)
    assert same_rotation(q, wxyz(r.as_quat()))


@pytest.mark.parametrize("axis", [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 1], [0.3, -0.2, 0.9]])
@pytest.mark.parametrize("deg", [180.0, 179.999999, 179.9, -179.9])
def test_rotmat_to_quat_accurate_near_180_degrees(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    rot = Rotation.from_rotvec(np.deg2rad(deg) * axis)
    q = rotmat_to_quat(rot.as_matrix())
    assert q[0] >= 0
    assert same_rotation(q, wxyz(rot.as_quat()), atol=1e-12)
    np.testing.assert_allclose(quat_to_rotmat(q), rot.as_matrix(), atol=1e-14)


@pytest.mark.parametrize("deg", [0.0, 1e-9, 1e-6, 1e-3])
def test_rotmat_to_quat_near_identity(deg):
    rot = Rotation.from_rotvec(np.deg2rad(deg) * np.array([0.6, 0.0, 0.8]))
    q = rotmat_to_quat(rot.as_matrix())
    assert same_rotation(q, wxyz(rot.as_quat()), atol=1e-14)


@PROPS
@given(quats_any_norm)
def test_quat_matrix_round_trip_property(q):
    unit = q / np.linalg.norm(q)
    back = rotmat_to_quat(quat_to_rotmat(q))
    assert same_rotation(back, unit, atol=1e-10)
    assert back[0] >= 0
    r = quat_to_rotmat(q)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(r, Rotation.from_quat(xyzw(q)).as_matrix(), atol=1e-12)


# --- quat_multiply ----------------------------------------------------------------------------

def test_quat_multiply_basis_closed_forms():
    one, i, j, k = np.eye(4)
    np.testing.assert_array_equal(quat_multiply(i, j), k)
    np.testing.assert_array_equal(quat_multiply(j, k), i)
    np.testing.assert_array_equal(quat_multiply(k, i), j)
    np.testing.assert_array_equal(quat_multiply(j, i), -k)
    for e in (i, j, k):
        np.testing.assert_array_equal(quat_multiply(e, e), -one)
        np.testing.assert_array_equal(quat_multiply(one, e), e)


def test_quat_multiply_is_rotation_composition_like_scipy():
    a, b = random_rotations(100, 4), random_rotations(100, 5)
    prod = quat_multiply(wxyz(a.as_quat()), wxyz(b.as_quat()))
    assert prod.shape == (100, 4)
    np.testing.assert_allclose(quat_to_rotmat(prod), (a * b).as_matrix(), atol=1e-13)
    np.testing.assert_allclose(quat_to_rotmat(prod), a.as_matrix() @ b.as_matrix(), atol=1e-13)
    # a unit quaternion times its conjugate is the identity
    qa = wxyz(a.as_quat())
    conj = qa * np.array([1, -1, -1, -1])
    np.testing.assert_allclose(quat_multiply(qa, conj), np.tile([1.0, 0, 0, 0], (100, 1)), atol=1e-15)


# --- slerp ------------------------------------------------------------------------------------

def scipy_slerp(q0, q1, s):
    return Slerp([0.0, 1.0], Rotation.from_quat([xyzw(q0), xyzw(q1)]))(s)


def test_slerp_endpoints_and_midpoint_against_scipy():
    rots = random_rotations(2, 6)
    q0, q1 = wxyz(rots.as_quat())
    s = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
    out = slerp(q0, q1, s)
    assert out.shape == (5, 4)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-14)
    assert same_rotation(out[0], q0 / np.linalg.norm(q0))
    assert same_rotation(out[-1], q1, atol=1e-12)
    np.testing.assert_allclose(quat_to_rotmat(out), scipy_slerp(q0, q1, s).as_matrix(), atol=1e-12)


def test_slerp_closed_form_quarter_turn_about_z():
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    q1 = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])  # 90 deg about z
    s = np.linspace(0, 1, 7)
    out = slerp(q0, q1, s)
    expected = np.stack([np.cos(s * np.pi / 4), 0 * s, 0 * s, np.sin(s * np.pi / 4)], 1)
    np.testing.assert_allclose(out, expected, atol=1e-15)


def test_slerp_takes_the_short_arc():
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    q1 = -np.array([np.cos(np.radians(80)), np.sin(np.radians(80)), 0.0, 0.0])  # 160 deg about x, as -q
    mid = slerp(q0, q1, np.array([0.5]))[0]
    # the short way is 80 deg about +x, not 100 deg the other way round
    assert angle_between(np.eye(3), quat_to_rotmat(mid)) == pytest.approx(np.radians(80), abs=1e-12)
    np.testing.assert_allclose(quat_to_rotmat(mid), Rotation.from_euler("x", 80, degrees=True).as_matrix(),
                               atol=1e-12)


def test_slerp_of_nearly_equal_quaternions_is_close_to_scipy_and_unit():
    q0 = wxyz(Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_quat())
    q1 = wxyz(Rotation.from_euler("xyz", [10.5, 20, 30.5], degrees=True).as_quat())
    assert abs(np.dot(q0, q1)) > 0.9995  # the normalised-lerp branch
    s = np.linspace(0, 1, 11)
    out = slerp(q0, q1, s)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-14)
    ref = scipy_slerp(q0, q1, s).as_matrix()
    for r, e in zip(quat_to_rotmat(out), ref):
        assert angle_between(r, e) < 1e-6
    # identical inputs: constant output, no NaN from sin(0)
    same = slerp(q0, q0, s)
    assert np.all(np.isfinite(same))
    np.testing.assert_allclose(same, np.tile(q0, (11, 1)), atol=1e-15)


def test_slerp_of_opposite_signs_of_one_rotation_is_constant():
    q = wxyz(Rotation.from_euler("z", 40, degrees=True).as_quat())
    out = slerp(q, -q, np.linspace(0, 1, 5))
    assert np.all(np.isfinite(out))
    for r in quat_to_rotmat(out):
        np.testing.assert_allclose(r, quat_to_rotmat(q), atol=1e-14)


@PROPS
@given(quats_any_norm, quats_any_norm, st.floats(0.0, 1.0))
def test_slerp_matches_scipy_property(qa, qb, s):
    qa, qb = qa / np.linalg.norm(qa), qb / np.linalg.norm(qb)
    out = slerp(qa, qb, np.array([s]))
    assert out.shape == (1, 4)
    assert angle_between(quat_to_rotmat(out[0]), scipy_slerp(qa, qb, [s]).as_matrix()[0]) < 1e-6


# --- Euler angles -----------------------------------------------------------------------------

def elementary(axis, a):
    c, s = np.cos(a), np.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@pytest.mark.parametrize("rpy", [(0.1, 0.2, 0.3), (-2.0, 1.2, 3.0), (np.pi, 0.0, 0.0), (0.0, -np.pi / 2, 1.0)])
def test_euler_to_rotmat_is_rz_ry_rx(rpy):
    roll, pitch, yaw = rpy
    expected = elementary("z", yaw) @ elementary("y", pitch) @ elementary("x", roll)
    np.testing.assert_allclose(euler_to_rotmat(roll, pitch, yaw), expected, atol=1e-15)


@PROPS
@given(angle, st.floats(-np.pi / 2, np.pi / 2), angle)
def test_euler_to_rotmat_matches_scipy_intrinsic_zyx(roll, pitch, yaw):
    ref = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    np.testing.assert_allclose(euler_to_rotmat(roll, pitch, yaw), ref, atol=1e-13)
    # intrinsic z-y'-x'' equals extrinsic x, then y, then z
    ref2 = Rotation.from_euler("xyz", [roll, pitch, yaw]).as_matrix()
    np.testing.assert_allclose(euler_to_rotmat(roll, pitch, yaw), ref2, atol=1e-13)


@PROPS
@given(angle, pitch_ok, angle)
def test_rotmat_to_euler_round_trip_away_from_gimbal_lock(roll, pitch, yaw):
    r = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    out = rotmat_to_euler(r)
    assert all(isinstance(a, float) for a in out)
    np.testing.assert_allclose(euler_to_rotmat(*out), r, atol=1e-12)
    r2, p2, y2 = out
    assert p2 == pytest.approx(pitch, abs=1e-9)
    # angles equal modulo 2 pi (roll/yaw at +-pi may come back with the other sign)
    assert abs(np.angle(np.exp(1j * (r2 - roll)))) < 1e-8
    assert abs(np.angle(np.exp(1j * (y2 - yaw)))) < 1e-8
    assert -np.pi <= r2 <= np.pi and -np.pi <= y2 <= np.pi and -np.pi / 2 <= p2 <= np.pi / 2


def test_rotmat_to_euler_matches_scipy_as_euler():
    rots = random_rotations(50, 7)
    for rot in rots:
        yaw, pitch, roll = rot.as_euler("ZYX")
        np.testing.assert_allclose(rotmat_to_euler(rot.as_matrix()), (roll, pitch, yaw), atol=1e-10)


@pytest.mark.parametrize("rpy_deg", [
    (179.999, 0.0, -179.999), (-179.9999, 45.0, 179.9999), (180.0, 0.0, 180.0), (0.0, 0.0, -180.0),
    (90.0, 89.9, -90.0), (10.0, -89.99, 20.0),
])
def test_rotmat_to_euler_extreme_angles_reproduce_the_matrix(rpy_deg):
    rpy = np.deg2rad(rpy_deg)
    r = euler_to_rotmat(*rpy)
    back = rotmat_to_euler(r)
    np.testing.assert_allclose(euler_to_rotmat(*back), r, atol=1e-9)
    np.testing.assert_allclose(euler_to_rotmat(*back), Rotation.from_euler("ZYX", rpy[::-1]).as_matrix(),
                               atol=1e-9)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_gimbal_lock_pitch_is_recovered_and_matrix_is_finite(sign):
    # At pitch = +-90 deg only roll -/+ yaw is observable; pitch itself must come back exactly.
    r = euler_to_rotmat(0.3, sign * np.pi / 2, 0.7)
    roll, pitch, yaw = rotmat_to_euler(r)
    assert pitch == pytest.approx(sign * np.pi / 2, abs=1e-7)
    assert np.all(np.isfinite([roll, pitch, yaw]))
    # a matrix slightly outside [-1, 1] from round-off must not produce NaN
    r2 = r.copy()
    r2[2, 0] = -sign * (1.0 + 1e-15)
    assert np.isfinite(rotmat_to_euler(r2)[1])


def test_pose_from_xyz_rpy_uses_degrees_and_matches_scipy():
    t = pose_from_xyz_rpy([1.0, -2.0, 3.5], [10.0, -20.0, 30.0])
    assert t.shape == (4, 4) and t.dtype == np.float64
    np.testing.assert_allclose(t[:3, :3], Rotation.from_euler("ZYX", [30, -20, 10], degrees=True).as_matrix(),
                               atol=1e-15)
    np.testing.assert_array_equal(t[:3, 3], [1.0, -2.0, 3.5])
    np.testing.assert_array_equal(t[3], [0, 0, 0, 1])
    # yaw 90 deg: the child's x (forward) points along the parent's y (left)
    t90 = pose_from_xyz_rpy([0, 0, 0], [0, 0, 90])
    np.testing.assert_allclose(rotate_vectors(t90, np.array([[1.0, 0, 0]])), [[0, 1, 0]], atol=1e-15)


# --- poses ------------------------------------------------------------------------------------

def test_make_pose_defaults_and_values():
    np.testing.assert_array_equal(make_pose(), np.eye(4))
    r = Rotation.from_euler("y", 30, degrees=True).as_matrix()
    t = make_pose(r, [1, 2, 3])
    assert t.dtype == np.float64
    np.testing.assert_array_equal(t[:3, :3], r)
    np.testing.assert_array_equal(t[:3, 3], [1, 2, 3])
    np.testing.assert_array_equal(t[3], [0, 0, 0, 1])
    np.testing.assert_array_equal(make_pose(translation=[4, 5, 6])[:3, :3], np.eye(3))


def test_invert_pose_times_pose_is_identity_single_and_batch():
    rots = random_rotations(20, 8)
    rng = np.random.default_rng(9)
    ts = np.stack([rigid(r, rng.normal(0, 100, 3)) for r in rots])
    inv = invert_pose(ts)
    assert inv.shape == (20, 4, 4)
    np.testing.assert_allclose(inv @ ts, np.tile(np.eye(4), (20, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(ts @ inv, np.tile(np.eye(4), (20, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(inv, np.linalg.inv(ts), atol=1e-12)
    np.testing.assert_allclose(invert_pose(ts[3]), np.linalg.inv(ts[3]), atol=1e-12)
    np.testing.assert_array_equal(inv[:, 3], np.tile([0, 0, 0, 1.0], (20, 1)))


def test_invert_pose_exact_far_from_the_origin():
    r = Rotation.from_euler("ZYX", [33, 4, -2], degrees=True)
    t = rigid(r, [1.0e6, -2.5e6, 1234.5])
    inv = invert_pose(t)
    p = np.array([[1.0e6 + 0.001, -2.5e6 - 0.002, 1234.0]])
    back = transform_points(t, transform_points(inv, p))
    # float64 at 2.5e6 m resolves ~5e-10 m; a float32 path would lose ~0.25 m
    np.testing.assert_allclose(back, p, rtol=0, atol=2e-9)
    np.testing.assert_allclose((inv @ t)[:3, 3], 0.0, atol=1e-9)


def test_transform_points_matches_homogeneous_matmul():
    rng = np.random.default_rng(10)
    t = rigid(random_rotations(1, 11)[0], rng.normal(0, 5, 3))
    p = rng.normal(0, 10, (50, 3))
    homo = np.c_[p, np.ones(50)]
    expected = (t @ homo.T).T[:, :3]
    out = transform_points(t, p)
    assert out.shape == (50, 3) and out.dtype == np.float64
    np.testing.assert_allclose(out, expected, atol=1e-12)
    # p_parent = R p_child + t, explicitly
    np.testing.assert_allclose(out[7], t[:3, :3] @ p[7] + t[:3, 3], atol=1e-12)


def test_transform_points_per_point_poses():
    rng = np.random.default_rng(12)
    rots = random_rotations(30, 13)
    ts = np.stack([rigid(r, rng.normal(0, 5, 3)) for r in rots])
    p = rng.normal(0, 3, (30, 3))
    out = transform_points(ts, p)
    expected = np.stack([ts[i, :3, :3] @ p[i] + ts[i, :3, 3] for i in range(30)])
    np.testing.assert_allclose(out, expected, atol=1e-12)


def test_rotate_vectors_ignores_translation():
    rng = np.random.default_rng(14)
    rot = random_rotations(1, 15)[0]
    t = rigid(rot, [1e6, 2e6, 3e6])
    v = rng.normal(size=(40, 3))
    np.testing.assert_allclose(rotate_vectors(t, v), rot.apply(v), atol=1e-13)
    ts = np.stack([t] * 40)
    np.testing.assert_allclose(rotate_vectors(ts, v), rot.apply(v), atol=1e-13)


def test_transform_points_float32_input_is_computed_in_float64():
    t = make_pose(translation=[1.0e6, 0.0, 0.0])
    p = np.array([[0.25, 0.5, 0.125]], np.float32)  # exactly representable
    out = transform_points(t, p)
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, [[1.0e6 + 0.25, 0.5, 0.125]])


# --- interpolate_poses --------------------------------------------------------------------------

def test_interpolate_poses_endpoints_midpoint_against_scipy():
    r0, r1 = Rotation.from_euler("ZYX", [10, 5, -3], degrees=True), Rotation.from_euler("ZYX", [100, -20, 30], degrees=True)
    t0, t1 = rigid(r0, [0.0, 0.0, 0.0]), rigid(r1, [10.0, -4.0, 2.0])
    s = np.array([0.0, 0.5, 1.0])
    out = interpolate_poses(t0, t1, s)
    assert out.shape == (3, 4, 4) and out.dtype == np.float64
    np.testing.assert_allclose(out[0], t0, atol=1e-12)
    np.testing.assert_allclose(out[2], t1, atol=1e-12)
    mid = Slerp([0, 1], Rotation.concatenate([r0, r1]))([0.5]).as_matrix()[0]
    np.testing.assert_allclose(out[1, :3, :3], mid, atol=1e-12)
    np.testing.assert_allclose(out[1, :3, 3], [5.0, -2.0, 1.0], atol=1e-15)
    for p in out:
        check_pose(p)


def test_interpolate_poses_scalar_fraction_and_translation_extrapolation():
    t0 = make_pose(translation=[1.0, 2.0, 3.0])
    t1 = make_pose(Rotation.from_euler("z", 60, degrees=True).as_matrix(), [3.0, 2.0, -1.0])
    one = interpolate_poses(t0, t1, 0.25)
    assert one.shape == (1, 4, 4)
    np.testing.assert_allclose(one[0, :3, :3], Rotation.from_euler("z", 15, degrees=True).as_matrix(), atol=1e-12)
    ext = interpolate_poses(t0, t1, np.array([-1.0, 2.0]))
    np.testing.assert_allclose(ext[:, :3, 3], [[-1.0, 2.0, 7.0], [5.0, 2.0, -5.0]], atol=1e-12)
    for p in ext:
        check_pose(p)  # still rigid


def test_interpolate_poses_large_translations_stay_exact():
    t0 = make_pose(translation=[1.0e6, -3.0e6, 50.0])
    t1 = make_pose(translation=[1.0e6 + 1.0, -3.0e6 - 2.0, 52.0])
    out = interpolate_poses(t0, t1, np.array([0.5, 0.125]))
    np.testing.assert_array_equal(out[0, :3, 3], [1.0e6 + 0.5, -3.0e6 - 1.0, 51.0])
    np.testing.assert_allclose(out[1, :3, 3], [1.0e6 + 0.125, -3.0e6 - 0.25, 50.25], rtol=0, atol=1e-9)


def test_interpolate_poses_across_plus_minus_180_yaw_takes_the_short_way():
    t0 = pose_from_xyz_rpy([0, 0, 0], [0, 0, 179.0])
    t1 = pose_from_xyz_rpy([0, 0, 0], [0, 0, -179.0])
    mid = interpolate_poses(t0, t1, np.array([0.5]))[0]
    np.testing.assert_allclose(mid[:3, :3], Rotation.from_euler("z", 180, degrees=True).as_matrix(), atol=1e-12)


def _interpolate_poses_per_quaternion(t0, t1, s):
    """The straightforward formula: one SLERP quaternion per fraction, then its matrix."""
    q = slerp(rotmat_to_quat(t0[:3, :3]), rotmat_to_quat(t1[:3, :3]), s)
    out = np.zeros((len(s), 4, 4))
    out[:, :3, :3] = quat_to_rotmat(q)
    out[:, :3, 3] = t0[:3, 3] + s[:, None] * (t1[:3, 3] - t0[:3, 3])
    out[:, 3, 3] = 1.0
    return out


@pytest.mark.parametrize("turn_deg", [0.0, 1e-7, 0.05, 3.0, 3.7, 30.0, 120.0, 179.9, 180.0])
def test_interpolate_poses_equals_one_slerp_quaternion_per_pose(turn_deg):
    # The closed form (a quadratic form in slerp's blend weights) against slerp + quat_to_rotmat,
    # on both of slerp's branches (normalised lerp below about 3.6 degrees), extrapolation
    # included: the same poses to a few float64 ulps.
    rng = np.random.default_rng(int(turn_deg * 1000) + 1)
    for _ in range(5):
        r0 = Rotation.from_rotvec(rng.normal(size=3))
        axis = rng.normal(size=3)
        r1 = Rotation.from_rotvec(np.radians(turn_deg) * axis / np.linalg.norm(axis)) * r0
        t0, t1 = rigid(r0, rng.normal(scale=50.0, size=3)), rigid(r1, rng.normal(scale=50.0, size=3))
        s = np.r_[rng.uniform(-0.5, 1.5, 200), 0.0, 1.0]
        got, want = interpolate_poses(t0, t1, s), _interpolate_poses_per_quaternion(t0, t1, s)
        np.testing.assert_allclose(got[:, :3, :3], want[:, :3, :3], rtol=0, atol=4e-15)
        np.testing.assert_array_equal(got[:, 3:], want[:, 3:])
        np.testing.assert_array_equal(got[:, :3, 3], want[:, :3, 3])
        rr = got[:, :3, :3]
        np.testing.assert_allclose(np.einsum("nij,nkj->nik", rr, rr), np.broadcast_to(np.eye(3), rr.shape),
                                   atol=4e-15)


@pytest.mark.parametrize("turn_deg", [20.0, 90.0, 170.0])
def test_interpolate_poses_turns_at_a_constant_rate_about_one_axis(turn_deg):
    # Analytic: between R0 and Rot(axis, phi) R0 the pose at s is Rot(axis, s phi) R0.
    rng = np.random.default_rng(7)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    r0 = Rotation.from_rotvec(rng.normal(size=3))
    phi = np.radians(turn_deg)
    t0, t1 = rigid(r0, [0.0, 0.0, 0.0]), rigid(Rotation.from_rotvec(phi * axis) * r0, [1.0, 0.0, 0.0])
    s = np.linspace(-0.25, 1.25, 31)
    want = np.stack([(Rotation.from_rotvec(si * phi * axis) * r0).as_matrix() for si in s])
    np.testing.assert_allclose(interpolate_poses(t0, t1, s)[:, :3, :3], want, atol=1e-14)


# --- check_pose -------------------------------------------------------------------------------

def test_check_pose_accepts_rigid_and_returns_float64():
    t = rigid(random_rotations(1, 16)[0], [1e6, -1e6, 3.0])
    out = check_pose(t.astype(np.float32).tolist())
    assert isinstance(out, np.ndarray) and out.dtype == np.float64 and out.shape == (4, 4)
    check_pose(np.eye(4))
    # round-off well inside the tolerance is fine
    check_pose(np.eye(4) + np.diag([1e-7, -1e-7, 0, 0]))


@pytest.mark.parametrize("bad, needle", [
    (np.eye(3), "shape"),
    (np.eye(4)[None], "shape"),
    (np.full((4, 4), np.nan), "NaN"),
    (make_pose(translation=[np.inf, 0, 0]), "NaN or Inf"),
    (np.diag([2.0, 2.0, 2.0, 1.0]), "orthonormal"),                  # scale
    (np.diag([1.0, 1.0, -1.0, 1.0]), "det"),                         # reflection
    (make_pose(np.array([[1.0, 0.1, 0], [0, 1, 0], [0, 0, 1]])), "orthonormal"),  # shear
    (np.vstack([np.eye(4)[:3], [0.0, 0.0, 1.0, 1.0]]), "last row"),
    (np.vstack([np.eye(4)[:3], [0.0, 0.0, 0.0, 2.0]]), "last row"),
])
def test_check_pose_rejects_with_a_message_naming_the_pose(bad, needle):
    with pytest.raises(ValueError) as err:
        check_pose(bad, name="T_world_lidar")
    msg = str(err.value)
    assert msg.startswith("T_world_lidar:")
    assert needle in msg


def test_check_pose_nan_in_rotation_is_reported_as_nan_not_as_rotation():
    t = np.eye(4)
    t[1, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        check_pose(t)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_gimbal_lock_matrix_is_rebuilt_exactly(sign):
    """At pitch = +-90 deg the returned angles must still rebuild the same matrix (scipy's)."""
    m = Rotation.from_euler("ZYX", [0.7, sign * np.pi / 2, 0.3]).as_matrix()
    roll, pitch, yaw = rotmat_to_euler(m)
    assert roll == 0.0 and pitch == sign * np.pi / 2
    np.testing.assert_allclose(euler_to_rotmat(roll, pitch, yaw), m, atol=1e-14)


def test_huge_finite_quaternion_is_normalised_not_reset():
    q = np.array([1e160, 1e160, 0.0, 0.0])
    with np.errstate(all="raise"):
        np.testing.assert_allclose(normalize_quat(q), [np.sqrt(0.5), np.sqrt(0.5), 0, 0], rtol=1e-15)
    np.testing.assert_allclose(quat_to_rotmat(q), Rotation.from_quat([1, 0, 0, 1]).as_matrix(), atol=1e-15)


def test_quat_to_rotmat_takes_nested_lists():
    np.testing.assert_array_equal(quat_to_rotmat([[1, 0, 0, 0], [0, 0, 0, 1]]),
                                  [np.eye(3), np.diag([-1.0, -1.0, 1.0])])
