"""Where the ego is: pose sources for self-driven runs.

A pose source (`contracts.PoseSource`) has `t_start`, `t_end` (seconds) and
`poses_at(times (N,)) -> (N, 4, 4)` ego-to-world poses. Trajectories interpolate linearly in
position and by SLERP in rotation, and hold their ends (`track_pose_fn`, also the actors' tracks).
`EditedTrajectory` makes counterfactual replays: a lateral offset (optionally ramped in, for a lane
change), a speed scale and a time shift applied to a recorded trajectory.
The CAN source (dead reckoning from a bus or a log) is in `sim.can`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.openscenario import read_openscenario
from ..transforms import PoseFn, SlerpSegment, check_pose
from .contracts import PoseSource


def track_pose_fn(times: np.ndarray, poses: np.ndarray) -> PoseFn:
    """A pose function from a sampled track: times (T,) increasing seconds, poses (T, 4, 4);
    linear in position, SLERP in rotation (`transforms.interpolate_poses`), held at the ends."""
    times = np.asarray(times, np.float64)
    poses = np.asarray(poses, np.float64)
    segments: dict[int, SlerpSegment] = {}  # built on first use: a sweep touches one or two

    def fn(t: np.ndarray) -> np.ndarray:
        t = np.clip(np.atleast_1d(np.asarray(t, np.float64)), times[0], times[-1])
        if len(times) == 1:
            return np.broadcast_to(poses[0], (t.shape[0], 4, 4)).copy()
        i = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
        s = (t - times[i]) / (times[i + 1] - times[i])
        out = np.empty((t.shape[0], 4, 4))
        if np.all(i[1:] >= i[:-1]):  # times in order (a sweep's fire times): one slice per segment
            cuts = np.r_[0, np.nonzero(i[1:] != i[:-1])[0] + 1]
            ks = i[cuts]
            sels = [slice(a, b) for a, b in zip(cuts, np.r_[cuts[1:], len(i)])]
        else:
            ks = np.unique(i)
            sels = [i == k for k in ks]
        for k, sel in zip(ks.tolist(), sels):
            seg = segments.get(k)
            if seg is None:
                seg = segments[k] = SlerpSegment(poses[k], poses[k + 1])
            out[sel] = seg(s[sel])
        return out

    return fn


class TrajectorySource:
    """A recorded trajectory as a `PoseSource`: timestamps (T,) increasing seconds, poses
    (T, 4, 4) ego-to-world."""

    def __init__(self, times, poses, name: str = "trajectory"):
        times, poses = np.asarray(times, np.float64), np.asarray(poses, np.float64)
        if times.ndim != 1:
            raise InputError(f"{name}: times: expected shape (T,), got {times.shape}")
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            # (T, 3, 4) would reshape into wrong poses without a word when 12 T divides by 16
            raise InputError(f"{name}: poses: expected shape (T, 4, 4), got {poses.shape}")
        if times.shape[0] != poses.shape[0] or times.shape[0] < 1:
            raise InputError(f"{name}: need as many poses as timestamps (got {poses.shape[0]} and {times.shape[0]})")
        if np.any(np.diff(times) <= 0) or not np.all(np.isfinite(times)):
            raise InputError(f"{name}: timestamps must be finite and strictly increasing")
        for i, p in enumerate(poses):
            check_pose(p, f"{name}: pose {i}")
        self.times, self.poses, self.name = times, poses, name
        self._fn = track_pose_fn(times, poses)

    @property
    def t_start(self) -> float:
        return float(self.times[0])

    @property
    def t_end(self) -> float:
        return float(self.times[-1])

    def poses_at(self, times) -> np.ndarray:
        return self._fn(np.atleast_1d(np.asarray(times, np.float64)))

    def pose_at(self, t: float) -> np.ndarray:
        return self.poses_at(np.array([t]))[0]

    @classmethod
    def from_file(cls, path: str | Path, rate_hz: float = 10.0) -> "TrajectorySource":
        """Read poses: a KITTI pose file (12 numbers per line, row-major 3 x 4; times at
        `rate_hz` from 0), or an .npz with `times` (T,) and `poses` (T, 4, 4)."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such trajectory file")
        if path.suffix.lower() == ".npz":
            with np.load(path, allow_pickle=False) as z:
                for key in ("times", "poses"):
                    if key not in z.files:
                        raise InputError(f"{path}: missing key {key!r} (expected times (T,) and poses (T, 4, 4))")
                return cls(z["times"], z["poses"], str(path))
        try:
            rows = np.loadtxt(path, ndmin=2)
        except ValueError as exc:
            raise InputError(f"{path}: not a KITTI pose file ({exc})") from None
        if rows.shape[1] != 12:
            raise InputError(f"{path}: expected 12 numbers per line (KITTI 3 x 4 poses), got {rows.shape[1]}")
        poses = np.tile(np.eye(4), (rows.shape[0], 1, 1))
        poses[:, :3, :] = rows.reshape(-1, 3, 4)
        return cls(np.arange(rows.shape[0]) / rate_hz, poses, str(path))

    @classmethod
    def from_openscenario(cls, path: str | Path, entity: str | None = None) -> "TrajectorySource":
        """The ego's trajectory in an OpenSCENARIO (.xosc) file (`io.openscenario.read_openscenario`):
        linear in position, SLERP in rotation between vertices, held at the ends."""
        tr = read_openscenario(path, entity)
        return cls(tr.times, tr.poses, f"{tr.path} (entity {tr.entity})")


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * x)


