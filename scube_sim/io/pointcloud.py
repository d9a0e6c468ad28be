"""Point-cloud files: PCD v0.7 (DATA ascii / binary / binary_compressed), PLY, KITTI .bin, .npz.

A point cloud is a numpy *structured* array of shape (N,) with any scalar fields, e.g. the LiDAR
output ``x y z intensity`` (float32) ``ring`` (uint16) ``time`` ``range`` ``azimuth`` (float32)
``label`` (int16) ``column`` (int32) ``return_id`` (uint8). Positions are metres in whatever frame
the caller chose (the files carry no frame). A plain (N, 3) or (N, 4) array is accepted as
``x y z [intensity]``.

Every writer goes through `atomic_path`, so a reader never sees a half-written file. Readers raise
ValueError naming the file for malformed or truncated input.
"""

from __future__ import annotations

import json
import struct
import zipfile
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from ..atomic import atomic_path
from ..errors import InputError
from ..transforms import check_pose, rotmat_to_quat

__all__ = [
    "as_structured", "write_pcd", "read_pcd", "pcd_header", "write_ply_points", "read_ply_points",
    "write_kitti_bin", "read_kitti_bin", "write_npz", "read_npz", "write_points", "read_points",
]

NPZ_FORMAT = "scube_sim.points"
NPZ_VERSION = 1


def as_structured(points: np.ndarray) -> np.ndarray:
    """Return `points` as a 1-D structured array; (N, 3)/(N, 4) become ``x y z [intensity]``."""
    points = np.asarray(points)
    if points.dtype.names is not None:
        if points.ndim != 1:
            points = points.reshape(-1)
        return points
    if points.ndim == 2 and points.shape[1] in (3, 4) and points.dtype.kind in "fiu":
        names = ["x", "y", "z", "intensity"][: points.shape[1]]
        dt = points.dtype if points.dtype.kind == "f" else np.dtype(np.float64)
        out = np.empty(points.shape[0], [(n, dt) for n in names])
        for i, n in enumerate(names):
            out[n] = points[:, i]
        return out
    raise InputError(f"points: expected a structured array or an (N, 3)/(N, 4) array, "
                     f"got dtype {points.dtype} shape {points.shape}")


def _field_items(points: np.ndarray):
    """(name, base dtype, shape) of each field, in order."""
    for name in points.dtype.names:
        dt = points.dtype.fields[name][0]
        yield name, dt.base, dt.shape


# --- PCD ------------------------------------------------------------------------------------

_PCD_TYPES = {("F", 4): np.float32, ("F", 8): np.float64,
              ("U", 1): np.uint8, ("U", 2): np.uint16, ("U", 4): np.uint32, ("U", 8): np.uint64,
              ("I", 1): np.int8, ("I", 2): np.int16, ("I", 4): np.int32, ("I", 8): np.int64}


def _pcd_type(name: str, dt: np.dtype) -> tuple[str, np.dtype]:
    """PCD TYPE letter and the little-endian dtype a field is stored as."""
    if dt.kind == "b":
        return "U", np.dtype("<u1")
    if dt.kind == "f" and dt.itemsize == 2:  # PCD has no half floats; float32 holds them exactly
        return "F", np.dtype("<f4")
    letter = {"f": "F", "u": "U", "i": "I"}.get(dt.kind)
    if letter is None or (letter, dt.itemsize) not in _PCD_TYPES:
        raise InputError(f"write_pcd: field {name!r} has dtype {dt}, which PCD cannot store "
                         f"(supported: float32/64, int8..64, uint8..64, bool)")
    return letter, np.dtype(_PCD_TYPES[(letter, dt.itemsize)]).newbyteorder("<")


