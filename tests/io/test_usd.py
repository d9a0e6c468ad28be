"""USD export: values read back through pxr, precision at 1e6 m, validation."""

from __future__ import annotations

import os

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")
from pxr import Usd, UsdGeom, UsdVol  # noqa: E402

from scube_sim.io import usd as usd_io  # noqa: E402
from scube_sim.io.usd import GAUSSIANS_PATH, POINTS_PATH, export_usd  # noqa: E402
from scube_sim.transforms import pose_from_xyz_rpy, transform_points  # noqa: E402
from scube_sim.voxsplat import Gaussians, VoxSplat  # noqa: E402

FAR = np.array([1.0e6 + 0.123, -2.0e6 + 0.456, 35.789])  # a float64 origin far from 0


@pytest.fixture
def voxsplat(rng) -> VoxSplat:
    n = 300
    g = Gaussians(
        means=rng.uniform(-20, 20, (n, 3)), scales=rng.uniform(0.01, 0.3, (n, 3)),
        quats=rng.normal(size=(n, 4)), opacities=rng.uniform(0.01, 0.99, n),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32), origin=FAR.copy(),
    )
    labels = rng.integers(0, 26, n)
    return VoxSplat.from_gaussians(g, 0.5, labels=labels)


@pytest.fixture
def lidar(rng) -> np.ndarray:
    n = 500
    p = np.zeros(n, [("x", "f8"), ("y", "f8"), ("z", "f8"), ("intensity", "f4"), ("ring", "u2"),
                     ("time", "f4"), ("label", "i2"), ("return_id", "u1"), ("valid", "?")])
    p["x"], p["y"], p["z"] = (FAR[:, None] + rng.uniform(-50, 50, (3, n)))
    p["intensity"] = rng.random(n)
    p["ring"] = rng.integers(0, 64, n)
    p["time"] = np.linspace(0, 0.1, n)
    p["label"] = rng.integers(-1, 26, n)
    p["return_id"] = rng.integers(0, 3, n)
    p["valid"] = rng.random(n) < 0.9
    return p


def world_positions(prim, local: np.ndarray) -> np.ndarray:
    """Compose local positions with the prim's full transform, in double precision."""
    m = np.array(UsdGeom.XformCache().GetLocalToWorldTransform(prim), dtype=np.float64)
    # Gf matrices are row-vector convention: p_world = [p 1] @ M
    return local.astype(np.float64) @ m[:3, :3] + m[3, :3]


def validation_errors(stage) -> list[str]:
    from pxr import UsdValidation

    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    return [f"{e.GetType()} {e.GetName()}: {e.GetMessage()}" for e in errors]


