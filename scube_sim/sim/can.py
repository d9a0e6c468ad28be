"""CAN bus in the loop: ego motion from a vehicle's CAN traffic, and "frame ready" messages out.

- `CanVehicleDecoder` turns python-can `Message`s into speed / steering-wheel angle / yaw-rate
  samples with a cantools DBC (message and signal names configurable; defaults: the 2017 Toyota
  RAV4 powertrain DBC of opendbc).
- `DeadReckoner` integrates those samples with a kinematic bicycle model into planar poses.
- `CanPoseSource` feeds a `DeadReckoner` from a live python-can bus or a CAN log file (optionally
  paced in real time) and answers `pose_at(t)` like any other pose source of the simulator.
- `CanFrameSink` is a simulator `Sink` that announces every finished frame on a CAN bus.

Units: seconds, metres, m/s, radians unless a name says `_deg`. Poses are (4, 4) float64
ego-to-world (`transforms` conventions: x forward, y left, z up). The dead-reckoned pose is the
**rear-axle centre** (the reference point of the kinematic bicycle model); compose a mount
transform to get a sensor pose.

RAV4 parameters (`RAV4_WHEELBASE`, `RAV4_STEER_RATIO`): the 2017 RAV4's wheelbase is 2.66 m
(2 660 mm, manufacturer spec; openpilot uses 2.65) and the steering ratio 15.7 is a nominal
*low-speed* value (openpilot's tuned value is 16.88, its comment quotes 14.5 end-to-end). On the
comma2k19 RAV4 log (highway, 17 m/s, steering-wheel angles within +-5 deg) the ratio that best
maps the steering angle to the ground-truth yaw rate is 22-34 (an *effective* ratio that absorbs
understeer at speed; poorly conditioned there), and the position drift is dominated instead by
the steering sensor's zero offset (about -0.15 deg) and the wheel-speed scale (the wheels read
0.85 % slow). Those two are `steer_offset_deg` and `speed_scale` (defaults 0 and 1: nominal,
uncalibrated); `calibrate_bicycle` estimates them against a reference trajectory, and
`tools/can_drift.py` prints the numbers.
"""

from __future__ import annotations

import math
import os
import queue
import struct
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from ..transforms import check_pose, interpolate_poses
from .frame import Frame
from .sinks import RunInfo, Sink

RAV4_WHEELBASE = 2.66  # m
RAV4_STEER_RATIO = 15.7  # steering-wheel angle / road-wheel angle, nominal

#: Defaults for opendbc's ``toyota_rav4_2017_pt_generated.dbc``: WHEEL_SPEEDS (0xAA, km/h, mean
#: of the four wheels) and STEER_ANGLE_SENSOR (0x25, deg, STEER_ANGLE + STEER_FRACTION). The DBC
#: also has KINEMATICS (0x24) YAW_RATE, marked "verify" in the DBC: on the comma2k19 log it is
#: biased by -0.4 deg/s and barely correlated with the true yaw rate, so it is not used.
RAV4_SPEED = ("WHEEL_SPEEDS", ("WHEEL_SPEED_FL", "WHEEL_SPEED_FR", "WHEEL_SPEED_RL", "WHEEL_SPEED_RR"))
RAV4_STEER = ("STEER_ANGLE_SENSOR", ("STEER_ANGLE", "STEER_FRACTION"))

_SPEED_UNITS = {"km/h": 1 / 3.6, "kph": 1 / 3.6, "kmh": 1 / 3.6, "kmph": 1 / 3.6, "m/s": 1.0,
                "mps": 1.0, "mph": 0.44704}
_ANGLE_UNITS = {"deg": 1.0, "degree": 1.0, "degrees": 1.0, "°": 1.0, "rad": 180.0 / math.pi}
_RATE_UNITS = {"deg/s": math.pi / 180.0, "°/s": math.pi / 180.0, "rad/s": 1.0}


# ----------------------------------------------------------------------------------- decoding


