"""USD scene export: Gaussians as ``UsdVol.ParticleField3DGaussianSplat``, point clouds as
``UsdGeom.Points``.

Stage conventions: upAxis Z, metersPerUnit 1, default prim ``/World``. Precision: each prim
carries a double-precision ``xformOp:translate`` to its float64 local origin and stores its
positions as float32 relative to it, so scenes at 1e6 m keep sub-millimetre positions (float32
alone resolves only 6 cm there). Quaternions: our arrays are wxyz like ``Gf.Quatf`` and .usda
text, but numpy views of ``Vt.QuatfArray`` are xyzw; the reordering happens only here.

The pieces (`set_stage_metadata`, `add_gaussians`, `add_scene`, `add_points_prim`,
`primvar_type`, `to_vt_array`, `matrix4d`, `write_layer`) are public so that other writers (the
simulator's `UsdSink`) build stages with the same conventions.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ..atomic import atomic_path
from ..errors import InputError
from ..transforms import check_pose, normalize_quat, quat_to_rotmat
from ..voxsplat import Gaussians, VoxSplat
from .pointcloud import as_structured

__all__ = [
    "export_usd", "GAUSSIANS_PATH", "POINTS_PATH", "USD_SUFFIXES", "check_usd_suffix", "set_stage_metadata",
    "add_gaussians", "add_scene", "add_points_prim", "points_extent", "primvar_type", "declare_primvar",
    "to_vt_array", "vec3f", "matrix4d", "write_layer",
]

GAUSSIANS_PATH = "/World/Gaussians"
POINTS_PATH = "/World/Points"
USD_SUFFIXES = (".usda", ".usdc", ".usd")
_SUFFIXES = USD_SUFFIXES
_KSIGMA = 3.0  # extent = the 3-sigma ellipsoids' bounding box


def _pxr() -> SimpleNamespace:
    """pxr's modules, imported on first use (slow to import): `scube_sim.sim` imports this module for its UsdSink, and
    only a run that writes a stage needs USD."""
    from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdVol, Vt

    return SimpleNamespace(Gf=Gf, Sdf=Sdf, Tf=Tf, Usd=Usd, UsdGeom=UsdGeom, UsdVol=UsdVol, Vt=Vt)


def _vt_types():
    pxr = _pxr()
    t, Vt = pxr.Sdf.ValueTypeNames, pxr.Vt
    # USD has no 8/16-bit signed or 16-bit unsigned scalars: those widen to int / uint (exact);
    # the original numpy dtype is kept in the attribute's customData "scube_sim:dtype".
    return {
        ("f", 2): (t.HalfArray, Vt.HalfArray, np.float16), ("f", 4): (t.FloatArray, Vt.FloatArray, np.float32),
        ("f", 8): (t.DoubleArray, Vt.DoubleArray, np.float64),
        ("i", 1): (t.IntArray, Vt.IntArray, np.int32), ("i", 2): (t.IntArray, Vt.IntArray, np.int32),
        ("i", 4): (t.IntArray, Vt.IntArray, np.int32), ("i", 8): (t.Int64Array, Vt.Int64Array, np.int64),
        ("u", 1): (t.UCharArray, Vt.UCharArray, np.uint8), ("u", 2): (t.UIntArray, Vt.UIntArray, np.uint32),
        ("u", 4): (t.UIntArray, Vt.UIntArray, np.uint32), ("u", 8): (t.UInt64Array, Vt.UInt64Array, np.uint64),
        ("b", 1): (t.BoolArray, Vt.BoolArray, np.bool_),
    }


def check_usd_suffix(path: Path) -> str:
    """The lower-case suffix of `path`, which must be a USD one (it picks text or crate)."""
    suffix = path.suffix.lower()
    if suffix not in USD_SUFFIXES:
        raise InputError(f"{path}: unknown USD suffix {path.suffix!r}; use one of {USD_SUFFIXES}")
    return suffix


def set_stage_metadata(stage, *, documentation: str = "Exported by scube_sim", time_codes_per_second=None):
    """upAxis Z, metersPerUnit 1, ``/World`` (an Xform) as the default prim; optionally the
    time base (timeCodesPerSecond, and framesPerSecond the same so playback runs in real time).
    Returns the /World prim."""
    UsdGeom = _pxr().UsdGeom

    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.LinearUnits.meters)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    stage.GetRootLayer().documentation = documentation
    if time_codes_per_second is not None:
        tcps = float(time_codes_per_second)
        if not (np.isfinite(tcps) and tcps > 0):
            raise InputError(f"time_codes_per_second must be finite and > 0, got {time_codes_per_second!r}")
        stage.SetTimeCodesPerSecond(tcps)
        stage.SetFramesPerSecond(tcps)
    return world.GetPrim()


def vec3f(a: np.ndarray):
    """(N, 3) -> Vt.Vec3fArray (float32)."""
    return _pxr().Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a, dtype=np.float32).reshape(-1, 3))


_vec3f = vec3f


def matrix4d(pose: np.ndarray):
    """(4, 4) float64 column-vector pose -> Gf.Matrix4d (row-vector convention: the transpose),
    exact in double precision."""
    return _pxr().Gf.Matrix4d(np.asarray(pose, np.float64).T.tolist())


def _quatf_wxyz(q: np.ndarray):
    xyzw = np.ascontiguousarray(np.roll(np.asarray(q, np.float32), -1, axis=1))
    return _pxr().Vt.QuatfArray.FromNumpy(xyzw)


def primvar_type(dtype, what: str = "field", who: str = "export_usd"):
    """(Sdf value type name, Vt array class, numpy storage dtype) for a numpy scalar dtype."""
    dtype = np.dtype(dtype)
    key = (dtype.kind, dtype.itemsize)
    types = _vt_types()
    if key not in types:
        raise InputError(f"{who}: {what} has dtype {dtype}, which USD primvars cannot hold")
    return types[key]


def to_vt_array(values: np.ndarray):
    """A flat Vt array of the matching (possibly widened, exactly) type."""
    values = np.asarray(values)
    _, vt_array, np_type = primvar_type(values.dtype)
    return vt_array.FromNumpy(np.ascontiguousarray(values, dtype=np_type).reshape(-1))


def declare_primvar(prim, name: str, dtype, interpolation: str, element_size: int = 1,
                    source_name: str | None = None, who: str = "export_usd"):
    """Create primvars:<name> (no value) for values of numpy `dtype`; the original dtype goes to
    the attribute's customData "scube_sim:dtype" (and the field name to "scube_sim:field")."""
    dtype = np.dtype(dtype)
    type_name, _, _ = primvar_type(dtype, f"field {source_name or name!r}", who)
    pv = _pxr().UsdGeom.PrimvarsAPI(prim).CreatePrimvar(name, type_name, interpolation, element_size)
    attr = pv.GetAttr()
    attr.SetCustomDataByKey("scube_sim:dtype", dtype.newbyteorder("=").str)
    if source_name is not None and source_name != name:
        attr.SetCustomDataByKey("scube_sim:field", source_name)
    return pv