@pytest.mark.parametrize("suffix, magic", [(".usda", b"#usda 1.0"), (".usdc", b"PXR-USDC"), (".usd", b"PXR-USDC")])
def test_gaussians_roundtrip(tmp_path, voxsplat, suffix, magic):
    path = export_usd(tmp_path / f"scene{suffix}", voxsplat=voxsplat)
    assert path.read_bytes()[: len(magic)] == magic
    assert os.listdir(tmp_path) == [path.name]  # no temporary left behind
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == "/World"

    g = voxsplat.gaussians()
    pf = UsdVol.ParticleField3DGaussianSplat(stage.GetPrimAtPath(GAUSSIANS_PATH))
    assert pf and pf.GetPrim().GetTypeName() == "ParticleField3DGaussianSplat"
    pos = np.asarray(pf.GetPositionsAttr().Get())
    assert pos.dtype == np.float32 and np.abs(pos).max() < 50  # local, small
    # positions composed through the double-precision translate: mm precision at 1e6 m
    np.testing.assert_allclose(world_positions(pf.GetPrim(), pos), g.means + g.origin, rtol=0, atol=1e-5)
    op = pf.GetOrderedXformOps()
    assert [o.GetOpName() for o in op] == ["xformOp:translate"]
    assert op[0].GetPrecision() == UsdGeom.XformOp.PrecisionDouble
    np.testing.assert_array_equal(np.array(op[0].Get()), voxsplat.origin)

    quats = pf.GetOrientationsAttr().Get()
    first = quats[0]  # Gf.Quatf: real part is w
    q0 = g.quats[0]
    assert first.GetReal() == pytest.approx(q0[0], abs=1e-7)
    np.testing.assert_allclose(list(first.GetImaginary()), q0[1:], atol=1e-7)
    wxyz = np.array([[q.GetReal(), *q.GetImaginary()] for q in quats])
    np.testing.assert_allclose(wxyz, g.quats, atol=1e-7)
    np.testing.assert_allclose(np.asarray(pf.GetScalesAttr().Get()), g.scales, rtol=1e-7)
    np.testing.assert_allclose(np.asarray(pf.GetOpacitiesAttr().Get()), g.opacities, rtol=1e-7)
    assert pf.GetRadianceSphericalHarmonicsDegreeAttr().Get() == 0
    np.testing.assert_array_equal(np.asarray(pf.GetRadianceSphericalHarmonicsCoefficientsAttr().Get()), g.sh_dc)
    np.testing.assert_allclose(np.asarray(pf.GetDisplayColorPrimvar().Get()), g.colors)
    labels = UsdGeom.PrimvarsAPI(pf.GetPrim()).GetPrimvar("label")
    np.testing.assert_array_equal(np.asarray(labels.Get()), voxsplat.labels[g.voxel])
    # the authored extent bounds every 3-sigma ellipsoid
    ext = np.asarray(pf.GetExtentAttr().Get())
    assert np.all(ext[0] <= pos.min(0)) and np.all(ext[1] >= pos.max(0))
    assert validation_errors(stage) == []


def test_usda_text_is_wxyz(tmp_path):
    q = np.array([[0.5, 0.5, -0.5, 0.5]])  # w x y z, all distinct in sign pattern
    g = Gaussians(np.zeros((1, 3)), np.ones((1, 3)), q, np.ones(1), np.zeros((1, 3), np.float32))
    text = export_usd(tmp_path / "q.usda", gaussians=g).read_text()
    assert "quatf[] orientations = [(0.5, 0.5, -0.5, 0.5)]" in text


def test_gaussians_plain(tmp_path, rng):
    n = 10
    g = Gaussians(rng.normal(size=(n, 3)), np.full((n, 3), 0.2), np.tile([1.0, 0, 0, 0], (n, 1)),
                  np.full(n, 0.5), np.zeros((n, 3), np.float32), origin=np.array([5.0, 6.0, 7.0]))
    stage = Usd.Stage.Open(str(export_usd(tmp_path / "g.usdc", gaussians=g)))
    prim = stage.GetPrimAtPath(GAUSSIANS_PATH)
    pos = np.asarray(UsdVol.ParticleField3DGaussianSplat(prim).GetPositionsAttr().Get())
    np.testing.assert_allclose(world_positions(prim, pos), g.means + g.origin, atol=1e-6)
    assert not UsdGeom.PrimvarsAPI(prim).HasPrimvar("label")