@dataclass(frozen=True)
class VehicleSample:
    """One decoded message: timestamp (s, the message's clock), and whichever of speed (m/s),
    steering-wheel angle (deg, positive = left) and yaw rate (rad/s, positive = left) it holds."""

    t: float
    speed: float | None = None
    steer_deg: float | None = None
    yaw_rate: float | None = None


def _load_dbc(dbc):
    """A cantools Database and a name for messages: path -> (db, path); Database -> (db, label)."""
    import cantools

    if isinstance(dbc, (str, os.PathLike)):
        path = Path(dbc)
        if not path.is_file():
            raise FileNotFoundError(f"DBC file {path} does not exist")
        try:
            return cantools.database.load_file(str(path)), str(path)
        except Exception as exc:  # noqa: BLE001 - cantools raises many kinds
            raise ValueError(f"DBC file {path}: cannot parse it: {exc}") from exc
    if hasattr(dbc, "get_message_by_name"):
        return dbc, getattr(dbc, "_scube_name", "<in-memory DBC>")
    raise TypeError(f"dbc must be a path or a cantools Database, got {type(dbc).__name__}")


def _lookup(db, dbc_name: str, message, signals, role: str):
    """(cantools Message, [Signal]) for a message name / frame id and signal names, or ValueError
    naming the DBC and what is missing."""
    try:
        msg = db.get_message_by_frame_id(int(message)) if isinstance(message, int) else \
            db.get_message_by_name(str(message))
    except KeyError:
        what = f"0x{message:X}" if isinstance(message, int) else repr(message)
        raise ValueError(f"DBC {dbc_name}: no message {what} (needed for {role})") from None
    names = [signals] if isinstance(signals, str) else list(signals)
    if not names:
        raise ValueError(f"{role}: no signal names given for message {msg.name}")
    have = {s.name: s for s in msg.signals}
    missing = [n for n in names if n not in have]
    if missing:
        raise ValueError(f"DBC {dbc_name}: message {msg.name} (0x{msg.frame_id:X}) has no signal "
                         f"{', '.join(repr(m) for m in missing)} (needed for {role}); it has "
                         f"{sorted(have)}")
    return msg, [have[n] for n in names]


def _unit_factor(table: dict, signals, override, role: str, dbc_name: str) -> float:
    if override is not None:
        return float(override)
    units = {(s.unit or "").strip().lower() for s in signals}
    if len(units) != 1 or next(iter(units)) not in table:
        raise ValueError(f"DBC {dbc_name}: {role} signals {[s.name for s in signals]} have unit(s) "
                         f"{sorted(units)}; known: {sorted(table)} - pass an explicit scale")
    return table[next(iter(units))]


