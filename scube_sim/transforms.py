"""Rigid transforms and quaternions: the one place for these conventions.

Conventions used everywhere in scube_sim:

- Quaternions are scalar-first ``(w, x, y, z)``, as in the 3DGS PLY layout and in ``Gf.Quatf``.
  (numpy views of ``Vt.QuatfArray`` are xyzw: convert only in ``io/usd.py``.)
- A pose is a ``(4, 4)`` float64 homogeneous matrix ``T_parent_child`` mapping points from the
  child frame into the parent frame: ``p_parent = R @ p_child + t``.
- Euler angles are roll, pitch, yaw about x, y, z applied as ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``
  (intrinsic z-y'-x'', the usual vehicle convention); sensor frames are x forward, y left, z up.
- Our frame is right-handed, metres, x forward, y left, z up (ROS REP-103 body frame). Other
  tools' axis conventions (CARLA/Unreal, OpenCV, nuScenes LIDAR_TOP, USD, OpenSCENARIO angles)
  are converted only through the "Frame conventions" section at the end of this module.
"""

from __future__ import annotations

from dataclasses import dataclass, field
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
        n = np.sqrt(np.add.reduce(q * q, axis=-1, keepdims=True))  # np.linalg.norm's own sum, bit for bit
    if np.all(n >= _EPS) and np.all(n < np.inf):  # every row fine (no NaN): skip the repairs' passes
        return q / n
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
# then spin for a while and take the cores from the tracer's threads, slowing the sweep.


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


def _quat_quadric(q: np.ndarray) -> np.ndarray:
    """(4,) wxyz -> (3, 3) H(q), quadratic in q, with R(q) = H(q) / |q|^2 for any non-zero q."""
    w, x, y, z = q
    return np.array([[w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]])