def test_points_roundtrip(tmp_path, lidar):
    xyz = np.stack([lidar["x"], lidar["y"], lidar["z"]], 1)
    path = export_usd(tmp_path / "pts.usda", points={"lidar_top": lidar, "plain": xyz[:5]},
                      point_width=0.03, point_colors={"plain": [1.0, 0.0, 0.0]})
    stage = Usd.Stage.Open(str(path))
    geom = UsdGeom.Points(stage.GetPrimAtPath(f"{POINTS_PATH}/lidar_top"))
    local = np.asarray(geom.GetPointsAttr().Get())
    assert np.abs(local).max() < 60
    np.testing.assert_allclose(world_positions(geom.GetPrim(), local), xyz, rtol=0, atol=1e-5)
    assert list(geom.GetWidthsAttr().Get()) == [pytest.approx(0.03)]
    assert geom.GetWidthsInterpolation() == UsdGeom.Tokens.constant
    pv = UsdGeom.PrimvarsAPI(geom.GetPrim())
    for field in ("intensity", "ring", "time", "label", "return_id", "valid"):
        p = pv.GetPrimvar(field)
        assert p and p.GetInterpolation() == UsdGeom.Tokens.vertex, field
        np.testing.assert_array_equal(np.asarray(p.Get()), lidar[field], err_msg=field)
        assert p.GetAttr().GetCustomDataByKey("scube_sim:dtype") == lidar.dtype[field].str
    assert str(pv.GetPrimvar("ring").GetTypeName()) == "uint[]"  # USD has no uint16: widened
    plain = UsdGeom.Points(stage.GetPrimAtPath(f"{POINTS_PATH}/plain"))
    color = plain.GetDisplayColorPrimvar()
    assert color.GetInterpolation() == UsdGeom.Tokens.constant and tuple(color.Get()[0]) == (1, 0, 0)
    assert validation_errors(stage) == []


def test_points_pose_and_names(tmp_path, rng):
    sensor = rng.normal(0, 10, (20, 3))
    pose = pose_from_xyz_rpy(FAR, [1, -2, 30])
    path = export_usd(tmp_path / "p.usda", points={"front-left": sensor}, points_poses={"front-left": pose})
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath(f"{POINTS_PATH}/front_left")
    assert prim.GetCustomDataByKey("scube_sim:name") == "front-left"
    local = np.asarray(UsdGeom.Points(prim).GetPointsAttr().Get())
    np.testing.assert_allclose(world_positions(prim, local), transform_points(pose, sensor), atol=1e-5)


def test_everything_together_validates(tmp_path, voxsplat, lidar):
    path = export_usd(tmp_path / "all.usdc", voxsplat=voxsplat, points={"lidar": lidar})
    stage = Usd.Stage.Open(str(path))
    assert validation_errors(stage) == []
    assert [p.GetPath().pathString for p in stage.Traverse()] == [
        "/World", GAUSSIANS_PATH, POINTS_PATH, f"{POINTS_PATH}/lidar"]


def test_validator_sees_problems(tmp_path):
    """The validation used above does report errors (so an empty list means something)."""
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.Xform.Define(stage, "/World")
    names = " ".join(validation_errors(stage))
    assert "MissingDefaultPrim" in names and "MissingUpAxisMetadata" in names


def test_bad_arguments(tmp_path, voxsplat):
    with pytest.raises(ValueError, match="unknown USD suffix"):
        export_usd(tmp_path / "a.usdz", voxsplat=voxsplat)
    with pytest.raises(ValueError, match="not both"):
        export_usd(tmp_path / "a.usda", voxsplat=voxsplat, gaussians=voxsplat.gaussians())
    with pytest.raises(ValueError, match="no field 'z'"):
        export_usd(tmp_path / "a.usda", points={"p": np.zeros(3, [("x", "f4"), ("y", "f4")])})
    with pytest.raises(ValueError, match="not in points"):
        export_usd(tmp_path / "a.usda", points={}, point_colors={"p": [1, 1, 1]})
    assert os.listdir(tmp_path) == []


def test_export_is_atomic(tmp_path, voxsplat, monkeypatch):
    target = export_usd(tmp_path / "s.usda", voxsplat=voxsplat)
    before = target.read_bytes()
    seen = []

    def crash(src, dst):  # the USD-suffixed temporary is fully written; fail before any rename
        seen.append(os.path.exists(src))
        raise OSError("crash")

    monkeypatch.setattr(usd_io.os, "replace", crash)
    with pytest.raises(OSError, match="crash"):
        export_usd(target, gaussians=voxsplat.gaussians().subset(slice(0, 3)))
    monkeypatch.undo()
    assert seen == [True]
    assert target.read_bytes() == before
    assert os.listdir(tmp_path) == ["s.usda"]
