"""`sensor_msgs/PointCloud2` point layouts: our LiDAR points packed the way ROS 2 drivers and
Autoware lay them out.

A layout is a list of `PointField`s (name, byte offset, datatype, count) and a `point_step`; the
packed data is little-endian, one point after another, padding bytes zero. Our points are a
structured array (`scube_sim.lidar.POINT_DTYPE`: x y z metres in the sensor frame, intensity,
ring, time s after the sweep start, range m, azimuth rad CCW from +x, label, instance, ...).

Layouts (`kind`: fields as name offset type; point_step; source):

- ``scube``: every field of the points' dtype, packed in order (bool as uint8); their sum.
  Ours, lossless.
- ``velodyne``: x 0, y 4, z 8, intensity 12 (float32), ring 16 (uint16), time 18 (float32 s);
  22. velodyne_pointcloud's ROS 2 `PointcloudXYZIRT`: fields packed without padding.
- ``ouster``: x 0, y 4, z 8, intensity 16 (float32), t 20 (uint32 ns), reflectivity 24, ring 26,
  ambient 28 (uint16), range 32 (uint32 mm); 48. ouster-ros `ouster_ros::Point` ("original", the
  default), a PCL struct aligned to 16 bytes.
- ``autoware_xyzirc``: x 0, y 4, z 8 (float32), intensity 12 (uint8), return_type 13 (uint8),
  channel 14 (uint16); 16. autoware_point_types `PointXYZIRC`.
- ``autoware_xyzircaedt``: as XYZIRC, then azimuth 16, elevation 20, distance 24 (float32),
  time_stamp 28 (uint32 ns); 32. autoware_point_types `PointXYZIRCAEDT`.

Extra fields (`EXTRA_FIELDS`: label int16, instance int32 and, where the points carry them,
observed uint8 and confidence float32) are appended after a driver layout's own fields (a
consumer that reads fields by name, as PCL's `fromROSMsg` does, ignores them). The Autoware
layouts never carry them: `is_data_layout_compatible_with_point_xyzircaedt` (autoware_core,
common/autoware_point_types/include/autoware/point_types/memory.hpp) requires exactly 10 fields,
and although `..._xyzirc` accepts more than 6, Autoware's PTv3 detector
(`PTv3TRT::detectCloudFormat`) takes XYZIRC only at `fields.size() == 6`.

Times: point times are written relative to the message's header stamp: `time_offset` (s) is
`stamp - t_start`, subtracted from our `time`. Velodyne's float `time` may go negative (its
driver stamps at the last packet by default); Ouster's `t` and Autoware's `time_stamp` are
unsigned nanoseconds, so their stamp must be at or before the first point (an error otherwise).
Float intensities (Velodyne, Ouster) are ours as they are (the sensor config's
`intensity.output_scale` sets their units). Integer intensities (Autoware uint8, Ouster
reflectivity uint16) are `round(intensity * intensity_scale)` clipped to 0..255: with the presets'
output_scale 1 our intensity is a reflectivity in [0, 1] and the default scale 255 gives the
drivers' 0..255.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from ..config import StrictModel
from ..errors import InputError

# sensor_msgs/msg/PointField datatype constants.
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
DATATYPE_DTYPES = {INT8: "<i1", UINT8: "<u1", INT16: "<i2", UINT16: "<u2", INT32: "<i4", UINT32: "<u4",
                   FLOAT32: "<f4", FLOAT64: "<f8"}
_DTYPE_DATATYPES = {np.dtype(v): k for k, v in DATATYPE_DTYPES.items()}

LayoutKind = Literal["scube", "velodyne", "ouster", "autoware_xyzirc", "autoware_xyzircaedt"]
LAYOUT_KINDS: tuple[str, ...] = ("scube", "velodyne", "ouster", "autoware_xyzirc", "autoware_xyzircaedt")
AUTOWARE_KINDS = ("autoware_xyzirc", "autoware_xyzircaedt")
EXTRA_FIELDS = {"label": INT16, "instance": INT32, "observed": UINT8, "confidence": FLOAT32}
"""Our extra per-point fields and their PointField datatypes (added only where the points have them)."""

# Each driver layout: (name, offset, datatype), then its point_step. Offsets are the C structs'
# (offsetof), not a packing of our own: see the module table for the sources.
_BASE: dict[str, tuple[tuple[tuple[str, int, int], ...], int]] = {
    "velodyne": ((("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 12, FLOAT32),
                  ("ring", 16, UINT16), ("time", 18, FLOAT32)), 22),
    "ouster": ((("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 16, FLOAT32),
                ("t", 20, UINT32), ("reflectivity", 24, UINT16), ("ring", 26, UINT16), ("ambient", 28, UINT16),
                ("range", 32, UINT32)), 48),
    "autoware_xyzirc": ((("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 12, UINT8),
                         ("return_type", 13, UINT8), ("channel", 14, UINT16)), 16),
    "autoware_xyzircaedt": ((("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 12, UINT8),
                             ("return_type", 13, UINT8), ("channel", 14, UINT16), ("azimuth", 16, FLOAT32),
                             ("elevation", 20, FLOAT32), ("distance", 24, FLOAT32), ("time_stamp", 28, UINT32)),
                            32),
}


@dataclass(frozen=True)
class PointField:
    """One `sensor_msgs/msg/PointField`: offset in bytes from the point's start."""

    name: str
    offset: int
    datatype: int
    count: int = 1


