"""Standard 3D Gaussian Splatting PLY files (the Inria ``train.py`` layout) and splat import.

Layout: binary little-endian element ``vertex`` with float properties
``x y z [nx ny nz] f_dc_0..2 [f_rest_*] opacity scale_0..2 rot_0..3``, where opacity is a logit,
scale is log(std-dev), rot is an unnormalised wxyz quaternion, colour = 0.5 + C0 * f_dc, and
``f_rest`` holds the higher SH bands channel-major (all of R, then G, then B). Positions are in the
file's world frame (scene units; metres for our own files).

Far from the origin float32 positions lose precision (0.25 m steps at 3e6 m). Where world
coordinates reach `FLOAT32_SAFE_M` (float32 steps coarser than 1 mm), `write_3dgs_ply` writes
positions relative to a whole-metre origin stored in the header as
``comment scube_sim_origin X Y Z`` (float64, repr); our reader adds it back, other readers load
the same standard layout, shifted by it (the writer warns). Reading a file without that comment
whose positions reach that far warns that the file itself has quantised them.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from .. import splat_params as sp
from ..atomic import atomic_path
from ..errors import InputError, ScubeSimWarning
from ..transforms import normalize_quat
from ..voxsplat import Gaussians, VoxSplat

# float32 steps at 16384 m are 1.95 mm: the largest power of two where they stay under ~2 mm
FLOAT32_SAFE_M = 16384.0
ORIGIN_COMMENT = "scube_sim_origin"

__all__ = ["SplatPlyInfo", "read_3dgs_ply_info", "read_3dgs_ply", "write_3dgs_ply",
           "default_voxel_size", "read_splat_file"]

REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
            "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
_WRITE_ORDER = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


@dataclass(frozen=True)
class SplatPlyInfo:
    """What a 3DGS PLY holds: vertex count, SH degree (from the number of ``f_rest_*``
    properties: 3 * ((d + 1)^2 - 1)), and all vertex property names in file order."""

    num_gaussians: int
    sh_degree: int
    properties: tuple[str, ...]


def _load_vertex(path: Path):

    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such splat file")
    with open(path, "rb") as fh:
        if fh.readline(8).strip() != b"ply":
            raise InputError(f"{path}: not a PLY file (no 'ply' magic line)")
    try:
        ply = PlyData.read(str(path), mmap=True)  # mmap=False parses row by row: far slower
    except PlyParseError as exc:  # header errors and early end-of-file alike
        raise InputError(f"{path}: malformed or truncated PLY ({exc})") from None
    except (ValueError, TypeError, UnicodeDecodeError) as exc:  # e.g. a negative element count in the header
        raise InputError(f"{path}: malformed PLY header ({exc})") from None
    if "vertex" not in ply:
        raise InputError(f"{path}: PLY has no 'vertex' element (elements: {[e.name for e in ply.elements]})")
    return np.array(ply["vertex"].data), _stored_origin(path, ply.comments)  # a copy: no memory map left open


def _stored_origin(path: Path, comments) -> np.ndarray | None:
    """The ``scube_sim_origin`` header comment as (3,) float64, or None."""
    for c in comments:
        words = c.split()
        if words and words[0] == ORIGIN_COMMENT:
            try:
                o = np.array([float(w) for w in words[1:]], np.float64)
            except ValueError:
                o = np.zeros(0)
            if o.shape != (3,) or not np.all(np.isfinite(o)):
                raise InputError(f"{path}: header comment {ORIGIN_COMMENT!r}: expected three finite numbers, got "
                                 f"{' '.join(words[1:])!r:.80}")
            return o
    return None


def _info(path: Path, names: tuple[str, ...], n: int) -> SplatPlyInfo:
    missing = [p for p in REQUIRED if p not in names]
    if missing:
        raise InputError(f"{path}: not a 3DGS PLY: vertex property {missing[0]!r} is missing "
                         f"(missing: {missing})")
    n_rest = sum(1 for p in names if p.startswith("f_rest_"))
    degree = int(round(np.sqrt(n_rest / 3 + 1))) - 1
    if 3 * ((degree + 1) ** 2 - 1) != n_rest:
        raise InputError(f"{path}: {n_rest} f_rest_* properties is not 3 * ((d + 1)^2 - 1) for any SH degree d")
    return SplatPlyInfo(n, degree, names)


def read_3dgs_ply_info(path: str | Path) -> SplatPlyInfo:
    """Header facts of a 3DGS PLY (reads only the header)."""
    path = Path(path)
    props: list[str] = []
    count, element = None, None
    with open(path, "rb") as fh:
        if fh.readline().strip() != b"ply":
            raise InputError(f"{path}: not a PLY file (no 'ply' magic line)")
        for raw in fh:
            words = raw.decode("ascii", errors="replace").split()
            if not words:
                continue
            if words[0] == "end_header":
                break
            if words[0] == "element" and len(words) == 3:
                element = words[1]
                if element == "vertex":
                    count = int(words[2])
            elif words[0] == "property" and element == "vertex":
                props.append(words[-1])
        else:
            raise InputError(f"{path}: malformed PLY header: no end_header line")
    if count is None:
        raise InputError(f"{path}: PLY has no 'vertex' element")
    return _info(path, tuple(props), count)


def _local_origin(world: np.ndarray) -> np.ndarray:
    """A float64 point near the data: the bounding-box centre rounded to whole units, so
    small scenes keep origin 0 and large coordinates become small local ones."""
    if world.shape[0] == 0:
        return np.zeros(3)
    return np.round(0.5 * (world.min(0) + world.max(0)))


def read_3dgs_ply(path: str | Path) -> Gaussians:
    """Read a 3DGS PLY into activated Gaussians.

    Returns means (N, 3) float64 relative to ``origin`` (a float64 point near the data),
    scales = exp(scale_*) (N, 3), unit wxyz quats, opacities = sigmoid(opacity), sh_dc = f_dc
    (N, 3) float32. Normals and ``f_rest_*`` (view-dependent colour) are dropped; use
    `read_3dgs_ply_info` for the SH degree. Extra properties are ignored; a missing required
    property or a truncated file raises ValueError naming the file.
    """
    path = Path(path)
    v, stored = _load_vertex(path)
    _info(path, tuple(v.dtype.names), v.shape[0])

    def cols(*names):
        return np.stack([v[n].astype(np.float64) for n in names], axis=1)

    # Raw values are checked before the activations, which would hide them: a NaN quaternion
    # normalises to the identity, an infinite scale logit clips to a 10 km Gaussian.
    for name in ("x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
                 "f_dc_0", "f_dc_1", "f_dc_2"):
        bad = ~np.isfinite(v[name])
        if bad.any():
            raise InputError(f"{path}: property {name!r} is NaN or Inf at {int(bad.sum())} vertices "
                             f"(first: vertex {int(np.argmax(bad))})")
    local = cols("x", "y", "z")
    if stored is None:
        _warn_if_quantised(path, local, v)
        stored = np.zeros(3)
    origin = stored + _local_origin(local)
    g = Gaussians(
        means=local - _local_origin(local),
        scales=sp.scales(cols("scale_0", "scale_1", "scale_2")),
        quats=normalize_quat(cols("rot_0", "rot_1", "rot_2", "rot_3")),
        opacities=sp.opacities(v["opacity"]),
        sh_dc=cols("f_dc_0", "f_dc_1", "f_dc_2").astype(np.float32),
        voxel=None, slot=None, origin=origin,
    )
    g.check_finite(str(path))
    _clamp_to_extent(g, str(path))
    return g


def _warn_if_quantised(path: Path, world: np.ndarray, v) -> None:
    reach = float(np.abs(world).max()) if world.size else 0.0
    if reach >= FLOAT32_SAFE_M and v["x"].dtype.itemsize < 8:
        step = float(np.spacing(np.float32(reach)))
        warnings.warn(f"{path}: float32 positions reach {reach:.4g} m from the file's origin, where they are "
                      f"quantised to {step:.3g} m steps: the file cannot hold this scene more precisely "
                      f"(scube-sim's writer stores an origin in the header instead)", ScubeSimWarning, stacklevel=3)


def _clamp_to_extent(g: Gaussians, source: str) -> int:
    """Clamp scales above the scene's extent (the means' bounding-box diagonal, 1 m at least):
    a Gaussian wider than the whole scene is a training failure that would make every ray a
    candidate. Warns with the count (ScubeSimWarning); returns it."""
    if not len(g):
        return 0
    extent = max(float(np.linalg.norm(g.means.max(0) - g.means.min(0))), 1.0)
    big = (g.scales > extent).any(axis=1)
    n = int(big.sum())
    if n:
        g.scales[big] = np.minimum(g.scales[big], extent)
        warnings.warn(f"{source}: {n} of {len(g)} Gaussians are wider than the scene ({extent:.3g} m, the "
                      f"diagonal of their centres' bounding box); clamped to that", ScubeSimWarning, stacklevel=3)
    return n


def write_3dgs_ply(path: str | Path, gaussians: Gaussians) -> Path:
    """Write Gaussians as an Inria-layout 3DGS PLY (SH degree 0, normals zero).

    Positions are float32 world coordinates (means + origin) while those stay within
    `FLOAT32_SAFE_M`; beyond, they are relative to a whole-metre origin kept in the header
    (``comment scube_sim_origin``, see the module doc; warns). Opacity as a logit (clipped to
    [1e-7, 1 - 1e-7] so that 0 and 1 stay finite), scales as logs, quats as unit wxyz.
    """
    path = Path(path)
    g = gaussians
    g.check_finite("write_3dgs_ply")
    n = len(g)
    out = np.zeros(n, [(p, "<f4") for p in _WRITE_ORDER])
    world = g.means + g.origin
    comments = []
    if n and np.abs(world).max() >= FLOAT32_SAFE_M:
        shift = np.round(g.origin) + _local_origin(g.means)  # whole metres, near the data
        local = (g.origin - shift) + g.means  # small numbers first: no float64 cancellation either
        comments.append(f"{ORIGIN_COMMENT} " + " ".join(repr(float(c)) for c in shift))
        half = float(np.abs(local).max())
        lost = (f"; the scene itself spans {2 * half:.4g} m, so float32 still rounds positions to "
                f"{float(np.spacing(np.float32(half))):.3g} m") if half >= FLOAT32_SAFE_M else ""
        warnings.warn(f"{path}: positions reach {float(np.abs(world).max()):.4g} m, past what float32 holds to a "
                      f"millimetre: written relative to the origin ({shift[0]:.0f}, {shift[1]:.0f}, {shift[2]:.0f}) "
                      f"kept in the header comment {ORIGIN_COMMENT!r}; scube-sim reads them back in place, other "
                      f"readers see the scene shifted by that origin{lost}", ScubeSimWarning, stacklevel=2)
        world = local
    for i, p in enumerate("xyz"):
        out[p] = world[:, i]
    op = np.clip(np.asarray(g.opacities, np.float64), 1e-7, 1 - 1e-7)
    out["opacity"] = np.log(op) - np.log1p(-op)
    log_s = np.log(np.clip(np.asarray(g.scales, np.float64), 1e-30, None))
    q = normalize_quat(g.quats)
    for i in range(3):
        out[f"f_dc_{i}"] = g.sh_dc[:, i]
        out[f"scale_{i}"] = log_s[:, i]
    for i in range(4):
        out[f"rot_{i}"] = q[:, i]
    ply = PlyData([PlyElement.describe(out, "vertex")], text=False, byte_order="<", comments=comments)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            ply.write(fh)
    return path


def _median_occupancy(local: np.ndarray, voxel_size: float) -> float:
    ijk = np.floor(local / voxel_size).astype(np.int64)
    ijk -= ijk.min(0)
    dims = ijk.max(0) + 1
    if np.prod(dims.astype(np.float64)) < 2**62:  # one int64 key per voxel: a fast 1-D unique
        keys = np.ravel_multi_index(ijk.T, dims)
        _, counts = np.unique(keys, return_counts=True)
    else:
        _, counts = np.unique(ijk, axis=0, return_counts=True)
    return float(np.median(counts))


def default_voxel_size(g: Gaussians, target: float = 4.0) -> float:
    """The voxel size (scene units) at which the median occupied voxel holds `target` Gaussians.

    Bisection in log space over [extent * 1e-6, 2 * extent] (extent = largest side of the
    bounding box of the centres) for the smallest size whose median occupancy (over occupied
    voxels) reaches `target`, to within 1 %. Median occupancy only grows, in practice, with the
    voxel size. Fewer than `target` Gaussians, or all at one point: the whole extent (or 1.0).
    """
    local = g.means
    if len(g) == 0:
        return 1.0
    extent = float((local.max(0) - local.min(0)).max())
    if extent <= 0 or len(g) < target:
        return extent if extent > 0 else 1.0
    lo, hi = np.log(extent * 1e-6), np.log(2.0 * extent)
    if _median_occupancy(local, float(np.exp(lo))) >= target:
        return float(np.exp(lo))
    while hi - lo > np.log(1.01):
        mid = 0.5 * (lo + hi)
        if _median_occupancy(local, float(np.exp(mid))) >= target:
            hi = mid
        else:
            lo = mid
    return float(np.exp(hi))


def read_splat_file(path: str | Path, voxel_size: float | None = None,
                    max_per_voxel: int | None = None) -> VoxSplat:
    """Import any 3DGS PLY as a VoxSplat by voxelizing the Gaussians' centres.

    voxel_size: in the file's units; None picks `default_voxel_size` (median occupied voxel
    holds about 4 Gaussians). max_per_voxel: M; None keeps every Gaussian (M = the fullest
    voxel's count, so empty slots cost memory on clumpy files; a cap drops the faintest first).
    The SH degree and source go into ``metadata``; ``f_rest`` is not kept.
    """
    path = Path(path)
    g = read_3dgs_ply(path)
    if voxel_size is None:
        voxel_size = default_voxel_size(g)
    vs = VoxSplat.from_gaussians(g, voxel_size, max_per_voxel=max_per_voxel)
    info = read_3dgs_ply_info(path)
    vs.metadata.update({"source": str(path), "source_format": "3dgs_ply",
                        "source_sh_degree": info.sh_degree, "source_num_gaussians": info.num_gaussians,
                        "num_dropped": info.num_gaussians - vs.num_gaussians})
    return vs
