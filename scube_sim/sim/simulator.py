"""`Simulator`: the plugin's outside face, tick by tick.

Host-driven: the host owns time and pose and calls `step(t, ego_pose)` (or gives `ego_velocity`,
a constant twist over the tick); the simulator returns a `Frame` with every sweep that finished in
(previous tick, t]. Self-driven: `run(source, ...)` ticks through a `PoseSource` and yields frames.
Each LiDAR sweeps on its own grid: sweep k of a sensor covers
[t0 + phase + (k - 1) / rate, t0 + phase + k / rate] (t0 = the first tick), and the sweep's
timestamp is that end. The ego pose inside a sweep comes from the pose source (self-driven), or is
interpolated between the previous tick's pose and this one (host-driven; extrapolated with the
last motion when a sweep starts before the previous tick). Sinks run behind a bounded queue on a
writer thread (`sinks.SinkRunner`); `close()` — also called on Ctrl-C or any exception inside
`with Simulator(...)` or `run()` — writes every completed frame and finalises the files.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator

import numpy as np
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from ..errors import InputError
from ..lidar.config import LidarConfig
from ..lidar.model import Lidar
from ..transforms import PoseFn, check_pose, interpolate_poses, quat_to_rotmat
from .contracts import PoseSource, SimulatedScene
from .frame import Frame, SensorFrame
from .scene import as_simulated_scene
from .sinks.base import RunInfo, Sink, SinkRunner


@dataclass
class LidarSensor:
    """A LiDAR on the rig: its model, name, rate (default: the pattern's own) and mount
    (sensor-to-ego (4, 4); default: the config's `mount`). phase: seconds by which its sweep grid
    is shifted against the first tick."""

    lidar: Lidar
    name: str = ""
    rate_hz: float | None = None
    mount: np.ndarray | None = None
    phase: float = 0.0

    @classmethod
    def from_config(cls, cfg: LidarConfig, name: str | None = None, **kw) -> "LidarSensor":
        return cls(Lidar(cfg), name or cfg.id or cfg.name, **kw)

    def __post_init__(self):
        self.name = self.name or (self.lidar.config.id or self.lidar.config.name)
        self.rate_hz = float(self.rate_hz or 1.0 / self.lidar.pattern.period_s)
        if self.rate_hz * self.lidar.pattern.period_s > 1.0 + 1e-9:
            raise InputError(f"{self.name}: rate {self.rate_hz:g} Hz would overlap sweeps of "
                             f"{self.lidar.pattern.period_s:g} s; change the pattern's rotation rate instead")
        self.mount = self.lidar.mount if self.mount is None else check_pose(self.mount, f"{self.name}: mount")


@dataclass
class _SensorState:
    next_k: int = 1  # index of the next sweep to produce


@dataclass
class _History:
    times: list = field(default_factory=list)
    poses: list = field(default_factory=list)


def _twist_poses(pose_end: np.ndarray, t_end: float, velocity, times: np.ndarray) -> np.ndarray:
    """Poses at `times` of a body that moves with constant twist `velocity` = (vx, vy, vz, wx, wy,
    wz) (metres/s and rad/s, ego frame) and is at `pose_end` at `t_end`: pose_end @ delta(t - t_end),
    delta = rotation by w (t - t_end) about w's axis, translation v (t - t_end) (first order, in the
    ego frame). All times at once: a sweep asks for tens of thousands."""
    v = np.asarray(velocity, np.float64).reshape(6)
    dt = np.atleast_1d(np.asarray(times, np.float64)) - t_end
    delta = np.zeros((dt.shape[0], 4, 4))
    w = v[3:]
    ang = np.linalg.norm(w)
    if ang > 1e-12:
        half = 0.5 * ang * dt
        q = np.concatenate([np.cos(half)[:, None], np.sin(half)[:, None] * (w / ang)], axis=1)
        delta[:, :3, :3] = quat_to_rotmat(q)
    else:
        delta[:, :3, :3] = np.eye(3)
    delta[:, :3, 3] = v[:3] * dt[:, None]
    delta[:, 3, 3] = 1.0
    return np.einsum("ij,njk->nik", pose_end, delta)  # einsum, not `@`: no BLAS threads


class Simulator:
    """Sensors on an ego in a scene, stepping in time.

    scene: a `SimulatedScene` (e.g. a `SimScene`: static parts, actors, chunks), or a plain
    `TraceableScene` (a Tracer, a list of tracers), held as a `StaticScene`.
    sensors: `LidarSensor`s. sinks: `Sink`s fed behind a bounded queue of `queue_size` frames.
    seed: the run's seed; each sweep draws from (seed, sensor index, sweep index), so a run is
    reproducible and does not depend on the order of ticks within it."""

    def __init__(self, scene, sensors: list[LidarSensor], sinks: list[Sink] | None = None, *, seed: int = 0,
                 queue_size: int = 8, run_info: RunInfo | None = None):
        if not sensors:
            raise InputError("Simulator: give at least one sensor")
        names = [s.name for s in sensors]
        if len(set(names)) != len(names):
            raise InputError(f"Simulator: sensor names must be unique, got {names}")
        self.scene: SimulatedScene = as_simulated_scene(scene)
        self.sensors = list(sensors)
        self.sinks = list(sinks or [])
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise InputError(f"seed: expected a non-negative integer, got {seed!r}")
        self.seed = int(seed)
        self.queue_size = int(queue_size)
        self.run_info = run_info or RunInfo()
        self._runner: SinkRunner | None = None
        self.reset()

    # --- lifecycle ---------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the past: the next step is tick 0 again (sinks stay open)."""
        self._t0: float | None = None
        self._tick = 0
        self._state = {s.name: _SensorState() for s in self.sensors}
        self._hist = _History()
        self._velocity = None

    def _ensure_runner(self, t0: float) -> None:
        if self._runner is None and self.sinks:
            info = self.run_info
            info.start_time = t0
            info.sensors = {s.name: {"kind": "lidar", "rate_hz": s.rate_hz, "sensor": s.lidar.config.name,
                                     "channels": s.lidar.config.channels, "mount": s.mount.tolist()}
                            for s in self.sensors}
            self._runner = SinkRunner(self.sinks, info, self.queue_size)
            self._runner.start()

    def close(self) -> None:
        """Write every queued frame and close the sinks (idempotent)."""
        if self._runner is not None:
            runner, self._runner = self._runner, None
            runner.close()

    def __enter__(self) -> "Simulator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- stepping ----------------------------------------------------------------------------
    def step(self, t: float, ego_pose: np.ndarray | None = None, ego_velocity=None, *,
             pose_fn: PoseFn | None = None) -> Frame:
        """Advance to time t (seconds, increasing). ego_pose: ego-to-world at t (host-driven);
        ego_velocity: (vx, vy, vz, wx, wy, wz) ego-frame twist, used for motion inside sweeps
        instead of the previous tick's pose (and to advance the pose when `ego_pose` is None);
        pose_fn: times -> (N, 4, 4) ego poses (self-driven runs pass their source)."""
        t = float(t)
        if not np.isfinite(t):
            raise InputError("step: t is not finite")
        if self._hist.times and t <= self._hist.times[-1]:
            raise InputError(f"step: time must increase (got {t} after {self._hist.times[-1]})")
        if ego_pose is None:
            if pose_fn is not None:
                ego_pose = pose_fn(np.array([t]))[0]
            elif ego_velocity is not None and self._hist.poses:
                ego_pose = _twist_poses(self._hist.poses[-1], self._hist.times[-1], ego_velocity, np.array([t]))[0]
            else:
                raise InputError("step: give ego_pose (or ego_velocity after the first tick, or pose_fn)")
        ego_pose = check_pose(ego_pose, "ego_pose")
        if self._t0 is None:
            self._t0 = t
            self._ensure_runner(t)
        self._velocity = ego_velocity
        self._hist.times.append(t)
        self._hist.poses.append(ego_pose)
        if len(self._hist.times) > 2:
            self._hist.times.pop(0)
            self._hist.poses.pop(0)
        ego_fn = pose_fn or self._interpolated_ego(ego_velocity)
        self.scene.update(t, ego_pose[:3, 3])
        frame = Frame(self._tick, t, ego_pose)
        for si, sensor in enumerate(self.sensors):
            sweeps = self._sweeps_until(si, sensor, t, ego_fn)
            if sweeps:
                frame.sensors[sensor.name] = sweeps
        frame.boxes = self.scene.boxes_at(t)
        self._tick += 1
        if self._runner is not None:
            self._runner.put(frame)
        return frame

    def _interpolated_ego(self, velocity) -> PoseFn:
        times, poses = list(self._hist.times), list(self._hist.poses)

        def fn(ts: np.ndarray) -> np.ndarray:
            ts = np.atleast_1d(np.asarray(ts, np.float64))
            if velocity is not None or len(times) == 1:
                if velocity is None:
                    return np.broadcast_to(poses[-1], (ts.shape[0], 4, 4)).copy()
                return _twist_poses(poses[-1], times[-1], velocity, ts)
            s = (ts - times[0]) / (times[1] - times[0])  # < 0: extrapolate back with the last motion
            return interpolate_poses(poses[0], poses[1], s)

        return fn

    def _sweeps_until(self, si: int, sensor: LidarSensor, t: float, ego_fn: PoseFn) -> list[SensorFrame]:
        st = self._state[sensor.name]
        period = 1.0 / sensor.rate_hz
        out = []
        while True:
            t_end = self._t0 + sensor.phase + st.next_k * period
            if t_end > t + 1e-9:
                break
            t_start = t_end - sensor.lidar.pattern.period_s

            def sensor_fn(ts, mount=sensor.mount):
                return ego_fn(ts) @ mount

            seed = int(np.random.SeedSequence([self.seed, si, st.next_k]).generate_state(1)[0])
            self.scene.time = t_end
            sweep = sensor.lidar.scan(self.scene, None, pose_fn=sensor_fn, t_start=t_start, seed=seed)
            out.append(SensorFrame(sensor.name, "lidar", sweep.points, sweep.t_start, sweep.t_end,
                                   t_start if sensor.lidar.config.motion.reference == "start" else sweep.t_end,
                                   sweep.pose_reference, sweep.pose_start, sweep.pose_end, st.next_k))
            st.next_k += 1
        return out

    def run(self, source: PoseSource, *, t_start: float | None = None, t_end: float | None = None, dt: float = 0.1,
            progress: bool = False) -> Iterator[Frame]:
        """Tick through a pose source every `dt` seconds from t_start to t_end (default: the
        source's span) and yield each frame. Closes the sinks when done or interrupted."""
        t0 = source.t_start if t_start is None else float(t_start)
        t1 = source.t_end if t_end is None else float(t_end)
        n = int(np.floor((t1 - t0) / dt + 1e-9)) + 1
        bar = task = None
        if progress:
            bar = Progress(TextColumn("[bold]ticks"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                           TimeElapsedColumn(), TimeRemainingColumn())
            bar.start()
            task = bar.add_task("ticks", total=n)
        try:
            for i in range(n):
                t = t0 + i * dt
                yield self.step(t, pose_fn=source.poses_at)
                if bar:
                    bar.advance(task)
        finally:
            if bar:
                bar.stop()
            self.close()
