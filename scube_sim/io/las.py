"""LAS 1.4 and LAZ point files (laspy; LAZ through its lazrs backend).

Layout: LAS 1.4, point format 6 (7 when the points carry ``red green blue``), no CRS (our local
frame: right-handed, x forward / y left / z up or whatever frame the caller's points are in).

- Coordinates: int32 ``X = round(x_local / scale)`` with the header offset set to the float64
  `origin`, so ``world = origin + X * scale``. The integers come from the local coordinates
  alone: a large origin (a UTM easting, 10^6 m) never meets float32 points. Default scale
  1 mm, which holds +-2147 km around the origin.
- intensity: LAS's uint16 ``I = round(65535 * clip(intensity / intensity_max, 0, 1))``;
  `intensity_max` (default 1.0, the LiDAR model's scale) is kept in a VLR (user id
  ``scube_sim``, record 1, JSON) and `read_las` maps back ``intensity = I / 65535 * intensity_max``
  (error at most ``intensity_max / 131070``; values outside [0, intensity_max] are clipped).
- return_id (0 first, 1 second) -> ``return_number = return_id + 1``; ``number_of_returns`` =
  the returns sharing the pulse's (ring, column) when both fields exist, else the return number.
- Fields named like a standard LAS dimension (classification, user_data, point_source_id,
  gps_time, scan_angle, scanner_channel, red/green/blue) go there (checked to fit); every other
  field (ring, time, label, instance, range, azimuth, column, ...) becomes an extra-bytes
  dimension of the same name and type (bool as uint8, float16 as float32).

Writes are atomic; the header's creation date is fixed (1970-01-01) unless given, so a file's
bytes depend only on its contents.
"""

from __future__ import annotations

import json
from datetime import date
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..errors import InputError
from .pointcloud import as_structured

__all__ = ["write_las", "read_las", "INTENSITY_SCALE"]

INTENSITY_SCALE = 65535  # LAS intensity is uint16: full scale maps to 65535
VLR_USER_ID = "scube_sim"
VLR_RECORD_ID = 1
FIXED_DATE = date(1970, 1, 1)
# our field -> LAS standard dimension (and the reverse on reading)
_STANDARD = ("classification", "user_data", "point_source_id", "gps_time", "scan_angle", "scanner_channel")
_RGB = ("red", "green", "blue")
_HANDLED = {"x", "y", "z", "intensity", "return_id"}


def _laspy():
    try:
        import laspy
    except ImportError:
        raise InputError("LAS/LAZ files need laspy (and lazrs for .laz): pip install laspy lazrs") from None
    return laspy


def _vector3(value, name: str) -> np.ndarray:
    v = np.broadcast_to(np.asarray(value, np.float64), (3,)).copy()
    if not np.all(np.isfinite(v)):
        raise InputError(f"write_las: {name}: expected finite numbers, got {v.tolist()}")
    return v


def _fits(values: np.ndarray, dt: np.dtype) -> bool:
    if values.size == 0 or dt.kind == "f":
        return True
    if values.dtype.kind == "f" and not np.all(np.isfinite(values) & (values == np.round(values))):
        return False
    info = np.iinfo(dt)
    return bool(values.min() >= info.min and values.max() <= info.max)