class CanVehicleDecoder:
    """Decodes ego speed, steering-wheel angle and/or yaw rate from CAN messages with a DBC.

    dbc: a .dbc path or a cantools Database. speed / steer / yaw_rate: ``(message, signals)``
    with the message's DBC name (or frame id) and one signal name or several; several speed
    signals are **averaged** (e.g. four wheel speeds), several steering or yaw-rate signals are
    **summed** (e.g. a coarse angle plus its fraction). None disables that quantity.
    Units come from the DBC (km/h, m/s, mph; deg, rad; deg/s, rad/s) unless a ``*_scale`` is
    given, which multiplies the physical DBC value to give m/s, deg or rad/s.
    channels: accept only messages whose `Message.channel` is in it (e.g. ``("can0",)``, for
    multi-bus logs); None accepts every channel.

    A name missing from the DBC raises ValueError naming the DBC file and the name. A frame that
    does not decode (wrong length, ...) is skipped and counted in `decode_errors`.
    """

    def __init__(self, dbc, speed=RAV4_SPEED, steer=RAV4_STEER, yaw_rate=None, *,
                 speed_scale: float | None = None, steer_scale: float | None = None,
                 yaw_rate_scale: float | None = None, channels: Iterable[str] | None = None):
        self.db, self.dbc_name = _load_dbc(dbc)
        self.channels = None if channels is None else frozenset(
            [channels] if isinstance(channels, str) else channels)
        self.decode_errors = 0
        # frame id -> list of (kind, cantools message, signal names, factor, reduce)
        self._routes: dict[int, list] = {}
        self.has_speed = speed is not None
        self.has_steer = steer is not None
        self.has_yaw_rate = yaw_rate is not None
        if not (self.has_speed and (self.has_steer or self.has_yaw_rate)):
            raise ValueError("CanVehicleDecoder needs speed and at least one of steer / yaw_rate")
        for kind, spec, table, scale, reduce in (
                ("speed", speed, _SPEED_UNITS, speed_scale, "mean"),
                ("steer_deg", steer, _ANGLE_UNITS, steer_scale, "sum"),
                ("yaw_rate", yaw_rate, _RATE_UNITS, yaw_rate_scale, "sum")):
            if spec is None:
                continue
            message, names = spec
            msg, sigs = _lookup(self.db, self.dbc_name, message, names, kind)
            factor = _unit_factor(table, sigs, scale, kind, self.dbc_name)
            self._routes.setdefault(msg.frame_id, []).append(
                (kind, msg, [s.name for s in sigs], factor, reduce))

    @property
    def frame_ids(self) -> frozenset[int]:
        """Arbitration ids this decoder reads (for cheap pre-filtering)."""
        return frozenset(self._routes)

    def accepts(self, msg) -> bool:
        """True when `msg` is on an accepted channel and has an id this decoder reads."""
        if msg.arbitration_id not in self._routes or msg.is_error_frame or msg.is_remote_frame:
            return False
        return self.channels is None or msg.channel in self.channels

    def decode(self, msg) -> VehicleSample | None:
        """A `VehicleSample` for a relevant message, else None (other id / channel, bad frame)."""
        if not self.accepts(msg):
            return None
        routes = self._routes[msg.arbitration_id]
        if bool(msg.is_extended_id) != bool(routes[0][1].is_extended_frame):
            return None
        try:
            values = routes[0][1].decode(bytes(msg.data), decode_choices=False, scaling=True)
        except Exception:  # noqa: BLE001 - a corrupt frame must not stop a live source
            self.decode_errors += 1
            return None
        out = {}
        for kind, _m, names, factor, reduce in routes:
            vals = [float(values[n]) for n in names]
            v = sum(vals) / len(vals) if reduce == "mean" else sum(vals)
            out[kind] = v * factor
        return VehicleSample(t=float(msg.timestamp), **out)


# ------------------------------------------------------------------------------ dead reckoning


def _planar_pose(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0, x], [s, c, 0.0, y], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


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
            raise ValueError("wheelbase, steer_ratio and speed_scale must be > 0")
        if yaw_source not in ("steering", "yaw_rate"):
            raise ValueError(f"yaw_source must be 'steering' or 'yaw_rate', got {yaw_source!r}")
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
            raise ValueError("calibrate_bicycle: the fitted steering gain is not positive; the "
                             "reference has too little turning")
        return float(1.0 / k), float(np.degrees(c / k))
    k = 1.0 / float(steer_ratio)
    # w = k a + k sw0 b  ->  least squares for sw0
    off = float(np.dot(b * k, w - k * a) / np.dot(b * k, b * k))
    return float(steer_ratio), float(np.degrees(off))


# --------------------------------------------------------------------------------- pose source


class _Paced:
    """A message with its timestamp scaled for `can.MessageSync` (which only reads .timestamp)."""

    __slots__ = ("timestamp", "msg")

    def __init__(self, timestamp, msg):
        self.timestamp = timestamp
        self.msg = msg


