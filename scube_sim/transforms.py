"""Rigid transforms and quaternions: the one place for these conventions.

Conventions used everywhere in scube_sim:

- Quaternions are scalar-first ``(w, x, y, z)``, as in the 3DGS PLY layout and in ``Gf.Quatf``.
  (numpy views of ``Vt.QuatfArray`` are xyzw: convert only in ``io/usd.py``.)
- A pose is a ``(4, 4)`` float64 homogeneous matrix ``T_parent_child`` mapping points from the
  child frame into the parent frame: ``p_parent = R @ p_child + t``.
- Euler angles are roll, pitch, yaw about x, y, z applied as ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``
  (intrinsic z-y'-x'', the usual vehicle convention); sensor frames are x forward, y left, z up.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .errors import InputError

_EPS = 1e-12

# A pose that moves with time: absolute times (N,) seconds -> (N, 4, 4) float64 poses
# (`T_parent_child` at each time). The LiDAR's pose_fn, actor tracks and dataset pose streams.
PoseFn = Callable[[np.ndarray], np.ndarray]


def normalize_quat(q: np.ndarray) -> np.ndarray:
    """(..., 4) wxyz -> unit quaternions, float64. A zero-norm or non-finite quaternion becomes
    the identity (1, 0, 0, 0): a defined result, since raw network outputs can be exactly zero."""
    q = np.asarray(q, dtype=np.float64)
    with np.errstate(over="ignore"):
        n = np.linalg.norm(q, axis=-1, keepdims=True)
    big = np.isinf(n) & np.all(np.isfinite(q), axis=-1, keepdims=True)
    if np.any(big):  # finite but past sqrt(max float): normalise the rescaled quaternion instead
        q = np.where(big, q / np.where(big, np.abs(q).max(axis=-1, keepdims=True), 1.0), q)
        n = np.where(big, np.linalg.norm(q, axis=-1, keepdims=True), n)
    bad = ~np.isfinite(n) | (n < _EPS)
    out = np.where(bad, 0.0, q / np.where(bad, 1.0, n))
    if np.any(bad):
        out[..., 0] = np.where(bad[..., 0], 1.0, out[..., 0])
    return out


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """(..., 4) wxyz (any norm) -> (..., 3, 3) float64 rotation matrices."""
    w, x, y, z = np.moveaxis(normalize_quat(q), -1, 0)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    r = np.stack(
        [
            1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
            2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
            2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
        ],
        axis=-1,
    )
    return r.reshape(np.shape(q)[:-1] + (3, 3)) if np.ndim(q) > 1 else r.reshape(3, 3)


def rotmat_to_quat(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit wxyz quaternions with w >= 0, float64.

    Uses the largest-diagonal branch (Shepperd) so it stays accurate near 180-degree rotations.
    """
    r = np.asarray(r, dtype=np.float64)
    shape = r.shape[:-2]
    m = r.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    diag = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    branch = np.argmax(diag, axis=1)
    q = np.empty((m.shape[0], 4))
    for b in range(4):
        sel = branch == b
        if not np.any(sel):
            continue
        s = m[sel]
        if b == 0:
            t = np.sqrt(np.maximum(1.0 + tr[sel], 0.0)) * 2.0
            q[sel] = np.stack([0.25 * t, (s[:, 2, 1] - s[:, 1, 2]) / t,
                               (s[:, 0, 2] - s[:, 2, 0]) / t, (s[:, 1, 0] - s[:, 0, 1]) / t], 1)
        elif b == 1:
            t = np.sqrt(np.maximum(1.0 + s[:, 0, 0] - s[:, 1, 1] - s[:, 2, 2], 0.0)) * 2.0
            q[sel] = np.stack([(s[:, 2, 1] - s[:, 1, 2]) / t, 0.25 * t,
                               (s[:, 0, 1] + s[:, 1, 0]) / t, (s[:, 0, 2] + s[:, 2, 0]) / t], 1)
        elif b == 2:
            t = np.sqrt(np.maximum(1.0 + s[:, 1, 1] - s[:, 0, 0] - s[:, 2, 2], 0.0)) * 2.0
            q[sel] = np.stack([(s[:, 0, 2] - s[:, 2, 0]) / t, (s[:, 0, 1] + s[:, 1, 0]) / t,
                               0.25 * t, (s[:, 1, 2] + s[:, 2, 1]) / t], 1)
        else:
            t = np.sqrt(np.maximum(1.0 + s[:, 2, 2] - s[:, 0, 0] - s[:, 1, 1], 0.0)) * 2.0
            q[sel] = np.stack([(s[:, 1, 0] - s[:, 0, 1]) / t, (s[:, 0, 2] + s[:, 2, 0]) / t,
                               (s[:, 1, 2] + s[:, 2, 1]) / t, 0.25 * t], 1)
    q = normalize_quat(q)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(shape + (4,))


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) wxyz quaternions, float64."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, np.float64), -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


def slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Spherical interpolation between unit wxyz quaternions (4,) at fractions s (N,) -> (N, 4).

    Takes the short arc; falls back to normalised lerp when the quaternions nearly coincide."""
    q0 = normalize_quat(q0)
    q1 = normalize_quat(q1)
    s = np.asarray(s, dtype=np.float64)[..., None]
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        return normalize_quat(q0 + s * (q1 - q0))
    theta = np.arccos(min(dot, 1.0))
    sin_t = np.sin(theta)
    return (np.sin((1.0 - s) * theta) * q0 + np.sin(s * theta) * q1) / sin_t


def euler_to_rotmat(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Radians -> (3, 3) float64, R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def rotmat_to_euler(r: np.ndarray) -> tuple[float, float, float]:
    """(3, 3) -> (roll, pitch, yaw) radians, the inverse of `euler_to_rotmat` (at gimbal lock,
    pitch +-90 deg, roll is 0 and yaw carries the whole turn about z)."""
    r = np.asarray(r, dtype=np.float64)
    pitch = float(np.arcsin(np.clip(-r[2, 0], -1.0, 1.0)))
    if np.hypot(r[2, 1], r[2, 2]) < 1e-12:
        # Gimbal lock (pitch = +-90 deg): only yaw -+ roll is defined; report it all as yaw.
        return 0.0, float(np.copysign(np.pi / 2, -r[2, 0])), float(np.arctan2(-r[0, 1], r[1, 1]))
    roll = float(np.arctan2(r[2, 1], r[2, 2]))
    yaw = float(np.arctan2(r[1, 0], r[0, 0]))
    return roll, pitch, yaw


def make_pose(rotation: np.ndarray | None = None, translation=None) -> np.ndarray:
    """(3, 3) rotation and (3,) translation -> (4, 4) float64 pose."""
    t = np.eye(4)
    if rotation is not None:
        t[:3, :3] = rotation
    if translation is not None:
        t[:3, 3] = translation
    return t


def pose_from_xyz_rpy(xyz, rpy_deg) -> np.ndarray:
    """Metres and degrees (roll, pitch, yaw) -> (4, 4) float64 pose."""
    roll, pitch, yaw = np.deg2rad(np.asarray(rpy_deg, dtype=np.float64))
    return make_pose(euler_to_rotmat(roll, pitch, yaw), np.asarray(xyz, dtype=np.float64))


def invert_pose(t: np.ndarray) -> np.ndarray:
    """Inverse of (..., 4, 4) rigid poses without a general matrix inverse."""
    t = np.asarray(t, dtype=np.float64)
    out = np.zeros_like(t)
    rt = np.swapaxes(t[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, t[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


# The (N, 3) x (3, 3) products below are einsum, not `@`: `@` goes to BLAS, whose worker threads
# then spin for a while and take the cores from the tracer's threads (a LiDAR sweep ran 1.5x slower).


def transform_points(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) pose or (N, 4, 4) per-point poses to (N, 3) points -> (N, 3) float64."""
    t = np.asarray(t, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    if t.ndim == 2:
        return np.einsum("ij,nj->ni", t[:3, :3], p) + t[:3, 3]
    return np.einsum("nij,nj->ni", t[:, :3, :3], p) + t[:, :3, 3]


def rotate_vectors(t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate (N, 3) vectors by the rotation part of a (4, 4) or (N, 4, 4) pose."""
    t = np.asarray(t, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if t.ndim == 2:
        return np.einsum("ij,nj->ni", t[:3, :3], v)
    return np.einsum("nij,nj->ni", t[:, :3, :3], v)


def interpolate_poses(t0: np.ndarray, t1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Poses between (4, 4) t0 (s=0) and t1 (s=1): SLERP rotation, linear translation.
    s: (N,) fractions (may leave [0, 1] to extrapolate translation). Returns (N, 4, 4) float64."""
    s = np.atleast_1d(np.asarray(s, dtype=np.float64))
    q = slerp(rotmat_to_quat(t0[:3, :3]), rotmat_to_quat(t1[:3, :3]), s)
    out = np.zeros((s.shape[0], 4, 4))
    out[:, :3, :3] = quat_to_rotmat(q)
    out[:, :3, 3] = t0[:3, 3] + s[:, None] * (t1[:3, 3] - t0[:3, 3])
    out[:, 3, 3] = 1.0
    return out


def check_pose(t, name: str = "pose") -> np.ndarray:
    """Validate a (4, 4) rigid pose; raises ValueError naming `name` on NaN/Inf or a non-rotation."""
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (4, 4):
        raise InputError(f"{name}: expected a (4, 4) pose matrix, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise InputError(f"{name}: contains NaN or Inf")
    r = t[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or np.linalg.det(r) < 0:
        raise InputError(f"{name}: rotation part is not orthonormal with det +1")
    if not np.allclose(t[3], [0, 0, 0, 1]):
        raise InputError(f"{name}: last row must be [0, 0, 0, 1]")
    return t