def interpolate_poses(t0: np.ndarray, t1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Poses between (4, 4) t0 (s=0) and t1 (s=1): SLERP rotation, linear translation.
    s: (N,) fractions (may leave [0, 1] to extrapolate translation). Returns (N, 4, 4) float64.

    The rotation is `slerp`'s (the same short arc, the same normalised-lerp branch for nearly
    equal rotations), evaluated without a quaternion per pose: `slerp` gives q(s) = a(s) q0 +
    b(s) q1 (before normalising), and the matrix of a quaternion is a quadratic form over its
    squared norm, so R(s) = (a^2 H0 + a b H01 + b^2 H1) / |q(s)|^2 with three constant (3, 3)
    matrices. It equals `quat_to_rotmat(slerp(...))` to a few float64 ulps, and is faster:
    a sweep asks for one pose per distinct fire time (tens of thousands)."""
    return SlerpSegment(t0, t1)(s)


class SlerpSegment:
    """`interpolate_poses` between two fixed (4, 4) poses, with what depends only on them
    computed once: calling it with fractions s (N,) gives the (N, 4, 4) poses. Tracks keep one
    per segment, so a query pays only for its own fractions."""

    def __init__(self, t0: np.ndarray, t1: np.ndarray):
        t0, t1 = np.asarray(t0, np.float64), np.asarray(t1, np.float64)
        q0 = normalize_quat(rotmat_to_quat(t0[:3, :3]))
        q1 = normalize_quat(rotmat_to_quat(t1[:3, :3]))
        dot = float(np.dot(q0, q1))
        if dot < 0.0:
            q1, dot = -q1, -dot
        self.dot = dot
        self.theta = None if dot > 0.9995 else float(np.arccos(min(dot, 1.0)))  # None: slerp's lerp branch
        h0, h1 = _quat_quadric(q0), _quat_quadric(q1)
        self.k = np.stack([h0, _quat_quadric(q0 + q1) - h0 - h1, h1])  # cross term: H(q0 + q1) - H0 - H1
        self.p0, self.dp = t0[:3, 3].copy(), t1[:3, 3] - t0[:3, 3]

    def __call__(self, s: np.ndarray) -> np.ndarray:
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        if self.theta is None:  # slerp's normalised lerp: q0 + s (q1 - q0)
            a, b = 1.0 - s, s
        else:
            sin_t = np.sin(self.theta)
            a, b = np.sin((1.0 - s) * self.theta) / sin_t, np.sin(s * self.theta) / sin_t
        # |a q0 + b q1|^2 >= 1 - (1 - dot) / 2 > 0 on the lerp branch (a + b = 1), 1 on the SLERP one
        inv_n = 1.0 / (a * a + (2.0 * self.dot) * (a * b) + b * b)
        w = np.stack([a * a * inv_n, a * b * inv_n, b * b * inv_n], axis=1)
        out = np.zeros((s.shape[0], 4, 4))
        out[:, :3, :3] = np.einsum("nk,kij->nij", w, self.k)  # einsum, not `@`: see the note above
        out[:, :3, 3] = self.p0 + s[:, None] * self.dp
        out[:, 3, 3] = 1.0
        return out


RIGID_TOL = 1e-5  # |R R^T - I| per entry (plus 1e-5 relative, as np.allclose), for every rigid-pose check
RIGID = f"expected a rigid pose: rotation orthonormal with det +1 (within {RIGID_TOL:g}), last row [0, 0, 0, 1]"


def _not_rigid(t: np.ndarray) -> tuple[int, str] | None:
    """The first of (N, 4, 4) float64 poses that is not rigid and what is wrong with it, or None.
    The one rigidity test of the package (check_pose, check_poses)."""
    finite = np.isfinite(t).all(axis=(1, 2))
    r = t[:, :3, :3]
    with np.errstate(invalid="ignore", over="ignore"):  # NaN / Inf poses: refused by `finite` first
        err = np.abs(r @ np.swapaxes(r, 1, 2) - np.eye(3))
        ortho = (err <= RIGID_TOL + RIGID_TOL * np.eye(3)).all(axis=(1, 2))
        det = np.einsum("ni,ni->n", r[:, 0], np.cross(r[:, 1], r[:, 2]))  # rows r0 . (r1 x r2)
        row = (np.abs(t[:, 3] - [0.0, 0.0, 0.0, 1.0]) <= [1e-8, 1e-8, 1e-8, 1e-8 + 1e-5]).all(axis=1)
    bad = ~(finite & ortho & (det >= 0) & row)
    if not bad.any():
        return None
    i = int(np.argmax(bad))
    if not finite[i]:
        return i, "contains NaN or Inf"
    if not ortho[i]:
        return i, (f"rotation part is not orthonormal with det +1 (max |R R^T - I| = {float(err[i].max()):.3g}: "
                   f"scaled or sheared)")
    if det[i] < 0:
        return i, f"rotation part is not orthonormal with det +1 (det {float(det[i]):+.3f}: a reflection)"
    return i, f"last row must be [0, 0, 0, 1], got {[float(v) for v in t[i, 3]]}"


def check_pose(t, name: str = "pose") -> np.ndarray:
    """Validate a (4, 4) rigid pose; raises InputError naming `name` on NaN/Inf or a non-rotation."""
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (4, 4):
        raise InputError(f"{name}: expected a (4, 4) pose matrix, got shape {t.shape}")
    bad = _not_rigid(t[None])
    if bad is not None:
        raise InputError(f"{name}: {bad[1]}; {RIGID}")
    return t


def check_poses(t, name: str = "poses", times=None, count: int | None = None) -> np.ndarray:
    """Validate (N, 4, 4) rigid poses at once (N = `count` if given) -> float64. The InputError
    names `name`, the first bad pose's index (and its time, from `times` (N,) seconds) and what
    a rigid pose is."""
    t = np.asarray(t, dtype=np.float64)
    if t.ndim != 3 or t.shape[1:] != (4, 4) or (count is not None and t.shape[0] != count):
        want = "N" if count is None else str(count)
        raise InputError(f"{name}: expected ({want}, 4, 4) pose matrices, got shape {t.shape}")
    bad = _not_rigid(t)
    if bad is not None:
        i, problem = bad
        when = "" if times is None else f" (time {float(np.asarray(times).reshape(-1)[i]):.6f} s)"
        raise InputError(f"{name}: pose {i} of {t.shape[0]}{when}: {problem}; {RIGID}")
    return t


# --- Frame conventions ------------------------------------------------------------------------
# Every other tool's axes are described by one matrix: the convention's x, y, z unit axes written
# in our frame (x forward, y left, z up, metres). Points convert by that matrix (and the unit);
# a pose whose parent and child frames both follow a convention converts by conjugation, which
# keeps the rotation proper even when the convention is left-handed (CARLA/Unreal).


@dataclass(frozen=True)
class FrameConvention:
    """A named axis convention.

    basis: (3, 3) float64, columns = the convention's x, y, z unit axes expressed in our frame
    (x forward, y left, z up). meters_per_unit: metres per coordinate unit (Unreal: 0.01).
    A point converts as ``p_ours = meters_per_unit * basis @ p_conv``."""

    name: str
    basis: np.ndarray = field(repr=False)
    meters_per_unit: float = 1.0
    description: str = ""

    @property
    def right_handed(self) -> bool:
        return bool(np.linalg.det(self.basis) > 0)


def _axes(*cols) -> np.ndarray:
    b = np.array(cols, dtype=np.float64).T
    b.setflags(write=False)
    return b


_F, _B, _L, _R, _U, _D = (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)

FRAME_CONVENTIONS: dict[str, FrameConvention] = {c.name: c for c in [
    FrameConvention("ours", _axes(_F, _L, _U), 1.0,
                    "scube_sim: right-handed, x forward, y left, z up, metres (ROS REP-103 body frame)"),
    FrameConvention("rep103", _axes(_F, _L, _U), 1.0,
                    "ROS REP-103 body frame: x forward, y left, z up, metres (the same as ours)"),
    FrameConvention("carla", _axes(_F, _R, _U), 1.0,
                    "CARLA Python API (Unreal axes): LEFT-handed, x forward, y right, z up, metres"),
    FrameConvention("unreal", _axes(_F, _R, _U), 0.01,
                    "Unreal Engine: LEFT-handed, x forward, y right, z up, centimetres"),
    FrameConvention("opencv", _axes(_R, _D, _F), 1.0,
                    "OpenCV camera: x right, y down, z forward (optical axis), metres"),
    FrameConvention("nuscenes_lidar", _axes(_R, _F, _U), 1.0,
                    "nuScenes LIDAR_TOP sensor frame: x right, y forward, z up, metres"),
    FrameConvention("usd_z_up", _axes(_F, _L, _U), 1.0,
                    "USD stage with upAxis Z and metersPerUnit 1 (what scube_sim writes): our axes"),
    # USD fixes only the up axis; Y-up pairs with our axes by the usual Z-up -> Y-up turn about x
    # (as glTF and DCC exporters do): (x, y, z)_ours = (x, -z, y)_usd.
    FrameConvention("usd_y_up", _axes(_F, _U, _R), 1.0,
                    "USD stage with upAxis Y (metersPerUnit 1): x forward, y up, z right"),
]}

USD_FALLBACK_UP_AXIS = "Y"  # UsdGeom's fallback when a stage has no upAxis
USD_FALLBACK_METERS_PER_UNIT = 0.01  # UsdGeom's fallback (centimetres) when metersPerUnit is unset


def frame_convention(frame: "str | FrameConvention") -> FrameConvention:
    """A convention by name (see `FRAME_CONVENTIONS`) or the object itself."""
    if isinstance(frame, FrameConvention):
        return frame
    key = str(frame).lower().replace("-", "_")
    if key not in FRAME_CONVENTIONS:
        raise InputError(f"frame convention {frame!r}: unknown; expected one of {sorted(FRAME_CONVENTIONS)}")
    return FRAME_CONVENTIONS[key]


def usd_frame_convention(up_axis: str | None = None, meters_per_unit: float | None = None) -> FrameConvention:
    """The convention of a USD stage from its authored metadata; None means unset, which USD
    reads as upAxis "Y" and metersPerUnit 0.01 (centimetres), not as our Z-up metres."""
    up = USD_FALLBACK_UP_AXIS if up_axis is None else str(up_axis).upper()
    mpu = USD_FALLBACK_METERS_PER_UNIT if meters_per_unit is None else float(meters_per_unit)
    if up not in ("Y", "Z"):
        raise InputError(f"USD upAxis: expected 'Y' or 'Z', got {up_axis!r}")
    if not (np.isfinite(mpu) and mpu > 0):
        raise InputError(f"USD metersPerUnit: expected a finite number > 0, got {meters_per_unit!r}")
    base = FRAME_CONVENTIONS["usd_z_up" if up == "Z" else "usd_y_up"]
    return FrameConvention(f"usd_{up.lower()}_up@{mpu:g}m", base.basis, mpu,
                           f"USD stage: upAxis {up}, metersPerUnit {mpu:g}")


def check_rotation(r, name: str = "rotation") -> np.ndarray:
    """Validate a (3, 3) or (N, 3, 3) proper rotation (orthonormal, det +1) -> float64.

    A det -1 matrix is a reflection: a handedness mirror, typically a left-handed (CARLA/Unreal)
    matrix taken as ours, or a y flip applied to one side of a pose only."""
    r = np.asarray(r, dtype=np.float64)
    if r.shape[-2:] != (3, 3):
        raise InputError(f"{name}: expected (3, 3) rotation matrices, got shape {r.shape}")
    if not np.all(np.isfinite(r)):
        raise InputError(f"{name}: contains NaN or Inf")
    rt = np.swapaxes(r, -1, -2)
    if not np.allclose(np.einsum("...ij,...jk->...ik", r, rt), np.eye(3), atol=1e-5):
        raise InputError(f"{name}: not orthonormal (R R^T != I)")
    det = np.linalg.det(r)
    if np.any(det < 0):
        raise InputError(f"{name}: det {float(np.min(det)):+.3f}: a reflection, not a rotation (a handedness "
                         f"mirror: convert left-handed CARLA/Unreal poses with pose_to_ours, which flips "
                         f"both sides)")
    return r


def points_to_ours(points, frame: "str | FrameConvention") -> np.ndarray:
    """(N, 3) points in `frame`'s axes and units -> (N, 3) float64 metres in our frame."""
    c = frame_convention(frame)
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"points ({c.name}): expected shape (N, 3), got {p.shape}")
    return np.einsum("ij,nj->ni", c.basis * c.meters_per_unit, p)