class CanPoseSource:
    """Ego poses dead-reckoned from CAN: from a python-can bus or a CAN log file.

    Build with `from_log` or `from_bus`. Times: the source's clock is the message timestamps
    shifted so that the window start is 0 (``t_source = timestamp - time_offset``;
    `time_offset` is kept). The window is [start, stop) seconds after the **first message** of
    the log / the first message received from the bus (any id); stop None = open-ended.

    Reading: a log without pacing is read whole on construction. With ``realtime=True`` a
    thread replays the window through `can.MessageSync` at `speed` x real time, and `poll()`
    takes in what has been replayed so far (`wait()` blocks until the replay is done). A bus is
    read by `poll()`, non-blocking: it takes what is queued and returns. `pose_at`, `times`,
    `poses()`, `velocity_at` answer from what has been taken in.
    """

    def __init__(self, decoder: CanVehicleDecoder, reckoner: DeadReckoner | None = None, *,
                 start: float = 0.0, stop: float | None = None, name: str = "CAN"):
        if stop is not None and stop <= start:
            raise ValueError(f"CAN window: stop ({stop}) must be after start ({start})")
        if start < 0:
            raise ValueError(f"CAN window: start ({start}) must be >= 0 (seconds after the first message)")
        self.decoder = decoder
        if reckoner is None:
            yaw_source = "yaw_rate" if decoder.has_yaw_rate and not decoder.has_steer else "steering"
            reckoner = DeadReckoner(yaw_source=yaw_source)
        self.reckoner = reckoner
        self.start = float(start)
        self.stop = None if stop is None else float(stop)
        self.name = name
        self.log_start: float | None = None  # timestamp of the first message seen
        self.time_offset: float | None = None  # timestamp at source time 0
        self.messages = 0  # messages taken into the reckoner (in window, decoded)
        self.finished = False  # the window's end was reached (log) / stop passed (bus)
        self.path: Path | None = None  # the log file (from_log)
        self.realtime = False
        self.speed = 1.0
        self._bus = None
        self._owns_bus = False
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._stop_event = threading.Event()

    # -- construction
    @classmethod
    def from_log(cls, path, dbc=None, *, decoder: CanVehicleDecoder | None = None,
                 reckoner: DeadReckoner | None = None, start: float = 0.0,
                 stop: float | None = 20.0, channels=("can0",), realtime: bool = False,
                 speed: float = 1.0) -> "CanPoseSource":
        """From a log `can.LogReader` reads (.log candump, .asc, .blf, .csv, .trc, ... and their
        .gz). Give a `dbc` (path / Database; RAV4 signal defaults, `channels` filter) or a ready
        `decoder`. Default window: the first 20 s. realtime: replay paced with
        `can.MessageSync` at `speed` x (call `poll()` / `wait()`); else read now.
        Errors name the file: FileNotFoundError (missing), ValueError (unreadable / malformed /
        no usable message in the window)."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"CAN log {path} does not exist")
        if speed <= 0:
            raise ValueError(f"replay speed must be > 0, got {speed}")
        if decoder is None:
            if dbc is None:
                raise ValueError("CanPoseSource.from_log: give a dbc or a decoder")
            decoder = CanVehicleDecoder(dbc, channels=channels)
        self = cls(decoder, reckoner, start=start, stop=stop, name=str(path))
        self.path = path
        self.realtime = bool(realtime)
        self.speed = float(speed)
        if not realtime:
            for msg in self._window(path):
                self._take(msg)
            self.finished = True
            self._check_nonempty()
        else:
            self._queue = queue.Queue()
            self._thread = threading.Thread(target=self._replay, name="scube-can-replay", daemon=True)
            self._thread.start()
        return self

    @classmethod
    def from_bus(cls, bus, dbc=None, *, decoder: CanVehicleDecoder | None = None,
                 reckoner: DeadReckoner | None = None, start: float = 0.0,
                 stop: float | None = None, channels=None) -> "CanPoseSource":
        """From a python-can bus object, or a dict of `can.Bus` keyword arguments
        (e.g. ``{"interface": "socketcan", "channel": "can0"}``; the source then owns and shuts it
        down in `close()`). Read with `poll()`."""
        if decoder is None:
            if dbc is None:
                raise ValueError("CanPoseSource.from_bus: give a dbc or a decoder")
            decoder = CanVehicleDecoder(dbc, channels=channels)
        self = cls(decoder, reckoner, start=start, stop=stop, name="CAN bus")
        if isinstance(bus, dict):
            import can

            self._bus = can.Bus(**bus)
            self._owns_bus = True
            self.name = f"CAN bus {bus.get('interface', '?')}:{bus.get('channel', '?')}"
        else:
            self._bus = bus
            self.name = f"CAN bus {getattr(bus, 'channel_info', bus)}"
        return self

    # -- reading
    def _window(self, path: Path) -> Iterator:
        """The log's messages inside the window that the decoder reads (assumes a time-ordered
        log, as candump / ASC / BLF loggers write; reading stops at the window's end)."""
        import can

        n, last_t = 0, None
        try:
            reader = can.LogReader(str(path))
        except ValueError as exc:
            raise ValueError(f"CAN log {path}: cannot read it: {exc}") from exc
        try:
            it = iter(reader)
            while True:
                try:
                    msg = next(it)
                except StopIteration:
                    break
                except (ValueError, IndexError, KeyError, OSError, EOFError, UnicodeDecodeError,
                        struct.error) as exc:
                    where = "before the first message" if last_t is None else \
                        f"after message {n} (t={last_t:.6f})"
                    raise ValueError(f"CAN log {path}: malformed {where}: "
                                     f"{type(exc).__name__}: {exc}") from exc
                n += 1
                last_t = msg.timestamp
                if self.log_start is None:
                    self.log_start = float(msg.timestamp)
                    self.time_offset = self.log_start + self.start
                rel = msg.timestamp - self.log_start
                if self.stop is not None and rel >= self.stop:
                    break
                if rel < self.start or not self.decoder.accepts(msg):
                    continue
                yield msg
        finally:
            stop = getattr(reader, "stop", None)
            if stop is not None:
                stop()
        if n == 0:
            raise ValueError(f"CAN log {path}: contains no CAN messages")

    def _replay(self) -> None:
        import can

        try:
            # MessageSync sleeps by timestamp differences: compress them by `speed`
            paced = (_Paced((m.timestamp - self.time_offset) / self.speed, m) for m in self._window(self.path))
            for item in can.MessageSync(paced, timestamps=True, skip=3600.0):
                if self._stop_event.is_set():
                    return
                self._queue.put(item.msg)
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
            self._error = exc
        finally:
            self._queue.put(None)

    def _take(self, msg) -> bool:
        sample = self.decoder.decode(msg)
        if sample is None:
            return False
        self.reckoner.update(sample.t - self.time_offset, speed=sample.speed,
                             steer_deg=sample.steer_deg, yaw_rate=sample.yaw_rate)
        self.messages += 1
        return True

    def _check_nonempty(self) -> None:
        if not self.reckoner.ready:
            chans = "any channel" if self.decoder.channels is None else sorted(self.decoder.channels)
            ids = ", ".join(f"0x{i:X}" for i in sorted(self.decoder.frame_ids))
            raise ValueError(f"{self.name}: no usable speed and steering/yaw-rate messages (ids {ids}, "
                             f"{chans}) in the window [{self.start}, {self.stop}) s after the first "
                             f"message; {self.messages} decoded")

    def poll(self, max_messages: int | None = None) -> int:
        """Take in what is available now, without blocking; returns the number of messages
        used. Re-raises a replay thread's error."""
        used = 0
        count = 0
        if self._queue is not None:
            while max_messages is None or count < max_messages:
                try:
                    msg = self._queue.get_nowait()
                except queue.Empty:
                    break
                if msg is None:
                    self.finished = True
                    self._queue = None
                    if self._error is not None:
                        raise self._error
                    self._check_nonempty()
                    break
                count += 1
                used += self._take(msg)
        elif self._bus is not None:
            while max_messages is None or count < max_messages:
                msg = self._bus.recv(timeout=0.0)
                if msg is None:
                    break
                count += 1
                if self.log_start is None:
                    self.log_start = float(msg.timestamp)
                    self.time_offset = self.log_start + self.start
                rel = msg.timestamp - self.log_start
                if rel < self.start:
                    continue
                if self.stop is not None and rel >= self.stop:
                    self.finished = True
                    continue
                used += self._take(msg)
        return used

    def wait(self, timeout: float | None = None) -> bool:
        """Paced log: block until the replay has finished (or `timeout` s), taking everything
        in. Returns `finished`."""
        if self._thread is not None:
            self._thread.join(timeout)
        self.poll()
        return self.finished

    def close(self) -> None:
        """Stop a replay thread; shut down a bus this source opened."""
        self._stop_event.set()
        if self._thread is not None and self._thread.is_alive():
            self._thread.join(5.0)
        if self._bus is not None and self._owns_bus:
            self._bus.shutdown()
        self._bus = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- poses
    @property
    def times(self) -> np.ndarray:
        """(N,) state times on the source clock (s, window start = 0)."""
        return self.reckoner.times

    def poses(self) -> np.ndarray:
        """(N, 4, 4) poses at `times`."""
        return self.reckoner.poses()

    def pose_at(self, t) -> np.ndarray:
        """Pose at source time(s) t: (4, 4) or (N, 4, 4); see `DeadReckoner.pose_at`."""
        return self.reckoner.pose_at(t)

    def velocity_at(self, t) -> np.ndarray:
        """World velocity (m/s) at source time(s) t."""
        return self.reckoner.velocity_at(t)

    @property
    def duration(self) -> float:
        """Source time of the last state taken in so far (s; 0 before any)."""
        return float(self.reckoner._arr("t")[-1]) if self.reckoner.ready else 0.0