def _viewpoint_values(viewpoint) -> list[float]:
    """VIEWPOINT as tx ty tz qw qx qy qz from 7 numbers or a (4, 4) sensor pose."""
    if viewpoint is None:
        return [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    v = np.asarray(viewpoint, dtype=np.float64)
    if v.shape == (4, 4):

        check_pose(v, "viewpoint")
        return [*v[:3, 3], *rotmat_to_quat(v[:3, :3])]
    if v.shape == (7,) and np.all(np.isfinite(v)):
        return v.tolist()
    raise InputError(f"viewpoint: expected 7 finite numbers (tx ty tz qw qx qy qz) or a (4, 4) pose, "
                     f"got shape {v.shape}")


def _pcd_layout(points: np.ndarray):
    """Header columns and the packed little-endian dtype of the binary data."""
    fields, sizes, types, counts, packed = [], [], [], [], []
    for name, base, shape in _field_items(points):
        if not name or any(c.isspace() for c in name) or name == "_":
            raise InputError(f"write_pcd: field name {name!r} cannot be written to PCD "
                             f"(no whitespace; '_' is PCL's padding marker)")
        if len(shape) > 1:
            raise InputError(f"write_pcd: field {name!r} has shape {shape}; PCD stores scalars or 1-D counts")
        letter, st = _pcd_type(name, base)
        count = int(np.prod(shape)) if shape else 1
        fields.append(name)
        sizes.append(st.itemsize)
        types.append(letter)
        counts.append(count)
        packed.append((name, st, shape) if shape else (name, st))
    return fields, sizes, types, counts, np.dtype(packed)  # np.dtype(list) is packed (no padding)


def _pcd_body(points: np.ndarray, packed: np.dtype) -> bytes:
    out = np.empty(points.shape, dtype=packed)
    for name in packed.names:
        out[name] = points[name]
    return out.tobytes()


def write_pcd(path: str | Path, points: np.ndarray, *, viewpoint=None, data: str = "binary") -> Path:
    """Write binary PCD v0.7 with every field of `points`.

    points: structured (N,) (unorganised, HEIGHT 1) or (H, W) (organised, e.g. a range image).
    viewpoint: sensor pose in the points' frame, as 7 numbers ``tx ty tz qw qx qy qz`` or a
    (4, 4) matrix; default identity. bool is stored as U1, float16 as F4 (values exact).
    data: ``binary`` (rows of packed fields) or ``binary_compressed`` (PCL's LZF layout: the
    fields one after another, each for all points, LZF-compressed; needs the `lzf` module).
    """
    path = Path(path)
    if data not in ("binary", "binary_compressed"):
        raise InputError(f"write_pcd: data: expected 'binary' or 'binary_compressed', got {data!r}")
    points = np.asarray(points)
    if points.dtype.names is None:
        points = as_structured(points)
    if points.ndim not in (1, 2):
        raise InputError(f"write_pcd: points must be (N,) or (H, W), got shape {points.shape}")
    height, width = (1, points.shape[0]) if points.ndim == 1 else points.shape
    fields, sizes, types, counts, packed = _pcd_layout(points)
    vp = " ".join(format(v, ".17g") for v in _viewpoint_values(viewpoint))
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\n"
        "VERSION 0.7\n"
        f"FIELDS {' '.join(fields)}\n"
        f"SIZE {' '.join(map(str, sizes))}\n"
        f"TYPE {' '.join(types)}\n"
        f"COUNT {' '.join(map(str, counts))}\n"
        f"WIDTH {width}\nHEIGHT {height}\nVIEWPOINT {vp}\nPOINTS {width * height}\nDATA {data}\n"
    )
    body = _pcd_body(points, packed) if data == "binary" else _pcd_compressed_body(points, packed)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(body)
    return path


def _lzf():
    try:
        import lzf
    except ImportError:
        raise InputError("PCD 'DATA binary_compressed' needs the LZF codec: pip install python-neo-lzf") from None
    return lzf