class EditedTrajectory:
    """A counterfactual edit of a recorded trajectory, for replay at novel poses.

    The edited pose at time t is the base pose at ``base.t_start + (t - base.t_start) *
    speed_scale + time_shift`` moved `lateral_offset_m` to the left of the base's heading (its y
    axis; negative: to the right). With `lateral_ramp` = (t0, t1) the offset eases in from 0 at t0
    to its full value at t1 (a lane change); otherwise it applies throughout."""

    def __init__(self, base: PoseSource, *, lateral_offset_m: float = 0.0,
                 lateral_ramp: tuple[float, float] | None = None, speed_scale: float = 1.0, time_shift: float = 0.0):
        if not speed_scale > 0:
            raise InputError(f"speed_scale: expected > 0, got {speed_scale}")
        if lateral_ramp is not None and not lateral_ramp[1] > lateral_ramp[0]:
            raise InputError(f"lateral_ramp: expected (start, end) with end > start, got {lateral_ramp}")
        self.base = base
        self.lateral_offset_m = float(lateral_offset_m)
        self.lateral_ramp = lateral_ramp
        self.speed_scale = float(speed_scale)
        self.time_shift = float(time_shift)

    def _base_time(self, t):
        return self.base.t_start + (np.asarray(t, np.float64) - self.base.t_start) * self.speed_scale + self.time_shift

    @property
    def t_start(self) -> float:
        return self.base.t_start

    @property
    def t_end(self) -> float:
        return float(self.base.t_start + (self.base.t_end - self.base.t_start - self.time_shift) / self.speed_scale)

    def poses_at(self, times) -> np.ndarray:
        times = np.atleast_1d(np.asarray(times, np.float64))
        out = self.base.poses_at(self._base_time(times)).copy()
        w = np.ones_like(times) if self.lateral_ramp is None else _smoothstep(
            (times - self.lateral_ramp[0]) / (self.lateral_ramp[1] - self.lateral_ramp[0]))
        out[:, :3, 3] += (self.lateral_offset_m * w)[:, None] * out[:, :3, 1]
        return out

    def pose_at(self, t: float) -> np.ndarray:
        return self.poses_at(np.array([t]))[0]


class HeldPoses:
    """A pose source that stands still within each query: every time asked for in one call gets
    the base's pose at the call's last time. Asked for a sweep's fire times, it gives the pose at
    the sweep's end to every ray: motion distortion switched off."""

    def __init__(self, source: PoseSource):
        self.source = source
        self.t_start, self.t_end = source.t_start, source.t_end

    def poses_at(self, times) -> np.ndarray:
        times = np.atleast_1d(np.asarray(times, np.float64))
        return np.broadcast_to(self.source.poses_at(times[-1:])[0], (times.shape[0], 4, 4)).copy()