# ------------------------------------------------------------------------------- frame-ready sink

FRAME_READY_ID = 0x5F0

#: The default "frame ready" layout as a DBC (load with ``cantools.database.load_string``).
#: 8 data bytes, little-endian (Intel): bytes 0-1 COUNTER uint16 (0, 1, 2, ... rolling over after
#: 65535), byte 2 SWEEPS uint8 (LiDAR sweeps in the frame, saturating at 255), byte 3 reserved
#: (0), bytes 4-7 TIME_MS uint32 (frame time in ms on the simulator clock, rounded, wrapping
#: after 2**32 ms = 49.7 days).
FRAME_READY_DBC = """VERSION ""

NS_ :

BS_:

BU_: SCUBE_SIM

BO_ 1520 SCUBE_FRAME_READY: 8 SCUBE_SIM
 SG_ COUNTER : 0|16@1+ (1,0) [0|65535] "" Vector__XXX
 SG_ SWEEPS : 16|8@1+ (1,0) [0|255] "" Vector__XXX
 SG_ RESERVED : 24|8@1+ (1,0) [0|255] "" Vector__XXX
 SG_ TIME_MS : 32|32@1+ (1,0) [0|4294967295] "ms" Vector__XXX

CM_ BO_ 1520 "scube_sim: one simulator frame is ready";
"""

