"""A sink that announces every finished frame on a CAN bus. python-can is imported when the
sink opens its bus or sends (slow to import)."""

from __future__ import annotations

from ...errors import InputError
from ..can.dbc import load_dbc, lookup_signals
from ..can.frame_ready import FRAME_READY_ID, pack_frame_ready
from ..frame import Frame
from .base import RunInfo, Sink


def _can():
    """python-can, imported on first use: `scube_sim.sim` imports this sink, and only a run that sends needs it."""
    import can

    return can


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
                raise InputError("CanFrameSink: with a dbc, name the message to encode")
            db, name = load_dbc(dbc)
            sig = {"counter": "COUNTER", "sweeps": "SWEEPS", "time_ms": "TIME_MS", **(signals or {})}
            msg, sigs = lookup_signals(db, name, message, [sig["counter"], sig["sweeps"], sig["time_ms"]],
                                "the frame-ready message")
            self._message = msg
            self._signals = sig
            self._widths = {k: s.length for k, s in zip(("counter", "sweeps", "time_ms"), sigs)}
            self.arbitration_id = msg.frame_id
            self.is_extended_id = bool(msg.is_extended_frame)
        elif not (0 <= self.arbitration_id < (1 << (29 if self.is_extended_id else 11))):
            raise InputError(f"CanFrameSink: arbitration id 0x{self.arbitration_id:X} out of range")

    def open(self, run: RunInfo | None = None) -> None:
        if self.bus is None:
            self.bus = _can().Bus(interface=self.interface, channel=self.channel, **self.bus_kwargs)
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
        can = _can()

        if self.bus is None:
            self.open(None)
        if not (frame.time >= 0):
            raise InputError(f"CanFrameSink: frame time {frame.time} s is negative or NaN")
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
