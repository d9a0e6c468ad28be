"""Decoding a vehicle's CAN traffic with a DBC: speed, steering-wheel angle and yaw rate.

`CanVehicleDecoder` turns python-can `Message`s into `vehicle.VehicleSample`s with a cantools DBC
(message and signal names configurable; defaults: the 2017 Toyota RAV4 powertrain DBC of
opendbc). `load_dbc` / `lookup_signals` are shared with the frame-ready sink (`sinks.can`).
Units: m/s, degrees (steering-wheel angle), rad/s.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Iterable

from ...errors import InputError
from ..vehicle import VehicleSample

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


def load_dbc(dbc):
    """A cantools Database and a name for messages: path -> (db, path); Database -> (db, label)."""
    import cantools  # slow to import: only when a DBC is used

    if isinstance(dbc, (str, os.PathLike)):
        path = Path(dbc)
        if not path.is_file():
            raise FileNotFoundError(f"DBC file {path} does not exist")
        try:
            return cantools.database.load_file(str(path)), str(path)
        except Exception as exc:  # noqa: BLE001 - cantools raises many kinds
            raise InputError(f"DBC file {path}: cannot parse it: {exc}") from exc
    if hasattr(dbc, "get_message_by_name"):
        return dbc, getattr(dbc, "_scube_name", "<in-memory DBC>")
    raise TypeError(f"dbc must be a path or a cantools Database, got {type(dbc).__name__}")


def lookup_signals(db, dbc_name: str, message, signals, role: str):
    """(cantools Message, [Signal]) for a message name / frame id and signal names, or ValueError
    naming the DBC and what is missing."""
    try:
        msg = db.get_message_by_frame_id(int(message)) if isinstance(message, int) else \
            db.get_message_by_name(str(message))
    except KeyError:
        what = f"0x{message:X}" if isinstance(message, int) else repr(message)
        raise InputError(f"DBC {dbc_name}: no message {what} (needed for {role})") from None
    names = [signals] if isinstance(signals, str) else list(signals)
    if not names:
        raise InputError(f"{role}: no signal names given for message {msg.name}")
    have = {s.name: s for s in msg.signals}
    missing = [n for n in names if n not in have]
    if missing:
        raise InputError(f"DBC {dbc_name}: message {msg.name} (0x{msg.frame_id:X}) has no signal "
                         f"{', '.join(repr(m) for m in missing)} (needed for {role}); it has "
                         f"{sorted(have)}")
    return msg, [have[n] for n in names]


def _unit_factor(table: dict, signals, override, role: str, dbc_name: str) -> float:
    if override is not None:
        return float(override)
    units = {(s.unit or "").strip().lower() for s in signals}
    if len(units) != 1 or next(iter(units)) not in table:
        raise InputError(f"DBC {dbc_name}: {role} signals {[s.name for s in signals]} have unit(s) "
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
        self.db, self.dbc_name = load_dbc(dbc)
        self.channels = None if channels is None else frozenset(
            [channels] if isinstance(channels, str) else channels)
        self.decode_errors = 0
        # frame id -> list of (kind, cantools message, signal names, factor, reduce)
        self._routes: dict[int, list] = {}
        self.has_speed = speed is not None
        self.has_steer = steer is not None
        self.has_yaw_rate = yaw_rate is not None
        if not (self.has_speed and (self.has_steer or self.has_yaw_rate)):
            raise InputError("CanVehicleDecoder needs speed and at least one of steer / yaw_rate")
        for kind, spec, table, scale, reduce in (
                ("speed", speed, _SPEED_UNITS, speed_scale, "mean"),
                ("steer_deg", steer, _ANGLE_UNITS, steer_scale, "sum"),
                ("yaw_rate", yaw_rate, _RATE_UNITS, yaw_rate_scale, "sum")):
            if spec is None:
                continue
            message, names = spec
            msg, sigs = lookup_signals(self.db, self.dbc_name, message, names, kind)
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
