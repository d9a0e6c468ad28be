"""Sinks that hand frames to the host's own code in the same process."""

from __future__ import annotations

import queue
from typing import Callable

from ..frame import Frame
from .base import Sink


class CallbackSink(Sink):
    """Calls `fn(frame)` on the writer thread for every frame."""

    def __init__(self, fn: Callable[[Frame], None]):
        self.fn = fn

    def write(self, frame: Frame) -> None:
        self.fn(frame)


class QueueSink(Sink):
    """Puts every frame into `self.queue` (a `queue.Queue`, bounded by `maxsize`) for an
    in-process consumer; a full queue blocks the writer thread, hence the loop."""

    def __init__(self, maxsize: int = 0):
        self.queue: queue.Queue = queue.Queue(maxsize)

    def write(self, frame: Frame) -> None:
        self.queue.put(frame)

    def close(self) -> None:
        self.queue.put(None)  # end-of-run marker for consumers
