"""Ego poses dead-reckoned from a vehicle's CAN traffic, from a live bus or a log file.

`CanPoseSource` feeds a `vehicle.DeadReckoner` from python-can messages decoded by a
`dbc.CanVehicleDecoder` (optionally paced in real time) and answers `pose_at(t)`;
`CanTrajectory` presents it as a simulator `PoseSource`. Times are seconds on the source's
clock (the window's start = 0); poses (4, 4) float64 rear-axle-to-world.
python-can is imported where a bus or a log is opened (slow to import).
"""

from __future__ import annotations

import queue
import struct
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from ...errors import InputError, ScubeSimWarning
from ..vehicle import DeadReckoner
from .dbc import CanVehicleDecoder

# A log's timestamps may run back a little across channels (loggers stamp per interface); more than
# this is a jump. Forward: no message for GAP_S on a bus that carries speed at 50-100 Hz is a gap.
BACKWARD_TOLERANCE_S = 1e-3
GAP_S = 1.0


def _can():
    """python-can, imported on first use: `scube_sim.sim` imports this module; only an opened bus or log needs it."""
    import can

    return can


@dataclass
class TimeJumps:
    """Timestamp faults met while reading a log: `backward` messages stamped more than
    `BACKWARD_TOLERANCE_S` before an earlier message (skipped; the largest step back
    `max_back_s`), forward `gaps` over `GAP_S` (bridged by the dead reckoning at the last speed
    and steering; the largest `max_gap_s`, starting at source time `gap_at`), whether the window's
    end fell inside a gap (`ends_in_gap`), and the span of source time the messages used cover."""

    backward: int = 0
    max_back_s: float = 0.0
    gaps: int = 0
    max_gap_s: float = 0.0
    gap_at: float = 0.0
    ends_in_gap: bool = False
    used: tuple[float, float] | None = None

    def __bool__(self) -> bool:
        return bool(self.backward or self.gaps or self.ends_in_gap)


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
            raise InputError(f"CAN window: stop ({stop}) must be after start ({start})")
        if start < 0:
            raise InputError(f"CAN window: start ({start}) must be >= 0 (seconds after the first message)")
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
        self.jumps = TimeJumps()  # timestamp faults of the log (from_log), reported as a warning
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
            raise InputError(f"replay speed must be > 0, got {speed}")
        if decoder is None:
            if dbc is None:
                raise InputError("CanPoseSource.from_log: give a dbc or a decoder")
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
            self._warn_jumps()
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
                raise InputError("CanPoseSource.from_bus: give a dbc or a decoder")
            decoder = CanVehicleDecoder(dbc, channels=channels)
        self = cls(decoder, reckoner, start=start, stop=stop, name="CAN bus")
        if isinstance(bus, dict):
            self._bus = _can().Bus(**bus)
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
        can = _can()

        n, last_t, newest = 0, None, None
        jumps = self.jumps = TimeJumps()
        try:
            reader = can.LogReader(str(path))
        except ValueError as exc:
            raise InputError(f"CAN log {path}: cannot read it: {exc}") from exc
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
                    raise InputError(f"CAN log {path}: malformed {where}: "
                                     f"{type(exc).__name__}: {exc}") from exc
                n += 1
                last_t = ts = float(msg.timestamp)
                if self.log_start is None:
                    self.log_start = ts
                    self.time_offset = self.log_start + self.start
                if newest is not None and ts < newest - BACKWARD_TOLERANCE_S:
                    jumps.backward += 1  # the reckoner integrates forward in time only
                    jumps.max_back_s = max(jumps.max_back_s, newest - ts)
                    continue
                gap = 0.0 if newest is None else ts - newest
                newest = ts if newest is None else max(newest, ts)
                rel = ts - self.log_start
                if gap > GAP_S and rel - gap >= self.start:
                    jumps.gaps += 1
                    if gap > jumps.max_gap_s:
                        jumps.max_gap_s, jumps.gap_at = gap, rel - gap - self.start
                    if self.stop is not None and rel >= self.stop:
                        jumps.ends_in_gap = True
                if self.stop is not None and rel >= self.stop:
                    break
                if rel < self.start or not self.decoder.accepts(msg):
                    continue
                t = rel - self.start
                jumps.used = (t, t) if jumps.used is None else (jumps.used[0], t)
                yield msg
        finally:
            stop = getattr(reader, "stop", None)
            if stop is not None:
                stop()
        if n == 0:
            raise InputError(f"CAN log {path}: contains no CAN messages")

    def _warn_jumps(self) -> None:
        """One warning naming the log and counting its timestamp faults (see `TimeJumps`)."""
        j = self.jumps
        if not j:
            return
        parts = []
        if j.backward:
            parts.append(f"{j.backward} messages stamped before an earlier one (up to {j.max_back_s:.3g} s back) "
                         f"skipped")
        if j.gaps:
            parts.append(f"{j.gaps} forward jumps over {GAP_S:g} s (largest {j.max_gap_s:.3g} s, at t = "
                         f"{j.gap_at:.3f} s) bridged at the last speed and steering"
                         + ("; the window ends inside one" if j.ends_in_gap else ""))
        used = "no messages" if j.used is None else f"t = {j.used[0]:.3f} to {j.used[1]:.3f} s"
        stop = "end" if self.stop is None else f"{self.stop - self.start:g} s"
        warnings.warn(f"CAN log {self.path}: timestamps jump: {'; '.join(parts)}; the trajectory uses messages over "
                      f"{used} of the window (0 to {stop})", ScubeSimWarning, stacklevel=3)

    def _replay(self) -> None:
        can = _can()

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
            raise InputError(f"{self.name}: no usable speed and steering/yaw-rate messages (ids {ids}, "
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
                    self._warn_jumps()
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
        return self.reckoner.last_time


class CanTrajectory:
    """A `CanPoseSource` as a `PoseSource` over [0, duration] seconds of source time. A log read at
    once answers at once; with `realtime`, asking for a pose waits until the replayed messages
    have reached that time."""

    def __init__(self, can_source: CanPoseSource, duration: float):
        self.can = can_source
        self.t_start, self.t_end = 0.0, float(duration)

    def poses_at(self, times) -> np.ndarray:
        times = np.atleast_1d(np.asarray(times, np.float64))
        while self.can.realtime and not self.can.finished and self.can.duration < times.max():
            self.can.poll()
            time.sleep(0.002)
        return np.asarray(self.can.pose_at(times)).reshape(-1, 4, 4)