def _add_primvar(prim, name: str, values: np.ndarray, interpolation: str, source_name: str | None = None):
    """Author primvars:<name> from a (N,) or (N, k) array (k -> elementSize)."""
    values = np.asarray(values)
    element_size = int(np.prod(values.shape[1:])) if values.ndim > 1 else 1
    pv = declare_primvar(prim, name, values.dtype, interpolation, element_size, source_name)
    pv.Set(to_vt_array(values))
    return pv


def _set_translate(xformable, origin: np.ndarray, pose: np.ndarray | None = None) -> None:
    """xformOpOrder = [transform (the optional pose), translate (the local origin)], doubles."""
    pxr = _pxr()
    Gf, UsdGeom = pxr.Gf, pxr.UsdGeom

    if pose is not None:
        xformable.AddTransformOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Matrix4d(pose.T.tolist()))
    xformable.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, origin)))


def _gaussian_extent(local: np.ndarray, scales: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """(2, 3) bounding box of the k-sigma ellipsoids (exact box of each ellipsoid)."""
    r = quat_to_rotmat(quats)
    half = _KSIGMA * np.sqrt(np.einsum("nij,nj->ni", r**2, scales**2))
    return np.stack([(local - half).min(0), (local + half).max(0)])


def add_gaussians(stage, path: str, g: Gaussians, labels: np.ndarray | None = None,
                  voxel_size: float | None = None):
    """Define `path` as a ParticleField3DGaussianSplat holding `g` (see `export_usd`); returns it."""
    pxr = _pxr()
    UsdGeom, UsdVol, Vt = pxr.UsdGeom, pxr.UsdVol, pxr.Vt

    g.check_finite("export_usd")
    pf = UsdVol.ParticleField3DGaussianSplat.Define(stage, path)
    _set_translate(pf, np.asarray(g.origin, np.float64))
    pf.CreatePositionsAttr(_vec3f(g.means))
    pf.CreateOrientationsAttr(_quatf_wxyz(normalize_quat(g.quats)))
    pf.CreateScalesAttr(_vec3f(g.scales))  # linear std-devs, as the schema asks (not log)
    pf.CreateOpacitiesAttr(Vt.FloatArray.FromNumpy(np.ascontiguousarray(g.opacities, np.float32)))
    # Degree 0: one float3 coefficient per particle, the raw DC term (colour = 0.5 + C0 * c).
    # The schema's fallback degree is 3, so it must be authored.
    pf.CreateRadianceSphericalHarmonicsDegreeAttr(0)
    pf.CreateRadianceSphericalHarmonicsCoefficientsAttr(_vec3f(g.sh_dc))
    prim = pf.GetPrim()
    # For viewers without SH support.
    pf.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(_vec3f(g.colors))
    if labels is not None:
        _add_primvar(prim, "label", np.asarray(labels, np.int16), UsdGeom.Tokens.vertex)
    if len(g):
        pf.CreateExtentAttr(_vec3f(_gaussian_extent(g.means, g.scales, g.quats)))
    if voxel_size is not None:
        prim.SetCustomDataByKey("scube_sim:voxel_size", float(voxel_size))
    return pf


def _add_gaussians(stage, g: Gaussians, labels: np.ndarray | None, voxel_size: float | None):
    return add_gaussians(stage, GAUSSIANS_PATH, g, labels, voxel_size)


def add_scene(stage, path: str, scene):
    """A VoxSplat (with per-Gaussian labels and the voxel size) or Gaussians at `path`; returns
    the ParticleField3DGaussianSplat, or None for any other scene type (nothing authored)."""
    if isinstance(scene, VoxSplat):
        g = scene.gaussians()
        return add_gaussians(stage, path, g, scene.labels[g.voxel], scene.voxel_size)
    if isinstance(scene, Gaussians):
        return add_gaussians(stage, path, scene)
    return None


def add_points_prim(stage, path: str, *, width: float = 0.05, primvars: dict | None = None,
                    extent: bool = True, who: str = "export_usd"):
    """Define `path` as a UsdGeom.Points with constant `width`, an (unset) points attribute,
    optionally an (unset) extent, and vertex primvars declared (no values) from
    `primvars`: name -> numpy dtype. For writers that author values later (e.g. time samples)."""
    pxr = _pxr()
    Tf, UsdGeom, Vt = pxr.Tf, pxr.UsdGeom, pxr.Vt

    geom = UsdGeom.Points.Define(stage, path)
    geom.CreatePointsAttr()
    geom.CreateWidthsAttr(Vt.FloatArray([float(width)]))
    geom.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    if extent:
        geom.CreateExtentAttr()
    for field, dtype in (primvars or {}).items():
        declare_primvar(geom.GetPrim(), Tf.MakeValidIdentifier(field), dtype, UsdGeom.Tokens.vertex,
                        source_name=field, who=who)
    return geom


def points_extent(local: np.ndarray, width: float) -> np.ndarray:
    """(2, 3) float32 box of (N, 3) points padded by half the width; a zero box when N == 0."""
    if len(local) == 0:
        return np.zeros((2, 3), np.float32)
    return np.stack([local.min(0) - width / 2, local.max(0) + width / 2]).astype(np.float32)


def _add_points(stage, name: str, cloud, width: float, color, pose) -> None:
    pxr = _pxr()
    Tf, UsdGeom, Vt = pxr.Tf, pxr.UsdGeom, pxr.Vt

    prim_name = Tf.MakeValidIdentifier(str(name))
    cloud = np.asarray(cloud)
    pts = as_structured(cloud)
    for f in ("x", "y", "z"):
        if f not in pts.dtype.names:
            raise InputError(f"export_usd: point cloud {name!r} has no field {f!r}")
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float64)
    if not np.all(np.isfinite(xyz)):
        raise InputError(f"export_usd: point cloud {name!r} has NaN or Inf positions")
    origin = np.round(0.5 * (xyz.min(0) + xyz.max(0))) if len(xyz) else np.zeros(3)
    local = xyz - origin
    geom = UsdGeom.Points.Define(stage, f"{POINTS_PATH}/{prim_name}")
    _set_translate(geom, origin, None if pose is None else check_pose(pose, f"points_poses[{name!r}]"))
    geom.CreatePointsAttr(_vec3f(local))
    geom.CreateWidthsAttr(Vt.FloatArray([float(width)]))
    geom.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    if len(local):
        geom.CreateExtentAttr(_vec3f(np.stack([local.min(0) - width / 2, local.max(0) + width / 2])))
    prim = geom.GetPrim()
    if str(name) != prim_name:
        prim.SetCustomDataByKey("scube_sim:name", str(name))
    used = {"displayColor"} if color is not None else set()
    for field in pts.dtype.names:
        if field in ("x", "y", "z"):
            continue
        pv_name = Tf.MakeValidIdentifier(field)
        if pv_name in used:
            raise InputError(f"export_usd: point cloud {name!r}: field {field!r} clashes with primvar {pv_name!r}")
        used.add(pv_name)
        _add_primvar(prim, pv_name, pts[field], UsdGeom.Tokens.vertex, source_name=field)
    if color is not None:
        c = np.asarray(color, np.float32)
        if c.shape == (3,):
            geom.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(_vec3f(c[None]))
        elif c.shape == (len(local), 3):
            geom.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(_vec3f(c))
        else:
            raise InputError(f"export_usd: point_colors[{name!r}]: expected (3,) or ({len(local)}, 3), got {c.shape}")


