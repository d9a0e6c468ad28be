"""Vehicle motion from wheel speed and steering: the kinematic bicycle model.

- `VehicleSample`: one measurement of speed, steering-wheel angle and/or yaw rate (what
  `sim.can.CanVehicleDecoder` decodes from CAN).
- `DeadReckoner` integrates those samples into planar poses.
- `calibrate_bicycle` fits the steering ratio and zero offset against a reference yaw rate.

Units: seconds, metres, m/s, radians unless a name says `_deg`. Poses are (4, 4) float64
ego-to-world (`transforms` conventions: x forward, y left, z up). The dead-reckoned pose is the
**rear-axle centre** (the reference point of the kinematic bicycle model); compose a mount
transform to get a sensor pose.

RAV4 parameters (`RAV4_WHEELBASE`, `RAV4_STEER_RATIO`): the 2017 RAV4's wheelbase is 2.66 m
(2 660 mm, manufacturer spec; openpilot uses 2.65) and the steering ratio 15.7 is a nominal
*low-speed* value (openpilot's tuned value is 16.88, its comment quotes 14.5 end-to-end). On a
highway log (small steering angles) the ratio that best maps the steering angle to the yaw rate
is well above it (an *effective* ratio that absorbs understeer at speed; poorly conditioned
there), and the position drift comes instead from the steering sensor's zero offset and the
wheel-speed scale. Those two are `steer_offset_deg` and `speed_scale` (defaults 0 and 1: nominal,
uncalibrated); `calibrate_bicycle` estimates them against a reference trajectory, and
`tools/can_drift.py` prints the numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..transforms import check_pose, interpolate_poses

RAV4_WHEELBASE = 2.66  # m
RAV4_STEER_RATIO = 15.7  # steering-wheel angle / road-wheel angle, nominal


@dataclass(frozen=True)
class VehicleSample:
    """One decoded message: timestamp (s, the message's clock), and whichever of speed (m/s),
    steering-wheel angle (deg, positive = left) and yaw rate (rad/s, positive = left) it holds."""

    t: float
    speed: float | None = None
    steer_deg: float | None = None
    yaw_rate: float | None = None


class DeadReckoner:
    """Kinematic bicycle model (rear-axle reference) integrating (x, y, yaw) in a local plane.

    yaw rate = v tan(delta) / L, with delta = (steering-wheel angle - steer_offset_deg) /
    steer_ratio and L = wheelbase (m); v = speed_scale * decoded speed. With
    ``yaw_source="yaw_rate"`` a measured yaw rate (rad/s) is used instead of the steering angle.
    Forward driving only (wheel speeds carry no direction).

    Each new sample (speed, steering or yaw rate at time t) closes the step from the previous
    sample time: speed and yaw rate are taken as the means of their values at both ends
    (trapezoid) and the step follows the exact circular arc of that constant speed and yaw rate,
    so a constant-input manoeuvre is integrated exactly (circle / line). The state starts at
    (0, 0, 0) at the first instant at which both inputs are known; the world pose is
    ``start_pose @ planar_pose(x, y, yaw)``. Samples at or before the last time (out of order)
    only update the inputs (counted in `out_of_order`).

    `times`, `states` (N, 3), `speeds`, `yaw_rates`, `poses()` expose the series; `pose_at` /
    `velocity_at` interpolate it (SLERP via `transforms.interpolate_poses`) and hold the first /
    last value outside it.
    """

    def __init__(self, wheelbase: float = RAV4_WHEELBASE, steer_ratio: float = RAV4_STEER_RATIO, *,
                 steer_offset_deg: float = 0.0, speed_scale: float = 1.0,
                 yaw_source: str = "steering", start_pose: np.ndarray | None = None):
        if not (wheelbase > 0 and steer_ratio > 0 and speed_scale > 0):
            raise InputError("wheelbase, steer_ratio and speed_scale must be > 0")
        if yaw_source not in ("steering", "yaw_rate"):
            raise InputError(f"yaw_source must be 'steering' or 'yaw_rate', got {yaw_source!r}")
        self.wheelbase = float(wheelbase)
        self.steer_ratio = float(steer_ratio)
        self.steer_offset_deg = float(steer_offset_deg)
        self.speed_scale = float(speed_scale)
        self.yaw_source = yaw_source
        self.reset(start_pose)

    def reset(self, start_pose: np.ndarray | None = None) -> None:
        """Forget the series; optionally set a new start pose (4, 4), default identity."""
        self.start_pose = np.eye(4) if start_pose is None else check_pose(start_pose, "start_pose").copy()
        self._t: list[float] = []
        self._x: list[float] = []
        self._y: list[float] = []
        self._yaw: list[float] = []
        self._v: list[float] = []
        self._w: list[float] = []
        self._speed: float | None = None
        self._steer: float | None = None
        self._rate: float | None = None
        self._cache: dict = {}
        self.out_of_order = 0

    # -- inputs
    def yaw_rate_from_steering(self, speed: float, steer_deg: float) -> float:
        """rad/s from speed (m/s, already scaled) and steering-wheel angle (deg)."""
        delta = math.radians(steer_deg - self.steer_offset_deg) / self.steer_ratio
        return speed * math.tan(delta) / self.wheelbase

    def _current(self):
        if self._speed is None:
            return None
        if self.yaw_source == "steering":
            if self._steer is None:
                return None
            return self._speed, self.yaw_rate_from_steering(self._speed, self._steer)
        if self._rate is None:
            return None
        return self._speed, self._rate

    def add(self, sample: VehicleSample) -> bool:
        """Feed one decoded sample; see `update`."""
        return self.update(sample.t, speed=sample.speed, steer_deg=sample.steer_deg,
                           yaw_rate=sample.yaw_rate)

    def update(self, t: float, *, speed: float | None = None, steer_deg: float | None = None,
               yaw_rate: float | None = None) -> bool:
        """New input value(s) at time t (s). Returns True when a state was appended."""
        t = float(t)
        if speed is not None:
            self._speed = float(speed) * self.speed_scale
        if steer_deg is not None:
            self._steer = float(steer_deg)
        if yaw_rate is not None:
            self._rate = float(yaw_rate)
        cur = self._current()
        if cur is None:
            return False
        v1, w1 = cur
        if not self._t:
            self._append(t, 0.0, 0.0, 0.0, v1, w1)
            return True
        t0 = self._t[-1]
        if t <= t0:  # same instant or out of order: inputs only
            if t < t0:
                self.out_of_order += 1
            self._v[-1], self._w[-1] = v1, w1
            self._cache.clear()
            return False
        dt = t - t0
        v = 0.5 * (self._v[-1] + v1)
        w = 0.5 * (self._w[-1] + w1)
        yaw0 = self._yaw[-1]
        dyaw = w * dt
        # exact arc: chord length v dt sinc(dyaw / 2) along the mean heading yaw0 + dyaw / 2
        chord = v * dt * float(np.sinc(dyaw / (2.0 * math.pi)))
        mid = yaw0 + 0.5 * dyaw
        self._append(t, self._x[-1] + chord * math.cos(mid), self._y[-1] + chord * math.sin(mid),
                     yaw0 + dyaw, v1, w1)
        return True

    def _append(self, t, x, y, yaw, v, w):
        self._t.append(t)
        self._x.append(x)
        self._y.append(y)
        self._yaw.append(yaw)
        self._v.append(v)
        self._w.append(w)
        self._cache.clear()

    # -- series
    def __len__(self) -> int:
        return len(self._t)

    @property
    def ready(self) -> bool:
        """True once a first state exists."""
        return bool(self._t)

    @property
    def last_time(self) -> float:
        """Time (s) of the last state; 0 before any."""
        return float(self._t[-1]) if self._t else 0.0

    def _arr(self, key: str) -> np.ndarray:
        if key not in self._cache:
            src = {"t": self._t, "x": self._x, "y": self._y, "yaw": self._yaw, "v": self._v,
                   "w": self._w}[key]
            self._cache[key] = np.asarray(src, np.float64)
        return self._cache[key]

    @property
    def times(self) -> np.ndarray:
        """(N,) float64 state times (s)."""
        return self._arr("t").copy()

    @property
    def states(self) -> np.ndarray:
        """(N, 3) float64 planar (x m, y m, yaw rad, unwrapped) in the start pose's frame."""
        return np.column_stack([self._arr("x"), self._arr("y"), self._arr("yaw")])

    @property
    def speeds(self) -> np.ndarray:
        """(N,) m/s (after `speed_scale`)."""
        return self._arr("v").copy()

    @property
    def yaw_rates(self) -> np.ndarray:
        """(N,) rad/s."""
        return self._arr("w").copy()

    def poses(self) -> np.ndarray:
        """(N, 4, 4) float64 rear-axle-to-world poses at `times` (a copy)."""
        return self._poses().copy()

    def _poses(self) -> np.ndarray:
        if "poses" not in self._cache:
            x, y, yaw = self._arr("x"), self._arr("y"), self._arr("yaw")
            local = np.zeros((len(x), 4, 4))
            c, s = np.cos(yaw), np.sin(yaw)
            local[:, 0, 0], local[:, 0, 1], local[:, 1, 0], local[:, 1, 1] = c, -s, s, c
            local[:, 2, 2] = local[:, 3, 3] = 1.0
            local[:, 0, 3], local[:, 1, 3] = x, y
            self._cache["poses"] = np.einsum("ij,njk->nik", self.start_pose, local)
        return self._cache["poses"]

    def pose_at(self, t) -> np.ndarray:
        """Pose at time(s) t: scalar -> (4, 4), array (N,) -> (N, 4, 4). Linear translation and
        SLERP rotation between the bracketing states; held before the first / after the last.
        Before any state: the start pose."""
        scalar = np.ndim(t) == 0
        tq = np.atleast_1d(np.asarray(t, np.float64))
        out = np.empty((len(tq), 4, 4))
        if not self._t:
            out[:] = self.start_pose
            return out[0] if scalar else out
        times, poses = self._arr("t"), self._poses()
        if len(times) == 1:
            out[:] = poses[0]
            return out[0] if scalar else out
        tc = np.clip(tq, times[0], times[-1])
        i = np.clip(np.searchsorted(times, tc, side="right") - 1, 0, len(times) - 2)
        s = (tc - times[i]) / (times[i + 1] - times[i])
        for k in np.unique(i):
            sel = i == k
            out[sel] = interpolate_poses(poses[k], poses[k + 1], s[sel])
        return out[0] if scalar else out

    def velocity_at(self, t) -> np.ndarray:
        """World-frame velocity (m/s) of the rear-axle centre at time(s) t: (3,) or (N, 3)."""
        scalar = np.ndim(t) == 0
        tq = np.atleast_1d(np.asarray(t, np.float64))
        if not self._t:
            out = np.zeros((len(tq), 3))
            return out[0] if scalar else out
        times = self._arr("t")
        v = np.interp(tq, times, self._arr("v"))
        yaw = np.interp(tq, times, self._arr("yaw"))
        local = np.column_stack([v * np.cos(yaw), v * np.sin(yaw), np.zeros_like(v)])
        out = local @ self.start_pose[:3, :3].T
        return out[0] if scalar else out


def calibrate_bicycle(times, speed, steer_deg, yaw_rate_ref, wheelbase: float = RAV4_WHEELBASE,
                      steer_ratio: float | None = None) -> tuple[float, float]:
    """Least-squares steering ratio and steering-angle zero offset (deg) from a reference yaw rate.

    All inputs are (N,) on common times: speed m/s, steering-wheel angle deg, reference yaw rate
    rad/s (e.g. differentiated from a ground-truth heading, smoothed). Small-angle model
    ``yaw_rate = v (steer - offset) / (ratio L)``. With `steer_ratio` given only the offset is
    fitted. Returns (steer_ratio, steer_offset_deg)."""
    v = np.asarray(speed, np.float64)
    sw = np.radians(np.asarray(steer_deg, np.float64))
    w = np.asarray(yaw_rate_ref, np.float64)
    a = v * sw / wheelbase
    b = -v / wheelbase
    if steer_ratio is None:
        (k, c), *_ = np.linalg.lstsq(np.column_stack([a, b]), w, rcond=None)
        if k <= 0:
            raise InputError("calibrate_bicycle: the fitted steering gain is not positive; the "
                             "reference has too little turning")
        return float(1.0 / k), float(np.degrees(c / k))
    k = 1.0 / float(steer_ratio)
    # w = k a + k sw0 b  ->  least squares for sw0
    off = float(np.dot(b * k, w - k * a) / np.dot(b * k, b * k))
    return float(steer_ratio), float(np.degrees(off))