_LAYOUT = struct.Struct("<HBBI")


def pack_frame_ready(counter: int, sweeps: int, time_ms: int) -> bytes:
    """8 bytes of the default layout (see `FRAME_READY_DBC`); counter and time wrap, sweeps
    saturate."""
    return _LAYOUT.pack(int(counter) & 0xFFFF, min(max(int(sweeps), 0), 255), 0,
                        int(time_ms) & 0xFFFFFFFF)


def unpack_frame_ready(data: bytes) -> tuple[int, int, int]:
    """(counter, sweeps, time_ms) from 8 bytes of the default layout."""
    counter, sweeps, _reserved, time_ms = _LAYOUT.unpack(bytes(data[:8]))
    return counter, sweeps, time_ms


class CanFrameSink(Sink):
    """Sends one "frame ready" CAN message per frame.

    Default layout: `FRAME_READY_DBC` / `pack_frame_ready` on `arbitration_id` (default 0x5F0,
    standard 11-bit id): rolling 16-bit counter from 0, number of LiDAR sweeps in the frame,
    frame time in ms. With `dbc` (path / Database) and `message` (name or frame id) the message
    is encoded by cantools instead, on the DBC's frame id; `signals` maps ``counter``,
    ``sweeps``, ``time_ms`` to signal names (default COUNTER, SWEEPS, TIME_MS); other signals
    of the message are sent as 0; counter and time wrap at the signals' widths.

    The bus: an existing python-can bus object (`bus`, not shut down by the sink), or
    `can.Bus(interface=..., channel=..., **bus_kwargs)` opened in `open()` and shut down in
    `close()`. A failed send raises (the `SinkRunner` then stops the run).
    """

    def __init__(self, bus=None, *, interface: str = "virtual", channel="vcan0",
                 arbitration_id: int = FRAME_READY_ID, is_extended_id: bool = False,
                 dbc=None, message=None, signals: dict | None = None,
                 send_timeout: float = 0.1, bus_kwargs: dict | None = None):
        self.bus = bus
        self._owns_bus = False
        self.interface = interface
        self.channel = channel
        self.bus_kwargs = dict(bus_kwargs or {})
        self.arbitration_id = int(arbitration_id)
        self.is_extended_id = bool(is_extended_id)
        self.send_timeout = send_timeout
        self.counter = 0
        self.sent = 0
        self._message = None
        if dbc is not None:
            if message is None:
                raise ValueError("CanFrameSink: with a dbc, name the message to encode")
            db, name = _load_dbc(dbc)
            sig = {"counter": "COUNTER", "sweeps": "SWEEPS", "time_ms": "TIME_MS", **(signals or {})}
            msg, sigs = _lookup(db, name, message, [sig["counter"], sig["sweeps"], sig["time_ms"]],
                                "the frame-ready message")
            self._message = msg
            self._signals = sig
            self._widths = {k: s.length for k, s in zip(("counter", "sweeps", "time_ms"), sigs)}
            self.arbitration_id = msg.frame_id
            self.is_extended_id = bool(msg.is_extended_frame)
        elif not (0 <= self.arbitration_id < (1 << (29 if self.is_extended_id else 11))):
            raise ValueError(f"CanFrameSink: arbitration id 0x{self.arbitration_id:X} out of range")

    def open(self, run: RunInfo | None = None) -> None:
        if self.bus is None:
            import can

            self.bus = can.Bus(interface=self.interface, channel=self.channel, **self.bus_kwargs)
            self._owns_bus = True
        self.counter = 0

    def payload(self, counter: int, sweeps: int, time_ms: int) -> bytes:
        """The data bytes for one frame."""
        if self._message is None:
            return pack_frame_ready(counter, sweeps, time_ms)
        w = self._widths
        values = {s.name: 0 for s in self._message.signals}
        values[self._signals["counter"]] = counter % (1 << w["counter"])
        values[self._signals["sweeps"]] = min(sweeps, (1 << w["sweeps"]) - 1)
        values[self._signals["time_ms"]] = time_ms % (1 << w["time_ms"])
        return self._message.encode(values, scaling=False, padding=True, strict=False)

    def write(self, frame: Frame) -> None:
        import can

        if self.bus is None:
            self.open(None)
        if not (frame.time >= 0):
            raise ValueError(f"CanFrameSink: frame time {frame.time} s is negative or NaN")
        sweeps = sum(1 for s in frame.sweeps() if s.kind == "lidar")
        time_ms = int(round(frame.time * 1000.0))
        data = self.payload(self.counter, sweeps, time_ms)
        self.bus.send(can.Message(arbitration_id=self.arbitration_id, is_extended_id=self.is_extended_id,
                                  data=data), timeout=self.send_timeout)
        self.counter = (self.counter + 1) & 0xFFFF
        self.sent += 1

    def close(self) -> None:
        if self.bus is not None and self._owns_bus:
            self.bus.shutdown()
            self.bus = None
            self._owns_bus = False