def write_layer(layer, path: str | Path) -> Path:
    """Export `layer` to `path` atomically. USD picks the file format from the suffix, so the
    export goes to a temporary name that keeps it, then moves onto atomic_path's temporary."""
    Tf = _pxr().Tf

    path = Path(path)
    with atomic_path(path) as tmp:
        usd_tmp = tmp.with_name(tmp.name + path.suffix)
        try:
            try:
                ok = layer.Export(str(usd_tmp))
            except Tf.ErrorException as exc:  # a full disk, a folder without write access
                raise OSError(f"{path}: USD export failed: {tf_reason(exc)}") from None
            if not ok:
                raise OSError(f"{path}: USD export failed")
            os.replace(usd_tmp, tmp)
        finally:
            usd_tmp.unlink(missing_ok=True)
    return path


def tf_reason(exc: Exception) -> str:
    """The innermost reason of a pxr Tf error (its messages repeat one 'Error in ... : REASON'
    per layer of the call stack), on one line."""
    text = " ".join(str(exc).split())
    quoted = re.findall(r": '([^']+)'", text)
    return quoted[0] if quoted else (text[:200] or type(exc).__name__)


_write_layer = write_layer


def export_usd(
    path: str | Path,
    *,
    voxsplat: VoxSplat | None = None,
    gaussians: Gaussians | None = None,
    points: dict | None = None,
    point_width: float = 0.05,
    point_colors: dict | None = None,
    points_poses: dict | None = None,
) -> Path:
    """Write a USD stage (.usda text, .usdc or .usd binary crate, by suffix).

    voxsplat / gaussians (at most one): becomes ``/World/Gaussians``, a
    ParticleField3DGaussianSplat with local float32 positions under a double translate to the
    float64 origin; orientations wxyz; linear scales (m); linear opacities; SH degree 0 with
    ``sh_dc`` as the coefficients; ``primvars:displayColor`` = the RGB colour; from a VoxSplat
    also ``primvars:label`` (int, per Gaussian, the voxel's label).
    points: name -> structured (N,) array with x y z (+ any fields) or an (N, 3) array; each
    becomes ``/World/Points/<name>``, a UsdGeom.Points whose other fields are vertex primvars.
    point_width: metres, constant. point_colors: name -> (3,) or (N, 3) RGB in [0, 1].
    points_poses: name -> (4, 4) pose of the cloud's frame in the world (e.g. the sensor pose).
    """
    pxr = _pxr()
    Tf, Usd, UsdGeom = pxr.Tf, pxr.Usd, pxr.UsdGeom

    path = Path(path)
    suffix = check_usd_suffix(path)
    if voxsplat is not None and gaussians is not None:
        raise InputError("export_usd: pass voxsplat or gaussians, not both")
    points = dict(points or {})
    unknown = set(point_colors or {}) - set(points) | set(points_poses or {}) - set(points)
    if unknown:
        raise InputError(f"export_usd: point_colors/points_poses name clouds not in points: {sorted(unknown)}")

    # The in-memory layer's identifier fixes its file format (text or crate) as well.
    stage = Usd.Stage.CreateInMemory(f"scube_sim_export{suffix}")
    set_stage_metadata(stage)

    if voxsplat is not None:
        g = voxsplat.gaussians()
        _add_gaussians(stage, g, voxsplat.labels[g.voxel], voxsplat.voxel_size)
    elif gaussians is not None:
        _add_gaussians(stage, gaussians, None, None)
    if points:
        UsdGeom.Scope.Define(stage, POINTS_PATH)
        seen = {}
        for name, cloud in points.items():
            prim_name = Tf.MakeValidIdentifier(str(name))
            if prim_name in seen:
                raise InputError(f"export_usd: point clouds {seen[prim_name]!r} and {name!r} map to the same prim name")
            seen[prim_name] = name
            _add_points(stage, name, cloud, point_width, (point_colors or {}).get(name),
                        (points_poses or {}).get(name))
    write_layer(stage.GetRootLayer(), path)
    return path
