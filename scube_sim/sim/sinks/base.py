"""Where frames go: the sink contract, and the writer thread that feeds sinks behind a bounded
queue.

A sink (`Sink`) has `open(run)`, `write(frame)` and `close()`. The simulator never calls sinks
itself: it puts frames into a `SinkRunner`, whose single writer thread calls every sink in order.
The queue is bounded, so a slow sink slows the loop down (back-pressure) and no frame is ever
dropped. A sink that raises stops the run: the error is re-raised in the loop at its next `put`
(or at `close`). `close()` — also on Ctrl-C or an exception in the host — writes every frame
already queued, then closes every sink, so each completed frame is on disk and files are
finalised. The sinks themselves are in `files`, `usd`, `can` and `inprocess`.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass, field

import numpy as np

from ...errors import ScubeSimError
from ..frame import Frame


@dataclass
class RunInfo:
    """What sinks may need to know when a run starts.

    sensors: name -> dict (kind, rate_hz, preset/config name, channels, mount (4, 4)); scene:
    the static scene object (VoxSplat / Gaussians / TriangleMesh) or None; origin: float64 world
    offset of the scene's local frame; time_codes_per_second: the USD time base; metadata: free."""

    sensors: dict = field(default_factory=dict)
    scene: object | None = None
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    time_codes_per_second: float = 100.0
    start_time: float = 0.0
    metadata: dict = field(default_factory=dict)


class Sink:
    """Base class of every sink: `open(run)` once before the first frame, `write(frame)` for every
    frame in order, `close()` once at the end (also after an error). Override what you need."""

    def open(self, run: RunInfo) -> None:  # noqa: B027 - optional hook
        pass

    def write(self, frame: Frame) -> None:
        raise NotImplementedError

    def close(self) -> None:  # noqa: B027 - optional hook
        pass


class SinkError(ScubeSimError, RuntimeError):
    """A sink failed; the run stops. `__cause__` is the sink's own exception."""


_STOP = object()


class SinkRunner:
    """Feeds frames to sinks on one writer thread behind a bounded queue (see module doc)."""

    def __init__(self, sinks: list[Sink], run: RunInfo, maxsize: int = 8):
        self.sinks = list(sinks)
        self.run = run
        self._queue: queue.Queue = queue.Queue(maxsize=max(1, maxsize))
        self._error: BaseException | None = None
        self._failed_sink: Sink | None = None
        self._thread: threading.Thread | None = None
        self.written = 0

    def start(self) -> None:
        for sink in self.sinks:
            sink.open(self.run)
        self._thread = threading.Thread(target=self._loop, name="scube-sim-sinks", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is _STOP:
                    return
                if self._error is not None:
                    continue  # stopped: drain without writing
                for sink in self.sinks:
                    try:
                        sink.write(item)
                    except BaseException as exc:  # noqa: BLE001 - handed to the loop's thread
                        self._error, self._failed_sink = exc, sink
                        break
                else:
                    self.written += 1
            finally:
                self._queue.task_done()

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise SinkError(f"sink {type(self._failed_sink).__name__} failed: {self._error}") from self._error

    def put(self, frame: Frame) -> None:
        """Queue a frame; blocks while the queue is full (a slow sink slows the loop)."""
        self._raise_if_failed()
        while True:
            try:
                self._queue.put(frame, timeout=0.1)
                return
            except queue.Full:
                self._raise_if_failed()
                if self._thread is not None and not self._thread.is_alive():
                    raise SinkError("the sink writer thread stopped") from self._error

    def close(self) -> None:
        """Write what is queued, stop the thread and close every sink (also after an error).
        Re-raises a sink's error after closing."""
        if self._thread is not None and self._thread.is_alive():
            self._queue.put(_STOP)
            self._thread.join()
        close_errors = []
        for sink in self.sinks:
            try:
                sink.close()
            except BaseException as exc:  # noqa: BLE001 - close them all, then report
                close_errors.append((sink, exc))
        also = "".join(f"; closing {type(sink).__name__} failed too: {exc}" for sink, exc in close_errors)
        if self._error is not None:  # the first failure, and what it cost the other sinks
            raise SinkError(f"sink {type(self._failed_sink).__name__} failed: {self._error}{also}") from self._error
        if close_errors:
            raise SinkError(also[2:].replace(" too", "", 1)) from close_errors[0][1]
