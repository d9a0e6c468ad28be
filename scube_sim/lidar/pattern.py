"""Scan patterns: every ray a sensor fires in one sweep, in the sensor frame, in firing order.

Sensor frame: x forward, y left, z up; azimuth counter-clockwise from +x, elevation up from the
xy-plane. A ray is ``origin_offset + r * direction`` with r the reported range.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .config import ConfigError, EmitterPattern, LidarConfig, SpinningPattern


@dataclass(frozen=True)
class ScanPattern:
    """All rays of one sweep, ordered by fire time (then channel).

    directions (N, 3) float64 unit, sensor frame; offsets (N, 3) float64 beam origins, metres;
    time (N,) float64 seconds after the sweep start; ring (N,) uint16 channel index in the
    vendor's order; column (N,) int32 firing column (-1 for emitter tables without columns);
    azimuth, elevation (N,) float64 radians; period_s: sweep duration; columns: columns per
    sweep (0 for emitter tables); ring_elevation_deg (C,) per-channel elevation (for range images).
    """

    directions: np.ndarray
    offsets: np.ndarray
    time: np.ndarray
    ring: np.ndarray
    column: np.ndarray
    azimuth: np.ndarray
    elevation: np.ndarray
    period_s: float
    columns: int
    ring_elevation_deg: np.ndarray

    def __len__(self) -> int:
        return int(self.directions.shape[0])


def unit_directions(azimuth: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    """Radians -> (N, 3) float64 unit vectors in the sensor frame."""
    ce = np.cos(elevation)
    return np.stack([ce * np.cos(azimuth), ce * np.sin(azimuth), np.sin(elevation)], axis=1)


def spinning_pattern(p: SpinningPattern) -> ScanPattern:
    ch = p.channels
    c = ch.count
    elev = np.deg2rad(ch.table("elevation_deg"))
    az_off = np.deg2rad(ch.table("azimuth_offset_deg"))
    fire = ch.table("fire_time_us") * 1e-6
    sign = -1.0 if p.direction == "cw" else 1.0
    omega = 2.0 * np.pi * p.rotation_hz  # rad/s
    col = np.arange(p.columns)
    t_col = col / (p.columns * p.rotation_hz)
    t = t_col[:, None] + fire[None, :]  # (columns, channels)
    # The head keeps turning while the channels of one column fire: each beam points where the
    # head is at its own fire instant, plus its fixed azimuth offset.
    az = np.deg2rad(p.start_azimuth_deg) + sign * omega * t + az_off[None, :]
    az = np.mod(az + np.pi, 2 * np.pi) - np.pi
    el = np.broadcast_to(elev, t.shape)
    dirs = unit_directions(az.ravel(), el.ravel())
    v = ch.table("origin_vertical_m")
    h = ch.table("origin_horizontal_m")
    if np.any(v) or np.any(h):
        azr, elr = az.ravel(), el.ravel()
        vv = np.broadcast_to(v, t.shape).ravel()
        hh = np.broadcast_to(h, t.shape).ravel()
        offsets = (hh[:, None] * np.stack([-np.sin(azr), np.cos(azr), np.zeros_like(azr)], 1)
                   + vv[:, None] * np.stack([-np.sin(elr) * np.cos(azr), -np.sin(elr) * np.sin(azr),
                                             np.cos(elr)], 1))
    else:
        offsets = np.zeros_like(dirs)
    tt = t.ravel()
    ring = np.broadcast_to(np.arange(c, dtype=np.uint16), t.shape).ravel()
    column = np.broadcast_to(col[:, None].astype(np.int32), t.shape).ravel()
    order = np.lexsort((ring, tt))  # firing order
    return ScanPattern(dirs[order], offsets[order], tt[order], ring[order], column[order],
                       az.ravel()[order], el.ravel()[order], p.period_s, p.columns,
                       np.asarray(ch.elevation_deg, np.float64))


def read_emitter_table(path: str | Path) -> dict[str, np.ndarray]:
    """Read an emitter table: .csv with a header (azimuth_deg, elevation_deg[, time_s][, channel])
    or .npy (K, 2..4) in that column order. Errors name the file and the problem."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: emitter table not found")
    cols = ("azimuth_deg", "elevation_deg", "time_s", "channel")
    if path.suffix.lower() == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as exc:
            raise ConfigError(f"{path}: not a readable .npy array ({exc})") from None
        if arr.ndim != 2 or not 2 <= arr.shape[1] <= 4:
            raise ConfigError(f"{path}: expected a (K, 2..4) array of {', '.join(cols)}, got {arr.shape}")
        out = {name: arr[:, i].astype(np.float64) for i, name in enumerate(cols[: arr.shape[1]])}
    elif path.suffix.lower() == ".csv":
        with open(path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            fields = [f.strip() for f in (reader.fieldnames or [])]
            twice = next((f for k, f in enumerate(fields) if f in fields[:k]), None)
            if twice is not None:  # csv.DictReader would keep the last column of the name
                raise ConfigError(f"{path}: header: column {twice!r} is listed twice ({', '.join(fields)})")
            for need in cols[:2]:
                if need not in fields:
                    raise ConfigError(f"{path}: missing column {need!r} (header: {', '.join(fields)})")
            rows = list(reader)
        out = {}
        for name in cols:
            if name in fields:
                try:
                    out[name] = np.array([float(r[name]) for r in rows], np.float64)
                except (TypeError, ValueError):
                    raise ConfigError(f"{path}: column {name!r} holds a non-number") from None
    else:
        raise ConfigError(f"{path}: emitter table must be .csv or .npy")
    if not all(np.all(np.isfinite(v)) for v in out.values()):
        raise ConfigError(f"{path}: emitter table holds NaN or Inf")
    if not len(out["azimuth_deg"]):
        raise ConfigError(f"{path}: emitter table has no rays")
    if np.any(np.abs(out["elevation_deg"]) > 90.0):
        raise ConfigError(f"{path}: elevation_deg must lie in [-90, 90] degrees")
    return out


def emitter_pattern(p: EmitterPattern) -> ScanPattern:
    if p.file is not None:
        tab = read_emitter_table(p.file)
    else:
        tab = {"azimuth_deg": np.asarray(p.azimuth_deg, np.float64),
               "elevation_deg": np.asarray(p.elevation_deg, np.float64)}
        if p.time_s is not None:
            tab["time_s"] = np.asarray(p.time_s, np.float64)
        if p.channel is not None:
            tab["channel"] = np.asarray(p.channel, np.float64)
    az = np.deg2rad(tab["azimuth_deg"])
    el = np.deg2rad(tab["elevation_deg"])
    if np.any(np.abs(tab["elevation_deg"]) > 90):
        raise ConfigError(f"{p.file or 'emitter table'}: elevation outside [-90, 90] degrees")
    n = az.shape[0]
    t = tab.get("time_s", np.zeros(n))
    ring = tab.get("channel", np.zeros(n)).astype(np.uint16)
    order = np.lexsort((ring, t))
    dirs = unit_directions(az, el)
    return ScanPattern(dirs[order], np.zeros((n, 3)), t[order], ring[order], np.full(n, -1, np.int32),
                       az[order], el[order], p.period_s, 0, np.zeros(0))


def replay_pattern(directions: np.ndarray, time: np.ndarray | None = None, ring: np.ndarray | None = None, *,
                   period_s: float = 0.1) -> ScanPattern:
    """The rays of a recorded sweep, to simulate it ray for ray.

    directions (N, 3) sensor frame (normalised here); time (N,) seconds after the sweep start
    (default 0); ring (N,) channel ids. `column` holds each ray's index in the input, so returns
    map back to the recorded points."""
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    norm = np.linalg.norm(d, axis=1)
    if not np.all(np.isfinite(d)) or np.any(norm == 0):
        raise InputError("replay_pattern: directions must be finite and non-zero")
    if d.shape[0] > np.iinfo(np.int32).max:
        raise InputError("replay_pattern: too many rays")
    d = d / norm[:, None]
    n = d.shape[0]
    t = np.zeros(n) if time is None else np.asarray(time, np.float64).reshape(n)
    rg = np.zeros(n, np.uint16) if ring is None else np.asarray(ring).astype(np.uint16).reshape(n)
    az = np.arctan2(d[:, 1], d[:, 0])
    el = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
    period = max(float(period_s), float(t.max(initial=0.0)))
    return ScanPattern(d, np.zeros((n, 3)), t, rg, np.arange(n, dtype=np.int32), az, el, period, 0, np.zeros(0))


def make_pattern(cfg: LidarConfig) -> ScanPattern:
    if isinstance(cfg.pattern, SpinningPattern):
        return spinning_pattern(cfg.pattern)
    return emitter_pattern(cfg.pattern)


def channels_by_elevation(directions: np.ndarray, ring: np.ndarray, cfg: LidarConfig,
                          valid: np.ndarray | None = None) -> np.ndarray:
    """The sensor channel (index into `cfg`'s per-channel tables) of each ray of a recorded sweep.

    Datasets number rings their own way (nuScenes by elevation, the vendor by laser id), so each
    recorded ring id is matched to the channel whose elevation is nearest the median elevation of
    that ring's rays. directions (N, 3) unit, sensor frame; ring (N,) int (< 0: unknown); valid
    (N,) bool: the rays whose directions are measured (default all). Returns (N,) int64, -1 where
    the ring is unknown or `cfg` has no channel table (emitter patterns)."""
    ring = np.asarray(ring, np.int64)
    out = np.full(ring.shape[0], -1, np.int64)
    if not isinstance(cfg.pattern, SpinningPattern) or ring.size == 0:
        return out
    table = np.deg2rad(np.asarray(cfg.pattern.channels.elevation_deg, np.float64))
    el = np.arcsin(np.clip(np.asarray(directions, np.float64)[:, 2], -1.0, 1.0))
    ok = ring >= 0 if valid is None else (ring >= 0) & np.asarray(valid, bool)
    for k in np.unique(ring[ok]):
        out[ring == k] = int(np.argmin(np.abs(table - np.median(el[ok & (ring == k)]))))
    return out