class PointLayout(StrictModel):
    """How one sensor's points are packed.

    kind: see the module table. extras: append our extra fields (None: wherever the layout
    allows them, i.e. not for Autoware). intensity_scale: our intensity -> integer intensity
    fields. return_types: Autoware `return_type` for our return_id 0 and 1 (default
    SINGLE_STRONGEST = 1 and SINGLE_LAST = 2, the presets' 'strongest' and the 'dual' mode's
    strongest + last)."""

    kind: LayoutKind = "velodyne"
    extras: bool | None = None
    intensity_scale: float = Field(default=255.0, gt=0)
    return_types: tuple[int, int] = (1, 2)

    @model_validator(mode="after")
    def _autoware_has_no_extras(self):
        if self.extras and self.kind in AUTOWARE_KINDS:
            raise ValueError(f"extras: layout {self.kind!r} cannot carry extra fields (Autoware checks the exact "
                             "field list: is_data_layout_compatible_with_point_xyzircaedt wants exactly 10 fields)")
        for v in self.return_types:
            if not 0 <= v <= 255:
                raise ValueError(f"return_types: expected uint8 values, got {self.return_types}")
        return self

    @property
    def with_extras(self) -> bool:
        return self.kind not in AUTOWARE_KINDS and self.extras is not False


def as_layout(layout: "str | PointLayout | dict", where: str = "layout") -> PointLayout:
    """A `PointLayout` from a kind name, a dict of its fields or a layout; errors name `where`."""
    if isinstance(layout, PointLayout):
        return layout
    if isinstance(layout, str):
        if layout not in LAYOUT_KINDS:
            raise InputError(f"{where}: unknown point layout {layout!r}; use one of {', '.join(LAYOUT_KINDS)}")
        return PointLayout(kind=layout)
    if isinstance(layout, dict):
        try:
            return PointLayout(**layout)
        except ValueError as exc:
            raise InputError(f"{where}: {exc}") from exc
    raise InputError(f"{where}: expected a layout name or mapping, got {type(layout).__name__}")


@dataclass
class PackedPoints:
    """A PointCloud2 body: fields, point_step (bytes), data (N * point_step,) uint8, width N
    (height 1), is_dense (every x y z finite)."""

    fields: list[PointField]
    point_step: int
    data: np.ndarray
    width: int
    is_dense: bool

    @property
    def row_step(self) -> int:
        return self.width * self.point_step


def layout_fields(layout: "str | PointLayout", dtype: np.dtype) -> tuple[list[PointField], int]:
    """The PointFields and point_step of `layout` for points of structured `dtype`."""
    layout = as_layout(layout)
    names = dtype.names or ()
    if layout.kind == "scube":
        fields, offset = [], 0
        for name in names:
            fields.append(PointField(name, offset, _datatype(dtype[name], name)))
            offset += np.dtype(DATATYPE_DTYPES[fields[-1].datatype]).itemsize
        return fields, offset
    base, step = _BASE[layout.kind]
    fields = [PointField(n, o, t) for n, o, t in base]
    if layout.with_extras:
        for name, datatype in EXTRA_FIELDS.items():
            if name in names:
                fields.append(PointField(name, step, datatype))
                step += np.dtype(DATATYPE_DTYPES[datatype]).itemsize
    return fields, step


def pack_points(points: np.ndarray, layout: "str | PointLayout", *, time_offset: float = 0.0) -> PackedPoints:
    """Pack structured `points` (N,) (POINT_DTYPE fields, sensor frame) into `layout`.

    time_offset: seconds from the sweep start to the header stamp, subtracted from point times."""
    layout = as_layout(layout)
    points = np.asarray(points).reshape(-1)
    if points.dtype.names is None:
        raise InputError("pack_points: expected a structured point array (POINT_DTYPE fields)")
    fields, step = layout_fields(layout, points.dtype)
    out_dtype = np.dtype({"names": [f.name for f in fields], "offsets": [f.offset for f in fields],
                          "formats": [DATATYPE_DTYPES[f.datatype] for f in fields], "itemsize": step})
    n = points.shape[0]
    raw = np.zeros(n * step, np.uint8)  # zero padding bytes: the same input gives the same bytes
    out = raw.view(out_dtype) if n else np.zeros(0, out_dtype)
    for f in fields:
        out[f.name] = _value(points, f.name, layout, time_offset, out_dtype[f.name])
    finite = all(np.all(np.isfinite(points[c])) for c in ("x", "y", "z") if c in points.dtype.names)
    return PackedPoints(fields, step, raw, n, bool(finite))


