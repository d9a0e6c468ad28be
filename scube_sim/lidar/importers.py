"""Read vendor calibration files directly into a `LidarConfig`.

Every importer returns a spinning-pattern config in our sensor frame (x forward, y left, z up;
azimuth counter-clockwise from +x, see config.py). Channel order is the vendor's channel order.
Settings a file does not hold (columns, rotation rate, range, noise, mount ...) come from the
keyword arguments; ``**overrides`` are top-level `LidarConfig` sections (``range=``, ``noise=``,
``mount=``, ``notes=`` ...), and a ``pattern=`` mapping is merged into the pattern section.
A missing file, a missing key or column, or a wrong row count raises `ConfigError` naming the file.

Sign conventions (derived from the vendors' own decoders; tests/lidar/test_importers.py
re-implements each decoder formula and checks it against our beam model):

* Velodyne (ros-drivers/velodyne rawdata.cc): the driver's rotation angle is
  ``psi = R - rot_correction`` with the encoder angle R growing clockwise seen from above, and
  the point is ``x_d = xy sin(psi) - h cos(psi)``, ``y_d = xy cos(psi) + h sin(psi)``,
  ``z = d sin(el) + v cos(el)`` with ``xy = d cos(el) - v sin(el)``; the ROS frame is
  ``(X, Y) = (y_d, -x_d)``. Substituting ``az = -psi`` gives
  ``X, Y, Z = d (cos el cos az, cos el sin az, sin el) + h (-sin az, cos az, 0)
  + v (-sin el cos az, -sin el sin az, cos el)``: exactly our Channels origin model with
  ``origin_horizontal_m = horiz_offset_correction`` and ``origin_vertical_m = vert_offset_correction``,
  and ``az = -R + rot_correction``, i.e. ``azimuth_offset_deg = +degrees(rot_correction)``
  (the old driver says the same: "the Velodyne turns clockwise", heading = -(rotation - rot_corr)).
* Hesai (HesaiLidar_SDK_2.0 UdpParser): ``azimuth = block_azimuth + Azimuth_i (+ fire-time
  correction)``, ``x = xy sin(azimuth)``, ``y = xy cos(azimuth)``: the angle grows clockwise from
  the sensor's forward (+y there), so the CSV's Azimuth is clockwise-positive and
  ``azimuth_offset_deg = -Azimuth``. The fire-time correction adds ``t * rpm * 6e-6`` degrees in
  the rotation direction, so a fire time is the channel's delay after the block's encoder instant:
  it maps to ``fire_time_us`` unchanged (Pandar64's are negative: fired before the block stamp).
* Ouster (sensor docs, ouster-sdk): encoder angle ``theta = 2 pi (1 - mid / N)`` (clockwise in
  time), beam azimuth ``alpha = theta - beam_azimuth_angles[i]``, so
  ``azimuth_offset_deg = -beam_azimuth_angles[i]``; every channel of a column fires at once.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..config import json_loads
from ..errors import InputError
from ..transforms import rotmat_to_euler
from .config import ConfigError, LidarConfig, config_from_dict, load_yaml

__all__ = ["from_velodyne_yaml", "from_hesai_csv", "from_ouster_json", "from_waymo_frame",
           "velodyne_distance_resolution", "parse_lidar_mode"]


# --- shared helpers ----------------------------------------------------------------------------


def _require_file(path: str | Path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such file")
    return path


def _float(value, path: Path, where: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{path}: {where}: expected a number, got {value!r}") from None
    if not math.isfinite(out):
        raise ConfigError(f"{path}: {where}: expected a finite number, got {value!r}")
    return out


def _deg(rad: float) -> float:
    """Radians -> degrees rounded at 1e-10 degrees (0.3 nm at 200 m), so that the presets read
    -15.0 rather than -14.999999999999998."""
    return round(math.degrees(rad), 10) + 0.0  # + 0.0 turns -0.0 into 0.0


def _nonzero_or_none(values: list[float]) -> list[float] | None:
    """Omit all-zero tables so the preset files stay short (absent means zeros)."""
    return values if any(v != 0.0 for v in values) else None


def _build(path: Path, name: str | None, pattern: dict, overrides: dict) -> LidarConfig:
    """Assemble and validate; `overrides` are top-level sections, `pattern=` merges into pattern."""
    overrides = dict(overrides)
    pattern = {**pattern, **overrides.pop("pattern", {})}
    data: dict[str, Any] = {"name": name or path.stem, "source": path.name, "pattern": pattern}
    data.update(overrides)
    return config_from_dict(data, f"{path} (imported)")


# --- Velodyne ----------------------------------------------------------------------------------


def from_velodyne_yaml(path: str | Path, *, columns: int, rotation_hz: float, name: str | None = None,
                       fire_time_us: list[float] | None = None, **overrides) -> LidarConfig:
    """A ROS velodyne driver calibration YAML (`lasers:` list) -> LidarConfig.

    Channels in `laser_id` order. elevation = degrees(vert_correction); azimuth offset =
    +degrees(rot_correction) (see the module docstring); origin offsets are the file's
    vert/horiz_offset_correction in metres (a missing key counts as 0, as in the driver).
    The per-laser intensity correction (focal_distance, focal_slope, min/max_intensity, with the
    file's distance_resolution) becomes `intensity.response.velodyne` where the file has one (any
    focal_slope != 0 or intensity limits narrower than 0-255; a missing key counts as the driver's
    default: 0, 0, 0, 255). The distance corrections (dist_correction*) are not modelled. The file
    has no timing: pass `fire_time_us` (per channel, microseconds after the column's encoder instant).
    """
    path = _require_file(path)
    data = load_yaml(path)
    if not isinstance(data, dict) or "lasers" not in data:
        raise ConfigError(f"{path}: missing key 'lasers' (a ROS velodyne calibration has a 'lasers:' list)")
    lasers = data["lasers"]
    if not isinstance(lasers, list) or not lasers:
        raise ConfigError(f"{path}: 'lasers' must be a non-empty list")
    by_id: dict[int, dict] = {}
    for k, laser in enumerate(lasers):
        if not isinstance(laser, dict):
            raise ConfigError(f"{path}: lasers[{k}]: expected a mapping")
        for key in ("laser_id", "vert_correction", "rot_correction"):
            if key not in laser:
                raise ConfigError(f"{path}: lasers[{k}]: missing key '{key}'")
        lid = laser["laser_id"]
        if not isinstance(lid, int) or lid in by_id:
            raise ConfigError(f"{path}: lasers[{k}]: laser_id {lid!r} is not a new integer")
        by_id[lid] = laser
    n = len(lasers)
    if sorted(by_id) != list(range(n)):
        raise ConfigError(f"{path}: laser_id values must be 0..{n - 1}, got {sorted(by_id)}")
    if "num_lasers" in data and data["num_lasers"] != n:
        raise ConfigError(f"{path}: num_lasers is {data['num_lasers']} but 'lasers' has {n} rows")

    def table(key: str, default: float | None = None) -> list[float]:
        out = []
        for lid in range(n):
            raw = by_id[lid].get(key, default)
            out.append(_float(raw, path, f"laser_id {lid}: {key}"))
        return out

    channels = {
        "elevation_deg": [_deg(v) for v in table("vert_correction")],
        "azimuth_offset_deg": _nonzero_or_none([_deg(v) for v in table("rot_correction")]),
        "fire_time_us": fire_time_us,
        "origin_vertical_m": _nonzero_or_none(table("vert_offset_correction", 0.0)),
        "origin_horizontal_m": _nonzero_or_none(table("horiz_offset_correction", 0.0)),
    }
    if fire_time_us is not None and len(fire_time_us) != n:
        raise ConfigError(f"{path}: fire_time_us has {len(fire_time_us)} entries but the file has {n} lasers")
    pattern = {"type": "spinning", "columns": columns, "rotation_hz": rotation_hz, "direction": "cw",
               "channels": {k: v for k, v in channels.items() if v is not None}}
    # The driver's defaults and rounding (calibration.cc: absent limits are 0 and 255, floored).
    focal = {"focal_distance": table("focal_distance", 0.0), "focal_slope": table("focal_slope", 0.0),
             "min_intensity": [float(math.floor(v)) for v in table("min_intensity", 0.0)],
             "max_intensity": [float(math.floor(v)) for v in table("max_intensity", 255.0)]}
    if (any(focal["focal_slope"]) or min(focal["min_intensity"]) > 0 or max(focal["max_intensity"]) < 255):
        res = data.get("distance_resolution", 0.002)
        focal["distance_resolution_m"] = _float(res, path, "distance_resolution")
        intensity = dict(overrides.get("intensity", {}))
        intensity["response"] = {**intensity.get("response", {}), "velodyne": focal}
        overrides = {**overrides, "intensity": intensity}
    return _build(path, name, pattern, overrides)


def velodyne_distance_resolution(path: str | Path) -> float | None:
    """The calibration's `distance_resolution` (m), or None when absent."""
    data = load_yaml(_require_file(path))
    value = data.get("distance_resolution") if isinstance(data, dict) else None
    return None if value is None else _float(value, Path(path), "distance_resolution")


# --- Hesai -------------------------------------------------------------------------------------


def _read_csv_rows(path: Path) -> list[list[str]]:
    # utf-8-sig drops the BOM some Hesai files start with; newline='' keeps csv in charge of \r\n.
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text: {exc}") from None
    rows = [[c.strip() for c in row] for row in csv.reader(io.StringIO(text, newline=""))]
    return [row for row in rows if any(row)]


def _norm(s: str) -> str:
    return re.sub(r"[^a-z]", "", s.lower())


def _find_column(header: list[str], path: Path, wanted: str) -> int:
    for i, cell in enumerate(header):
        if _norm(cell).startswith(_norm(wanted)):
            if any(_norm(c) == _norm(cell) for c in header[i + 1:]):  # which one is meant?
                raise ConfigError(f"{path}: header: column {cell!r} is listed twice ({', '.join(header)})")
            return i
    raise ConfigError(f"{path}: missing column '{wanted}' (header: {', '.join(header)})")


def _channel_number(cell: str, path: Path, line: int) -> int:
    try:
        return int(cell)
    except ValueError:
        raise ConfigError(f"{path}: row {line}: channel {cell!r} is not an integer") from None


def _check_channels(found: list[int], path: Path, expected: int | None) -> int:
    n = len(found)
    if expected is not None and n != expected:
        raise ConfigError(f"{path}: expected {expected} channel rows, found {n}")
    if sorted(found) != list(range(1, n + 1)):
        raise ConfigError(f"{path}: channels must be numbered 1..{n} once each")
    return n


def _hesai_angles(path: Path, channels: int | None) -> tuple[list[float], list[float]]:
    rows = _read_csv_rows(path)
    if not rows:
        raise ConfigError(f"{path}: empty file")
    header = rows[0]
    # Some SDK files start with an 'EEFF' line before the header (the SDK skips it too).
    if _norm(header[0]) == "eeff":
        rows = rows[1:]
        header = rows[0] if rows else []
    ic, ie, ia = (_find_column(header, path, w) for w in ("Channel", "Elevation", "Azimuth"))
    table: dict[int, tuple[float, float]] = {}
    for line, row in enumerate(rows[1:], start=2):
        if len(row) <= max(ic, ie, ia):
            raise ConfigError(f"{path}: row {line}: expected at least {max(ic, ie, ia) + 1} columns")
        ch = _channel_number(row[ic], path, line)
        if ch in table:
            raise ConfigError(f"{path}: row {line}: channel {ch} listed twice")
        table[ch] = (_float(row[ie], path, f"row {line} Elevation"), _float(row[ia], path, f"row {line} Azimuth"))
    n = _check_channels(list(table), path, channels)
    return [table[c][0] for c in range(1, n + 1)], [table[c][1] for c in range(1, n + 1)]


def _hesai_fire_times(path: Path, n: int, operation_mode: int, angle_state: int,
                      mode_table_unit: str) -> list[float]:
    """Per-channel fire times (µs) from either Hesai fire-time layout."""
    rows = _read_csv_rows(path)
    if not rows:
        raise ConfigError(f"{path}: empty file")
    header = rows[0]
    if _norm(header[0]) == "channel":
        # Simple layout: 'Channel,fire time(us)' (or μs / ns), rows in any channel order.
        it = _find_column(header, path, "fire time")
        unit = header[it].lower()
        per_us = 1000.0 if "ns" in unit else 1.0
        table: dict[int, float] = {}
        for line, row in enumerate(rows[1:], start=2):
            if len(row) <= it:
                raise ConfigError(f"{path}: row {line}: missing the fire time column")
            ch = _channel_number(row[0], path, line)
            if ch in table:
                raise ConfigError(f"{path}: row {line}: channel {ch} listed twice")
            table[ch] = _float(row[it], path, f"row {line} fire time") / per_us
        _check_channels(list(table), path, n)
        return [table[c] for c in range(1, n + 1)]

    # Mode-dependent layout (Pandar128E3X): header rows until the first integer channel row;
    # one row names the operation mode of each column, one the angle state; each (mode, state)
    # pair has two columns (distance >= A1, distance < A1). We take the first column of the
    # requested pair: the far-distance firing, which is what a scene beyond A1 (2.85 m) sees.
    first = next((k for k, r in enumerate(rows) if re.fullmatch(r"\d+", r[0])), None)
    if first is None:
        raise ConfigError(f"{path}: no channel rows found")
    head = rows[:first]
    mode_row = next((r for r in head if _norm(r[0]).startswith(("operationmode", "operationalstate"))), None)
    state_row = next((r for r in head if _norm(r[0]).startswith(("anglestate", "azimuthstate"))), None)
    if mode_row is None or state_row is None:
        raise ConfigError(f"{path}: missing the 'operation mode' / 'angle state' header rows")
    col = next((i for i in range(1, min(len(mode_row), len(state_row)))
                if mode_row[i] == str(operation_mode) and state_row[i] == str(angle_state)), None)
    if col is None:
        raise ConfigError(f"{path}: no column for operation mode {operation_mode}, angle state {angle_state}")
    if mode_table_unit not in ("ns", "us"):
        raise InputError(f"mode_table_unit must be 'ns' or 'us', got {mode_table_unit!r}")
    per_us = 1000.0 if mode_table_unit == "ns" else 1.0
    table = {}
    for line, row in enumerate(rows[first:], start=first + 1):
        ch = _channel_number(row[0], path, line)
        if len(row) <= col:
            raise ConfigError(f"{path}: row {line}: missing column {col + 1}")
        if row[col] in ("-", ""):
            raise ConfigError(f"{path}: row {line}: channel {ch} does not fire in operation mode "
                              f"{operation_mode}, angle state {angle_state}")
        if ch in table:
            raise ConfigError(f"{path}: row {line}: channel {ch} listed twice")
        table[ch] = _float(row[col], path, f"row {line} column {col + 1}") / per_us
    _check_channels(list(table), path, n)
    return [table[c] for c in range(1, n + 1)]


def from_hesai_csv(angle_csv: str | Path, firetime_csv: str | Path | None = None, *, columns: int,
                   rotation_hz: float, name: str | None = None, channels: int | None = None,
                   operation_mode: int = 2, angle_state: int = 0, mode_table_unit: str = "ns",
                   **overrides) -> LidarConfig:
    """Hesai angle correction CSV (`Channel,Elevation,Azimuth`, degrees) and optional fire-time CSV.

    Channels 1..N in order. azimuth_offset_deg = -Azimuth (Hesai's is clockwise-positive).
    Fire times (µs after the block's encoder instant) come from either layout:
    `Channel,fire time(us)` (µs; `μs` and a BOM accepted; `ns` scaled), or the mode-dependent
    table (Pandar128E3X), where we take operation mode `operation_mode` (2 = standard, the
    non-high-resolution mode in which every channel fires in every column; 0 is high resolution),
    angle state `angle_state` and the distance >= A1 column. That table is in nanoseconds (the SDK
    converts with ``t * rpm * 6e-9`` degrees), hence `mode_table_unit` = 'ns' ('us' for tables in µs).
    `channels`: the expected channel count (checked in both files when given).
    """
    angle_csv = _require_file(angle_csv)
    elevation, azimuth = _hesai_angles(angle_csv, channels)
    fire = None
    if firetime_csv is not None:
        fire = _hesai_fire_times(_require_file(firetime_csv), len(elevation), operation_mode,
                                 angle_state, mode_table_unit)
    ch = {"elevation_deg": elevation, "azimuth_offset_deg": _nonzero_or_none([-a for a in azimuth])}
    if fire is not None:
        ch["fire_time_us"] = fire
    ch = {k: v for k, v in ch.items() if v is not None}
    pattern = {"type": "spinning", "columns": columns, "rotation_hz": rotation_hz, "direction": "cw",
               "channels": ch}
    return _build(angle_csv, name, pattern, overrides)


# --- Ouster ------------------------------------------------------------------------------------


def _ouster_get(data: dict, path: Path, *keys: tuple[str, ...]):
    """The first of several key paths present in `data` (legacy flat or nested layout)."""
    for key_path in keys:
        node = data
        for k in key_path:
            if not isinstance(node, dict) or k not in node:
                break
            node = node[k]
        else:
            return node
    names = " or ".join(".".join(k) for k in keys)
    raise ConfigError(f"{path}: missing key {names}")


def parse_lidar_mode(mode: str, path: Path | str = "<lidar_mode>") -> tuple[int, float]:
    """'1024x10' -> (1024 columns, 10.0 Hz)."""
    m = re.fullmatch(r"\s*(\d+)\s*x\s*(\d+(?:\.\d+)?)\s*", str(mode))
    if not m:
        raise ConfigError(f"{path}: lidar_mode {mode!r} is not of the form '<columns>x<hz>'")
    return int(m.group(1)), float(m.group(2))


def from_ouster_json(path: str | Path, *, columns: int | None = None, rotation_hz: float | None = None,
                     name: str | None = None, **overrides) -> LidarConfig:
    """Ouster sensor metadata JSON (legacy flat or nested `beam_intrinsics` layout) -> LidarConfig.

    elevation = beam_altitude_angles; azimuth_offset_deg = -beam_azimuth_angles (see the module
    docstring); fire_time 0 (a column's channels fire together; the stagger is the azimuth table).
    columns / rotation_hz default to `lidar_mode` ('1024x10'). start_azimuth_deg is where
    measurement id 0 points in the sensor frame (theta = 0 is lidar-frame +x, which
    lidar_to_sensor_transform turns by 180 degrees: the sweep starts behind the sensor).
    Not representable and ignored: lidar_origin_to_beam_origin_mm (a radial beam-origin offset) and
    the lidar-to-sensor z offset (our sensor origin is the lidar-frame origin).
    """
    path = _require_file(path)
    try:
        data = json_loads(path.read_text(encoding="utf-8-sig"), path)  # a key twice: refused
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: not valid JSON (line {exc.lineno}, column {exc.colno}): {exc.msg}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a JSON object")
    alt = _ouster_get(data, path, ("beam_intrinsics", "beam_altitude_angles"), ("beam_altitude_angles",))
    az = _ouster_get(data, path, ("beam_intrinsics", "beam_azimuth_angles"), ("beam_azimuth_angles",))
    if not isinstance(alt, list) or not isinstance(az, list):
        raise ConfigError(f"{path}: beam_altitude_angles and beam_azimuth_angles must be lists")
    if len(alt) != len(az):
        raise ConfigError(f"{path}: {len(alt)} beam_altitude_angles but {len(az)} beam_azimuth_angles")
    try:
        ppc = _ouster_get(data, path, ("lidar_data_format", "pixels_per_column"),
                          ("data_format", "pixels_per_column"))
    except ConfigError:
        ppc = None  # very old metadata has no data_format; the two tables then define the count
    if ppc is not None and ppc != len(alt):
        raise ConfigError(f"{path}: pixels_per_column is {ppc} but there are {len(alt)} beam angles")
    if columns is None or rotation_hz is None:
        mode = _ouster_get(data, path, ("config_params", "lidar_mode"), ("lidar_mode",))
        mode_cols, mode_hz = parse_lidar_mode(mode, path)
        columns = mode_cols if columns is None else columns
        rotation_hz = mode_hz if rotation_hz is None else rotation_hz
    try:
        l2s = _ouster_get(data, path, ("lidar_intrinsics", "lidar_to_sensor_transform"),
                          ("lidar_to_sensor_transform",))
        m = np.asarray(l2s, dtype=np.float64).reshape(4, 4)
        start = math.degrees(math.atan2(m[1, 0], m[0, 0]))
    except (ConfigError, ValueError):
        start = 0.0
    elevation = [_float(v, path, f"beam_altitude_angles[{i}]") for i, v in enumerate(alt)]
    offsets = [-_float(v, path, f"beam_azimuth_angles[{i}]") for i, v in enumerate(az)]
    ch = {"elevation_deg": elevation}
    if _nonzero_or_none(offsets) is not None:
        ch["azimuth_offset_deg"] = offsets
    pattern = {"type": "spinning", "columns": columns, "rotation_hz": rotation_hz, "direction": "cw",
               "start_azimuth_deg": start, "channels": ch}
    return _build(path, name, pattern, overrides)


# --- Waymo -------------------------------------------------------------------------------------


def from_waymo_frame(frame_metadata_json: str | Path, laser_name: str = "TOP", *, columns: int = 2650,
                     rotation_hz: float = 10.0, name: str | None = None, **overrides) -> LidarConfig:
    """A laser of a Waymo frame's calibration (our `frame_metadata.json` extract) -> LidarConfig.

    elevation = degrees(beam_inclinations_rad) in the file's order, which is ascending (bottom beam
    first); Waymo range-image row r is channel N-1-r. No azimuth offsets or timing are published
    (fire_time 0). mount = extrinsic_laser_to_vehicle_4x4 (xyz m, rpy deg). start_azimuth_deg puts
    column 0 where Waymo's range image has it: vehicle azimuth 180 - 180/columns degrees, columns
    running clockwise (range_image_utils.compute_range_image_polar).
    """
    path = _require_file(frame_metadata_json)
    try:
        data = json_loads(path.read_text(encoding="utf-8"), path)  # a key twice: refused
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: not valid JSON (line {exc.lineno}, column {exc.colno}): {exc.msg}") from None
    lasers = data.get("laser_calibrations") if isinstance(data, dict) else None
    if not isinstance(lasers, list):
        raise ConfigError(f"{path}: missing key 'laser_calibrations'")
    hits = [k for k, l in enumerate(lasers) if isinstance(l, dict) and l.get("name") == laser_name]
    if len(hits) > 1:
        raise ConfigError(f"{path}: laser_calibrations: name {laser_name!r} is listed twice (at [{hits[0]}] and "
                          f"[{hits[1]}])")
    laser = next((l for l in lasers if isinstance(l, dict) and l.get("name") == laser_name), None)
    if laser is None:
        names = [l.get("name") for l in lasers if isinstance(l, dict)]
        raise ConfigError(f"{path}: no laser named {laser_name!r}; lasers: {', '.join(map(str, names))}")
    incl = laser.get("beam_inclinations_rad")
    if not incl:
        raise ConfigError(f"{path}: laser {laser_name}: beam_inclinations_rad is missing or empty "
                          f"(this laser only publishes min/max inclination)")
    elevation = [_deg(_float(v, path, f"{laser_name}.beam_inclinations_rad[{i}]"))
                 for i, v in enumerate(incl)]

    ext = laser.get("extrinsic_laser_to_vehicle_4x4")
    try:
        m = np.asarray(ext, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError):
        raise ConfigError(f"{path}: laser {laser_name}: extrinsic_laser_to_vehicle_4x4 is not a 4x4 matrix") from None
    rpy = [_deg(a) for a in rotmat_to_euler(m[:3, :3])]
    yaw = math.degrees(math.atan2(m[1, 0], m[0, 0]))
    start = (180.0 - 180.0 / columns - yaw + 180.0) % 360.0 - 180.0
    pattern = {"type": "spinning", "columns": columns, "rotation_hz": rotation_hz, "direction": "cw",
               "start_azimuth_deg": start, "channels": {"elevation_deg": elevation}}
    overrides.setdefault("mount", {"xyz": [float(v) for v in m[:3, 3]], "rpy_deg": rpy})
    return _build(path, name, pattern, overrides)