def points_from_ours(points, frame: "str | FrameConvention") -> np.ndarray:
    """(N, 3) metres in our frame -> (N, 3) float64 in `frame`'s axes and units."""
    c = frame_convention(frame)
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"points ({c.name}): expected shape (N, 3), got {p.shape}")
    return np.einsum("ji,nj->ni", c.basis / c.meters_per_unit, p)  # basis is orthonormal: inverse = transpose


def _pose_frames(frame, child_frame) -> tuple[FrameConvention, FrameConvention]:
    p = frame_convention(frame)
    c = p if child_frame is None else frame_convention(child_frame)
    if not np.isclose(p.meters_per_unit, c.meters_per_unit, rtol=1e-12):
        raise InputError(f"pose: parent frame {p.name} ({p.meters_per_unit:g} m/unit) and child frame {c.name} "
                         f"({c.meters_per_unit:g} m/unit) differ in units; a rigid pose cannot carry a scale")
    return p, c


def pose_to_ours(pose, frame: "str | FrameConvention", child_frame: "str | FrameConvention | None" = None,
                 *, name: str = "pose") -> np.ndarray:
    """(4, 4) or (N, 4, 4) pose `T_parent_child` written in `frame`'s conventions -> ours, float64.

    frame: the parent's (world's) convention; child_frame: the child's (body's or sensor's),
    default the same. ``R' = B_parent R B_child^T``, ``t' = meters_per_unit * B_parent t``.
    The result is checked to be a proper rotation (`check_rotation`)."""
    p, c = _pose_frames(frame, child_frame)
    t = np.asarray(pose, dtype=np.float64)
    if t.shape[-2:] != (4, 4):
        raise InputError(f"{name} ({p.name}): expected shape (4, 4) or (N, 4, 4), got {t.shape}")
    out = np.zeros_like(t)
    out[..., :3, :3] = np.einsum("ij,...jk,lk->...il", p.basis, t[..., :3, :3], c.basis)
    out[..., :3, 3] = np.einsum("ij,...j->...i", p.basis * p.meters_per_unit, t[..., :3, 3])
    out[..., 3, 3] = 1.0
    check_rotation(out[..., :3, :3], f"{name} ({p.name} -> ours)")
    return out