def _pcd_compressed_body(points: np.ndarray, packed: np.dtype) -> bytes:
    """PCL's binary_compressed block: uint32 compressed size, uint32 raw size, then LZF of the
    fields laid out one after another (each field's values for all points, row-major)."""
    flat = points.reshape(-1)
    raw = b"".join(np.ascontiguousarray(flat[name], dtype=packed[name].base).tobytes() for name in packed.names)
    if len(raw) >= 1 << 32:
        raise InputError(f"write_pcd: {len(raw)} bytes of point data exceed binary_compressed's 4 GiB limit; "
                         f"use data='binary'")
    if not raw:
        return struct.pack("<II", 0, 0)
    # LZF output can be a little longer than its input (incompressible data): allow for it
    comp = _lzf().compress(raw, len(raw) + len(raw) // 32 + 64)
    return struct.pack("<II", len(comp), len(raw)) + comp


def _parse_pcd_header(path: Path, raw: bytes) -> tuple[dict, int]:
    """Header entries (upper-case keys -> list of tokens) and the byte offset of the data."""
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        nl = raw.find(b"\n", pos)
        if nl < 0:
            raise InputError(f"{path}: malformed PCD header: no DATA line (truncated or not a PCD file)")
        try:
            line = raw[pos:nl].decode("ascii").strip()
        except UnicodeDecodeError:
            raise InputError(f"{path}: malformed PCD header: non-ASCII bytes before the DATA line "
                             f"(not a PCD file?)") from None
        pos = nl + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            return header, pos


def _pcd_spec(path: Path, header: dict):
    """Validate the header; return (names, dtypes, counts, n_points, data kind)."""
    def need(key):
        if key not in header or not header[key]:
            raise InputError(f"{path}: malformed PCD header: missing {key}")
        return header[key]

    def ints(key, vals):
        try:
            out = [int(v) for v in vals]
        except ValueError:
            raise InputError(f"{path}: malformed PCD header: {key} must be integers, got {vals}") from None
        if any(v < 0 for v in out):
            raise InputError(f"{path}: malformed PCD header: {key} must be non-negative, got {vals}")
        return out

    names = need("FIELDS")
    sizes = ints("SIZE", need("SIZE"))
    types = [t.upper() for t in need("TYPE")]
    counts = ints("COUNT", header.get("COUNT") or ["1"] * len(names))
    if not (len(names) == len(sizes) == len(types) == len(counts)):
        raise InputError(f"{path}: malformed PCD header: FIELDS/SIZE/TYPE/COUNT have "
                         f"{len(names)}/{len(sizes)}/{len(types)}/{len(counts)} entries")
    dtypes = []
    for n, s, t in zip(names, sizes, types):
        if (t, s) not in _PCD_TYPES:
            raise InputError(f"{path}: malformed PCD header: field {n!r} has TYPE {t} SIZE {s}")
        dtypes.append(np.dtype(_PCD_TYPES[(t, s)]).newbyteorder("<"))
    width = ints("WIDTH", need("WIDTH")[:1])[0]
    height = ints("HEIGHT", header.get("HEIGHT", ["1"])[:1])[0]
    n = ints("POINTS", header["POINTS"][:1])[0] if "POINTS" in header else width * height
    if n != width * height:
        raise InputError(f"{path}: malformed PCD header: POINTS {n} != WIDTH {width} x HEIGHT {height}")
    kind = need("DATA")[0].lower()
    real = [x for x in names if x != "_"]
    if len(set(real)) != len(real):
        raise InputError(f"{path}: malformed PCD header: duplicate field names in {names}")
    return names, dtypes, counts, n, kind


def pcd_header(path: str | Path) -> dict:
    """The header entries of a PCD file: upper-case key -> list of string tokens."""
    path = Path(path)
    with open(path, "rb") as fh:
        raw = fh.read(1 << 16)  # headers are a few hundred bytes
    return _parse_pcd_header(path, raw)[0]


def read_pcd(path: str | Path) -> np.ndarray:
    """Read a PCD file (DATA ascii, binary or binary_compressed) into a structured (N,) array,
    fields as in the file.

    Fields named ``_`` (PCL's alignment padding) are dropped; COUNT > 1 gives a sub-array field.
    Organised clouds come back flat (row-major); the header is available from `pcd_header`.
    """
    path = Path(path)
    raw = path.read_bytes()
    header, start = _parse_pcd_header(path, raw)
    names, dtypes, counts, n, kind = _pcd_spec(path, header)
    out_dtype = np.dtype([(nm, dt, (c,)) if c != 1 else (nm, dt)
                          for nm, dt, c in zip(names, dtypes, counts) if nm != "_"])

    if kind == "binary":
        offsets = np.cumsum([0] + [dt.itemsize * c for dt, c in zip(dtypes, counts)])
        row = np.dtype({
            "names": [nm for nm in names if nm != "_"],
            "formats": [(dt, (c,)) if c != 1 else dt for nm, dt, c in zip(names, dtypes, counts) if nm != "_"],
            "offsets": [int(o) for nm, o in zip(names, offsets[:-1]) if nm != "_"],
            "itemsize": int(offsets[-1]),
        })
        need = n * row.itemsize
        have = len(raw) - start
        if have < need:
            raise InputError(f"{path}: truncated PCD: {n} points need {need} bytes of data, "
                             f"found {have}")
        data = np.frombuffer(raw, dtype=row, count=n, offset=start)
        out = np.empty(n, out_dtype)
        for nm in out_dtype.names:
            out[nm] = data[nm]
        return out

    if kind == "ascii":
        try:
            tokens = raw[start:].decode("ascii").split()
        except UnicodeDecodeError:
            raise InputError(f"{path}: malformed PCD: non-ASCII bytes in ascii data") from None
        per_point = sum(counts)
        if len(tokens) != n * per_point:
            what = "truncated PCD" if len(tokens) < n * per_point else "malformed PCD"
            raise InputError(f"{path}: {what}: {n} points x {per_point} values need "
                             f"{n * per_point} numbers, found {len(tokens)}")
        table = np.array(tokens, dtype=str).reshape(n, per_point)
        out = np.empty(n, out_dtype)
        col = 0
        for nm, dt, c in zip(names, dtypes, counts):
            if nm != "_":
                cols = table[:, col:col + c]
                try:
                    vals = cols.astype(dt)
                except ValueError:  # integers written as "3.0" by some tools
                    try:
                        vals = cols.astype(np.float64).astype(dt)
                    except ValueError:
                        raise InputError(f"{path}: malformed PCD: field {nm!r} has non-numeric values") from None
                out[nm] = vals if c != 1 else vals[:, 0]
            col += c
        return out

    if kind == "binary_compressed":
        return _read_pcd_compressed(path, raw, start, names, dtypes, counts, n, out_dtype)
    raise InputError(f"{path}: malformed PCD header: unknown DATA kind {kind!r}")


def _read_pcd_compressed(path, raw, start, names, dtypes, counts, n, out_dtype) -> np.ndarray:
    what = "PCD 'DATA binary_compressed'"
    if len(raw) - start < 8:
        raise InputError(f"{path}: truncated {what}: no compressed/uncompressed size words after the header")
    comp_size, raw_size = struct.unpack_from("<II", raw, start)
    sizes = [dt.itemsize * c for dt, c in zip(dtypes, counts)]
    need = n * sum(sizes)
    if raw_size != need:
        raise InputError(f"{path}: malformed {what}: the data block holds {raw_size} bytes, but {n} points of "
                         f"{sum(sizes)} bytes need {need}")
    have = len(raw) - start - 8
    if have < comp_size:
        raise InputError(f"{path}: truncated {what}: {comp_size} compressed bytes announced, {have} present")
    if need == 0:
        data = b""
    else:
        try:
            data = _lzf().decompress(raw[start + 8:start + 8 + comp_size], raw_size)
        except ValueError:
            data = None
        if data is None or len(data) != raw_size:
            raise InputError(f"{path}: corrupt {what}: the LZF data does not decompress to {raw_size} bytes")
    out = np.empty(n, out_dtype)
    pos = 0
    for nm, dt, c, size in zip(names, dtypes, counts, sizes):
        if nm != "_":  # padding fields occupy their block too
            vals = np.frombuffer(data, dtype=dt, count=n * c, offset=pos)
            out[nm] = vals.reshape(n, c) if c != 1 else vals
        pos += n * size
    return out


# --- PLY ------------------------------------------------------------------------------------

def _ply_compatible(points: np.ndarray) -> np.ndarray:
    """Cast fields to the types PLY has: bool -> uint8, float16 -> float32, 64-bit integers to
    32-bit when every value fits (PLY has no 64-bit integers), else ValueError."""
    cols = []
    for name, base, shape in _field_items(points):
        if shape:
            raise InputError(f"write_ply_points: field {name!r} has shape {shape}; PLY vertex "
                             f"properties are scalars")
        a = points[name]
        if base.kind == "b":
            a = a.astype(np.uint8)
        elif base.kind == "f" and base.itemsize == 2:
            a = a.astype(np.float32)
        elif base.kind in "iu" and base.itemsize == 8:
            small = np.dtype(np.int32 if base.kind == "i" else np.uint32)
            info = np.iinfo(small)
            if a.size and (a.min() < info.min or a.max() > info.max):
                raise InputError(f"write_ply_points: field {name!r} ({base}) holds values outside "
                                 f"{small}, and PLY has no 64-bit integers")
            a = a.astype(small)
        elif base.kind not in "fiu" or base.itemsize > 8:
            raise InputError(f"write_ply_points: field {name!r} has dtype {base}, which PLY cannot store")
        cols.append((name, a))
    out = np.empty(points.shape[0], [(n, a.dtype.newbyteorder("<")) for n, a in cols])
    for n, a in cols:
        out[n] = a
    return out


def write_ply_points(path: str | Path, points: np.ndarray) -> Path:
    """Write a binary little-endian PLY with one ``vertex`` element holding every field."""
    path = Path(path)
    data = _ply_compatible(as_structured(points))
    for name in data.dtype.names:
        if not name or any(c.isspace() for c in name):
            raise InputError(f"write_ply_points: field name {name!r} cannot be a PLY property name")
    ply = PlyData([PlyElement.describe(data, "vertex")], text=False, byte_order="<")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            ply.write(fh)
    return path


def read_ply_points(path: str | Path) -> np.ndarray:
    """Read the ``vertex`` element of a PLY file as a structured (N,) array (scalar properties
    only; list properties such as a mesh's are skipped)."""
    path = Path(path)
    try:
        ply = PlyData.read(str(path), mmap=True)  # mmap=False parses row by row: far slower
    except PlyParseError as exc:
        raise InputError(f"{path}: malformed or truncated PLY ({exc})") from None
    if "vertex" not in ply:
        raise InputError(f"{path}: PLY has no 'vertex' element (elements: {[e.name for e in ply.elements]})")
    data = ply["vertex"].data
    keep = [n for n in data.dtype.names if data.dtype[n].kind != "O"]
    out = np.empty(data.shape[0], [(n, data.dtype[n]) for n in keep])
    for n in keep:
        out[n] = data[n]
    return out


# --- KITTI .bin -----------------------------------------------------------------------------

def write_kitti_bin(path: str | Path, points: np.ndarray) -> Path:
    """Write KITTI Velodyne .bin: float32 ``x y z intensity`` per point (N x 16 bytes, little-endian).
    A cloud without an ``intensity`` field gets zeros; other fields are not stored."""
    path = Path(path)
    points = as_structured(points)
    for f in ("x", "y", "z"):
        if f not in points.dtype.names:
            raise InputError(f"write_kitti_bin: points have no field {f!r} (fields: {points.dtype.names})")
    out = np.zeros((points.shape[0], 4), "<f4")
    for i, f in enumerate(("x", "y", "z", "intensity")):
        if f in points.dtype.names:
            out[:, i] = points[f]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(out.tobytes())
    return path


def read_kitti_bin(path: str | Path) -> np.ndarray:
    """Read KITTI Velodyne .bin into a structured (N,) array ``x y z intensity`` float32."""
    path = Path(path)
    raw = path.read_bytes()
    if len(raw) % 16:
        raise InputError(f"{path}: truncated KITTI .bin: {len(raw)} bytes is not a multiple of 16 "
                         f"(4 float32 per point)")
    return np.frombuffer(raw, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")]).copy()


# --- npz ------------------------------------------------------------------------------------

def write_npz(path: str | Path, points: np.ndarray, **meta) -> Path:
    """Write an uncompressed .npz with key ``points`` (the structured array) and one key per
    `meta` entry (numbers, strings, arrays; dicts and lists are stored as JSON text).
    Readable with ``allow_pickle=False``."""
    path = Path(path)
    arrays = {"format": np.array(NPZ_FORMAT), "version": np.array(NPZ_VERSION, np.int32),
              "points": as_structured(points)}
    for key, value in meta.items():
        if key in arrays or key.startswith("json:"):
            raise InputError(f"write_npz: meta key {key!r} is reserved")
        if isinstance(value, (dict, list, tuple)) and not isinstance(value, np.ndarray):
            try:
                arrays[f"json:{key}"] = np.array(json.dumps(value, sort_keys=True))
                continue
            except TypeError:
                pass
        a = np.asarray(value)
        if a.dtype.kind == "O" or a.dtype.hasobject:
            raise InputError(f"write_npz: meta {key!r} ({type(value).__name__}) cannot be stored "
                             f"without pickle; pass numbers, strings, arrays or JSON-able lists/dicts")
        arrays[key] = a
    if arrays["points"].dtype.hasobject:
        raise InputError("write_npz: points have object fields, which need pickle")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:  # a file object: np.savez would append .npz to a str name
            np.savez(fh, **arrays)
    return path


def read_npz(path: str | Path) -> tuple[np.ndarray, dict]:
    """Read a .npz written by `write_npz` -> (points, meta). 0-d meta values come back as Python
    scalars/strings, JSON-stored ones as dicts/lists, others as arrays."""
    path = Path(path)
    try:
        z = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path}: not a readable .npz ({exc})") from None
    if not hasattr(z, "files"):
        raise InputError(f"{path}: a .npy array, not a .npz archive")
    with z:
        if "points" not in z.files:
            raise InputError(f"{path}: no 'points' key (keys: {z.files})")
        try:
            points = z["points"]
            meta = {}
            for key in z.files:
                if key in ("points", "format", "version"):
                    continue
                a = z[key]
                if key.startswith("json:"):
                    meta[key[5:]] = json.loads(str(a))
                else:
                    meta[key] = a.item() if a.ndim == 0 else a
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:  # CRC or short member
            raise InputError(f"{path}: corrupt or truncated .npz ({exc})") from None
    return points, meta


# --- dispatch -------------------------------------------------------------------------------

_WRITERS = {".pcd": write_pcd, ".ply": write_ply_points, ".bin": write_kitti_bin, ".npz": write_npz}


def write_points(path: str | Path, points: np.ndarray) -> Path:
    """Write a point cloud in the format named by the suffix: .pcd .ply .bin (KITTI) .npz."""
    path = Path(path)
    writer = _WRITERS.get(path.suffix.lower())
    if writer is None:
        raise InputError(f"{path}: unknown point-cloud suffix {path.suffix!r}; "
                         f"use one of {sorted(_WRITERS)}")
    return writer(path, points)


def read_points(path: str | Path) -> np.ndarray:
    """Read a point cloud by suffix (.pcd .ply .bin .npz) into a structured (N,) array."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".pcd":
        return read_pcd(path)
    if suffix == ".ply":
        return read_ply_points(path)
    if suffix == ".bin":
        return read_kitti_bin(path)
    if suffix == ".npz":
        return read_npz(path)[0]
    raise InputError(f"{path}: unknown point-cloud suffix {path.suffix!r}; use one of {sorted(_WRITERS)}")