def write_las(path: str | Path, points: np.ndarray, *, origin=(0.0, 0.0, 0.0), scale=0.001,
              intensity_max: float = 1.0, point_format: int | None = None, compress: bool | None = None,
              creation_date: date | None = None) -> Path:
    """Write points as LAS 1.4 (or LAZ: `compress`, default by the ``.laz`` suffix).

    points: structured (N,) with x y z (metres, local to `origin`) and any scalar fields, or an
    (N, 3)/(N, 4) array (x y z [intensity]). origin: (3,) float64 metres, stored as the header
    offset. scale: metres per integer unit, one number or (3,). point_format: 6 or 7 (default 7
    when red/green/blue are present, else 6)."""
    laspy = _laspy()
    path = Path(path)
    points = as_structured(points)
    names = points.dtype.names
    for f in "xyz":
        if f not in names:
            raise InputError(f"write_las: points have no field {f!r} (fields: {names})")
    origin = _vector3(origin, "origin")
    scale = _vector3(scale, "scale")
    if np.any(scale <= 0):
        raise InputError(f"write_las: scale must be > 0, got {scale.tolist()}")
    if not (np.isfinite(intensity_max) and intensity_max > 0):
        raise InputError(f"write_las: intensity_max must be a finite number > 0, got {intensity_max}")
    has_rgb = all(c in names for c in _RGB)
    if point_format is None:
        point_format = 7 if has_rgb else 6
    if point_format not in (6, 7):
        raise InputError(f"write_las: point_format must be 6 or 7 (LAS 1.4 with GPS time), got {point_format}")
    compress = path.suffix.lower() == ".laz" if compress is None else bool(compress)

    header = laspy.LasHeader(point_format=point_format, version="1.4")
    header.offsets, header.scales = origin, scale
    header.generating_software = "scube-sim"
    header.creation_date = creation_date or FIXED_DATE
    header.global_encoding.wkt = True  # LAS 1.4 requires it for point formats 6-10
    standard = set(_STANDARD) | (set(_RGB) if point_format == 7 else set())
    extras = []
    for name in names:
        if name in _HANDLED or name in standard:
            continue
        dt = points.dtype[name]
        if dt.shape:
            raise InputError(f"write_las: field {name!r} has shape {dt.shape}; LAS extra bytes hold scalars")
        base = dt.base
        if base.kind == "b":
            base = np.dtype(np.uint8)
        elif base.kind == "f" and base.itemsize == 2:
            base = np.dtype(np.float32)
        if base.kind not in "fiu" or base.itemsize > 8:
            raise InputError(f"write_las: field {name!r} has dtype {dt}, which LAS extra bytes cannot store")
        if len(name) > 32:
            raise InputError(f"write_las: field name {name!r} is longer than LAS's 32 characters")
        extras.append((name, base.newbyteorder("=")))
    header.add_extra_dims([laspy.ExtraBytesParams(name=n, type=t) for n, t in extras])
    header.vlrs.append(laspy.VLR(VLR_USER_ID, VLR_RECORD_ID, "scube-sim field mapping",
                                 json.dumps({"intensity_max": float(intensity_max)}).encode()))

    las = laspy.LasData(header)
    for axis, f, s in zip("XYZ", "xyz", scale):
        local = np.asarray(points[f], np.float64)
        if not np.all(np.isfinite(local)):
            raise InputError(f"write_las: field {f!r} has NaN or Inf, which LAS cannot store")
        q = np.round(local / s)
        if q.size and (q.min() < -2**31 or q.max() > 2**31 - 1):
            raise InputError(f"write_las: {f} spans {local.min():.6g}..{local.max():.6g} m from the origin, past "
                             f"int32 at scale {s:g} m; use a larger scale or an origin nearer the points")
        setattr(las, axis, q.astype(np.int32))
    n = points.shape[0]
    if "intensity" in names:
        inten = np.asarray(points["intensity"], np.float64) / intensity_max
        las.intensity = np.round(np.clip(np.nan_to_num(inten, nan=0.0), 0.0, 1.0) * INTENSITY_SCALE).astype(np.uint16)
    ret = np.ones(n, np.int64)
    if "return_id" in names:
        ret = np.asarray(points["return_id"], np.int64) + 1
        if n and (ret.min() < 1 or ret.max() > 15):
            raise InputError("write_las: return_id must be 0..14 (LAS return numbers 1..15)")
    count = ret.copy()
    if "ring" in names and "column" in names and n:  # returns of one pulse share (ring, column)
        pulse = np.stack([np.asarray(points["ring"], np.int64), np.asarray(points["column"], np.int64)], 1)
        _, inv, counts = np.unique(pulse, axis=0, return_inverse=True, return_counts=True)
        count = np.maximum(counts[inv.reshape(-1)], ret)
    las.return_number = ret.astype(np.uint8)
    las.number_of_returns = np.minimum(count, 15).astype(np.uint8)
    for name in names:
        if name in standard:
            target = las[name]
            values = np.asarray(points[name])
            if not _fits(values, target.dtype):
                raise InputError(f"write_las: field {name!r} holds values that do not fit LAS's {name} "
                                 f"({target.dtype}); rename it to keep it as an extra dimension")
            las[name] = values.astype(target.dtype)
    for name, dt in extras:
        las[name] = np.asarray(points[name]).astype(dt)

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            try:
                las.write(fh, do_compress=compress, laz_backend=laspy.LazBackend.Lazrs if compress else None)
            except laspy.errors.LaspyException as exc:
                raise InputError(f"{path}: cannot write {'LAZ' if compress else 'LAS'} ({exc}); "
                                 f"LAZ needs lazrs: pip install lazrs") from None
    return path


def read_las(path: str | Path, *, world: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Read a LAS/LAZ file -> (points, origin).

    points: structured (N,): x y z float64 metres local to `origin` (the header offset; with
    `world`, absolute and origin zeros), intensity float32 (mapped back, see the module),
    return_id uint8, the standard dimensions that hold any non-zero value (classification, ...),
    then every extra-bytes dimension under its own name and type."""
    laspy = _laspy()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such LAS/LAZ file")
    try:
        las = laspy.read(path)
    except laspy.errors.LaspyException as exc:
        hint = "; .laz needs lazrs: pip install lazrs" if "LazBackend" in str(exc) or "laz" in str(exc).lower() else ""
        raise InputError(f"{path}: not a readable LAS/LAZ file ({exc}){hint}") from None
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"{path}: not a readable LAS/LAZ file ({exc})") from None
    h = las.header
    imax = 1.0
    for vlr in h.vlrs:
        if vlr.user_id == VLR_USER_ID and vlr.record_id == VLR_RECORD_ID:
            try:
                imax = float(json.loads(bytes(vlr.record_data).decode())["intensity_max"])
            except (ValueError, KeyError, TypeError):
                raise InputError(f"{path}: malformed {VLR_USER_ID} VLR (expected JSON with intensity_max)") from None
    origin = np.asarray(h.offsets, np.float64).copy()
    scales = np.asarray(h.scales, np.float64)
    extra = list(las.point_format.extra_dimension_names)
    std_names = set(las.point_format.dimension_names)
    standard = [n for n in (*_STANDARD, *_RGB) if n in std_names and np.any(np.asarray(las[n]) != 0)]
    fields = [("x", np.float64), ("y", np.float64), ("z", np.float64), ("intensity", np.float32),
              ("return_id", np.uint8)]
    fields += [(n, np.asarray(las[n]).dtype) for n in standard]
    fields += [(n, np.asarray(las[n]).dtype) for n in extra]
    out = np.empty(len(las.points), fields)
    for f, axis, s, o in zip("xyz", "XYZ", scales, origin):
        local = np.asarray(las[axis], np.float64) * s
        out[f] = local + o if world else local
    out["intensity"] = np.asarray(las.intensity, np.float64) / INTENSITY_SCALE * imax
    out["return_id"] = np.maximum(np.asarray(las.return_number, np.int64) - 1, 0)
    for n in standard + extra:
        out[n] = np.asarray(las[n])
    return out, (np.zeros(3) if world else origin)