def pose_from_ours(pose, frame: "str | FrameConvention", child_frame: "str | FrameConvention | None" = None,
                   *, name: str = "pose") -> np.ndarray:
    """The inverse of `pose_to_ours`: a (4, 4) or (N, 4, 4) pose in our frame -> `frame`'s
    conventions (`child_frame` for the child, default the same), float64."""
    p, c = _pose_frames(frame, child_frame)
    t = np.asarray(pose, dtype=np.float64)
    if t.shape[-2:] != (4, 4):
        raise InputError(f"{name}: expected shape (4, 4) or (N, 4, 4), got {t.shape}")
    check_rotation(t[..., :3, :3], f"{name} (ours)")
    out = np.zeros_like(t)
    out[..., :3, :3] = np.einsum("ji,...jk,kl->...il", p.basis, t[..., :3, :3], c.basis)
    out[..., :3, 3] = np.einsum("ji,...j->...i", p.basis / p.meters_per_unit, t[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


# CARLA: carla.Location in metres on Unreal's left-handed axes (x forward, y right, z up);
# carla.Rotation(pitch, yaw, roll) in degrees: yaw about z (positive turns x towards +y, i.e.
# clockwise seen from above: a right turn), pitch about y (positive raises the nose), roll about
# x (positive lowers the right side), applied yaw, then pitch, then roll about the turned axes.
# The matrix is LibCarla's geom::Transform::GetMatrix; in our frame yaw and pitch change sign and
# roll does not (as carla_ros_bridge converts).


def carla_rotation_matrix(pitch: float, yaw: float, roll: float) -> np.ndarray:
    """carla.Rotation angles (degrees, carla.Rotation's argument order) -> (3, 3) float64 in
    CARLA's own left-handed axes, as LibCarla's Transform::GetMatrix builds it."""
    p, y, r = np.deg2rad([pitch, yaw, roll])
    cp, sp, cy, sy, cr, sr = np.cos(p), np.sin(p), np.cos(y), np.sin(y), np.cos(r), np.sin(r)
    return np.array([
        [cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr],
        [cp * sy, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr],
        [sp, -cp * sr, cp * cr],
    ])


def carla_transform_to_pose(location, rotation) -> np.ndarray:
    """A carla.Transform -> (4, 4) float64 pose in our frame (parent and child both CARLA-axed:
    a world transform of an actor or sensor). location: (x, y, z) metres; rotation: (pitch, yaw,
    roll) degrees, carla.Rotation's order."""
    loc = np.asarray(location, dtype=np.float64)
    rot = np.asarray(rotation, dtype=np.float64)
    if loc.shape != (3,) or rot.shape != (3,) or not (np.all(np.isfinite(loc)) and np.all(np.isfinite(rot))):
        raise InputError(f"CARLA transform: expected finite location (x, y, z) and rotation (pitch, yaw, roll), "
                         f"got {loc.tolist()} and {rot.tolist()}")
    return pose_to_ours(make_pose(carla_rotation_matrix(*rot), loc), "carla", name="CARLA transform")


def pose_to_carla_transform(pose) -> tuple[np.ndarray, np.ndarray]:
    """(4, 4) pose in our frame -> (location (x, y, z) metres, rotation (pitch, yaw, roll) degrees)
    for carla.Transform(carla.Location(*loc), carla.Rotation(*rot)). Inverse of
    `carla_transform_to_pose`; at pitch +-90 deg roll is 0 and yaw carries the turn."""
    m = pose_from_ours(check_pose(pose, "pose"), "carla")
    r = m[:3, :3]
    pitch = np.arcsin(np.clip(r[2, 0], -1.0, 1.0))
    if np.hypot(r[2, 1], r[2, 2]) < 1e-12:  # gimbal lock: only yaw -+ roll is defined
        roll, yaw = 0.0, np.arctan2(-r[0, 1], r[1, 1])
    else:
        roll, yaw = np.arctan2(-r[2, 1], r[2, 2]), np.arctan2(r[1, 0], r[0, 0])
    return m[:3, 3].copy(), np.rad2deg([pitch, yaw, roll])


# ASAM OpenSCENARIO 1.x (ISO 8855 axes, the same as ours): heading h about z, pitch p about y,
# roll r about x, radians, right-hand rule, applied heading first, then pitch, then roll about
# the turned axes: R = Rz(h) Ry(p) Rx(r) (as ASAM OSI writes it), i.e. `euler_to_rotmat`.


def hpr_to_rotmat(h: float, p: float = 0.0, r: float = 0.0) -> np.ndarray:
    """OpenSCENARIO heading, pitch, roll (radians) -> (3, 3) float64, R = Rz(h) Ry(p) Rx(r)."""
    return euler_to_rotmat(r, p, h)


def rotmat_to_hpr(rot) -> tuple[float, float, float]:
    """(3, 3) rotation -> OpenSCENARIO (heading, pitch, roll) radians, the inverse of
    `hpr_to_rotmat` (heading and roll in (-pi, pi], pitch in [-pi/2, pi/2])."""
    roll, pitch, yaw = rotmat_to_euler(check_rotation(rot))
    return yaw, pitch, roll