def _datatype(dt: np.dtype, name: str) -> int:
    if dt == np.bool_:
        return UINT8
    key = dt.newbyteorder("<")  # values are converted with astype, so only the kind and size matter
    if key not in _DTYPE_DATATYPES:
        raise InputError(f"point field {name!r}: dtype {dt} has no PointField datatype")
    return _DTYPE_DATATYPES[key]


def _need(points: np.ndarray, name: str, kind: str) -> np.ndarray:
    if name not in points.dtype.names:
        raise InputError(f"point layout {kind!r}: the points have no {name!r} field")
    return points[name]


def _rel_time(points: np.ndarray, layout: PointLayout, time_offset: float) -> np.ndarray:
    """Point times (float64 s) relative to the header stamp."""
    return _need(points, "time", layout.kind).astype(np.float64) - float(time_offset)


def _unsigned_ns(points: np.ndarray, layout: PointLayout, time_offset: float, field: str) -> np.ndarray:
    rel = _rel_time(points, layout, time_offset)
    ns = np.rint(rel * 1e9)
    if ns.size and (ns.min() < 0 or ns.max() > np.iinfo(np.uint32).max):
        raise InputError(f"point layout {layout.kind!r}: {field} is uint32 nanoseconds after the header stamp, but "
                         f"point times run {rel.min():.6f}..{rel.max():.6f} s from it; stamp the message at the "
                         "sweep start (stamp='start')")
    return ns.astype(np.uint32)


def _scaled_uint(values: np.ndarray, scale: float, dtype, hi: int | None = None) -> np.ndarray:
    hi = np.iinfo(dtype).max if hi is None else hi
    v = np.rint(np.nan_to_num(values.astype(np.float64) * scale, nan=0.0, posinf=hi, neginf=0.0))
    return np.clip(v, 0, hi).astype(dtype)


def _value(points: np.ndarray, name: str, layout: PointLayout, time_offset: float, dt: np.dtype) -> np.ndarray:
    """The values of output field `name` (converted from our fields)."""
    kind = layout.kind
    if kind == "scube":
        if name == "time" and time_offset:
            return (points["time"].astype(np.float64) - float(time_offset)).astype(dt)
        return points[name].astype(dt)
    if name in ("x", "y", "z") or (name == "intensity" and dt == np.float32) or name in EXTRA_FIELDS:
        return _need(points, name, kind).astype(dt)
    if name == "time":  # Velodyne: float32 seconds
        v = _need(points, "time", kind)
        return v if not time_offset else _rel_time(points, layout, time_offset).astype(np.float32)
    if name in ("ring", "channel"):
        return _need(points, "ring", kind).astype(dt)
    if name in ("t", "time_stamp"):
        return _unsigned_ns(points, layout, time_offset, name)
    if name == "intensity":  # Autoware uint8
        return _scaled_uint(_need(points, "intensity", kind), layout.intensity_scale, np.uint8)
    if name == "reflectivity":  # Ouster's calibrated reflectivity is 8-bit (0..255) in a uint16 field
        return _scaled_uint(_need(points, "intensity", kind), layout.intensity_scale, np.uint16, hi=255)
    if name == "ambient":
        return np.zeros(points.shape[0], dt)  # no ambient (near-infrared background) light is simulated
    if name == "range":  # Ouster: uint32 millimetres
        return _scaled_uint(_need(points, "range", kind), 1000.0, np.uint32)
    if name == "return_type":
        rid = _need(points, "return_id", kind)
        return np.where(rid == 0, layout.return_types[0], layout.return_types[1]).astype(np.uint8)
    if name == "azimuth":  # CCW from +x like ours, wrapped to [0, 2 pi) as sensors report it
        a = np.mod(_need(points, "azimuth", kind).astype(np.float64), 2 * np.pi)
        return np.where(a >= 2 * np.pi, 0.0, a).astype(np.float32)
    if name == "elevation":
        x, y, z = (points[c].astype(np.float64) for c in ("x", "y", "z"))
        return np.arctan2(z, np.hypot(x, y)).astype(np.float32)
    if name == "distance":
        return _need(points, "range", kind).astype(np.float32)
    raise AssertionError(f"no conversion for field {name!r}")  # pragma: no cover - the tables above
