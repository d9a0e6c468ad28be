"""3DGS PLY reading/writing against the shipped third-party files, and splat import."""

from __future__ import annotations

import os
import shutil
import warnings

import numpy as np
import pytest

from scube_sim.errors import InputError, ScubeSimWarning
from scube_sim.io.ply3dgs import default_voxel_size, read_3dgs_ply, read_3dgs_ply_info, read_splat_file, write_3dgs_ply
from scube_sim.voxsplat import SH_C0, Gaussians
from tests.conftest import require

DONUT = "donut_mip-splatting_fused.ply"
INRIA = "inria3dgs_iteration_7000_point_cloud.ply"


@pytest.fixture(scope="module")
def splat_dir(shared_data):
    return shared_data / "gaussian-splat-ply"


def _sigmoid(x):
    return 1 / (1 + np.exp(-np.asarray(x, np.float64)))


def _raw(path):
    from plyfile import PlyData

    return PlyData.read(str(path))["vertex"].data


def assert_same_gaussians(a: Gaussians, b: Gaussians, pos_atol: float) -> None:
    """Equal to float32 precision; positions compared in the world frame."""
    assert len(a) == len(b)
    np.testing.assert_allclose(a.means + a.origin, b.means + b.origin, rtol=0, atol=pos_atol)
    np.testing.assert_allclose(a.scales, b.scales, rtol=2e-5)
    dot = np.abs(np.sum(a.quats * b.quats, axis=1))  # q and -q are the same rotation
    np.testing.assert_allclose(dot, 1.0, atol=1e-6)
    np.testing.assert_allclose(a.opacities, b.opacities, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(a.sh_dc, b.sh_dc)
    np.testing.assert_array_equal(a.colors, b.colors)


def _pos_atol(g: Gaussians) -> float:
    # one float32 ulp at the largest world coordinate, twice (write + the local/world shift)
    return 2 * float(np.spacing(np.float32(np.abs(g.means + g.origin).max())))


@pytest.mark.parametrize("name, n, degree, n_props", [(DONUT, 45624, 0, 14), (INRIA, 9080, 3, 62)])
def test_counts_and_info(splat_dir, name, n, degree, n_props):
    path = require(splat_dir / name)
    info = read_3dgs_ply_info(path)
    assert (info.num_gaussians, info.sh_degree, len(info.properties)) == (n, degree, n_props)
    g = read_3dgs_ply(path)
    assert len(g) == n
    assert g.means.dtype == np.float64 and g.origin.dtype == np.float64
    assert g.sh_dc.shape == (n, 3) and g.sh_dc.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(g.quats, axis=1), 1.0, atol=1e-12)


def test_donut_ranges_from_readme(splat_dir):
    g = read_3dgs_ply(require(splat_dir / DONUT))
    world = g.means + g.origin
    np.testing.assert_allclose(world.min(0), [-0.103, -0.098, -0.009], atol=6e-4)
    np.testing.assert_allclose(world.max(0), [0.105, 0.110, 0.086], atol=6e-4)
    assert np.median(g.opacities) == pytest.approx(0.65, abs=0.006)
    assert 6.3e-5 < g.scales.min() < 6.5e-5 and 3.3e-2 < g.scales.max() < 3.5e-2
    assert np.median(g.scales) == pytest.approx(5.2e-4, rel=0.02)
    # pink icing, blue sprinkles: colours are in range and not all grey
    assert g.colors.min() >= 0 and g.colors.max() <= 1 and g.colors.std() > 0.05


def test_inria_ranges_from_readme(splat_dir):
    g = read_3dgs_ply(require(splat_dir / INRIA))
    assert np.median(g.opacities) == pytest.approx(0.06, abs=0.005)
    assert np.median(g.scales) == pytest.approx(15, rel=0.05)
    world = g.means + g.origin
    assert 300 < np.abs(world).max() < 1100  # "extent about +-400 units"
    # the local frame is centred on the data, so local coordinates are no larger than the extent
    assert np.abs(g.means).max() <= 0.5 * (world.max(0) - world.min(0)).max() + 1


@pytest.mark.parametrize("name", [DONUT, INRIA])
def test_matches_plyfile_raw_values(splat_dir, name):
    path = require(splat_dir / name)
    v = _raw(path)
    g = read_3dgs_ply(path)
    np.testing.assert_array_equal(g.means + g.origin, np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64))
    np.testing.assert_allclose(g.opacities, _sigmoid(v["opacity"]), rtol=1e-12)
    np.testing.assert_allclose(g.scales, np.exp(np.stack([v[f"scale_{i}"] for i in range(3)], 1).astype(np.float64)),
                               rtol=1e-12)
    q = np.stack([v[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)
    np.testing.assert_allclose(g.quats, q / np.linalg.norm(q, axis=1, keepdims=True), atol=1e-12)
    fdc = np.stack([v[f"f_dc_{i}"] for i in range(3)], 1)
    np.testing.assert_array_equal(g.sh_dc, fdc)
    np.testing.assert_allclose(g.colors, np.clip(0.5 + SH_C0 * fdc, 0, 1), atol=1e-7)


@pytest.mark.parametrize("name", [DONUT, INRIA])
def test_matches_open3d_positions(splat_dir, name):
    o3d = pytest.importorskip("open3d")
    path = require(splat_dir / name)
    pcd = o3d.io.read_point_cloud(str(path))
    g = read_3dgs_ply(path)
    np.testing.assert_allclose(g.means + g.origin, np.asarray(pcd.points), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", [DONUT, INRIA])
def test_roundtrip_read_write_read(splat_dir, tmp_path, name):
    g = read_3dgs_ply(require(splat_dir / name))
    out = write_3dgs_ply(tmp_path / "out.ply", g)
    h = read_3dgs_ply(out)
    assert_same_gaussians(g, h, _pos_atol(g))
    # the written file is the plain Inria layout with normals and no f_rest
    info = read_3dgs_ply_info(out)
    assert info.properties[:6] == ("x", "y", "z", "nx", "ny", "nz") and info.sh_degree == 0
    assert len(info.properties) == 17
    assert all(_raw(out)[p].dtype == np.float32 for p in info.properties)


def _far_gaussians(rng, origin, n=200, spread=20.0) -> Gaussians:
    g = Gaussians(
        means=rng.normal(0, spread, (n, 3)), scales=rng.uniform(0.01, 0.5, (n, 3)),
        quats=rng.normal(size=(n, 4)), opacities=rng.uniform(0, 1, n),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32), origin=np.asarray(origin, np.float64),
    )
    g.quats /= np.linalg.norm(g.quats, axis=1, keepdims=True)
    return g


@pytest.mark.parametrize("origin", [[1e6, -2e6, 30.0], [3.7e6, 6.1e5, -1.2e3], [-9.9e6, 9.9e6, 12.0]])
def test_far_scenes_keep_their_positions_through_a_ply(tmp_path, rng, origin):
    """At 1e6-1e7 m float32 world coordinates step by 0.06-1 m (before: ranges off by up to 11 m
    against the .npz). The writer keeps positions local with the origin in the header: read back,
    every centre is where it was to float32 precision of the *local* numbers (under 10 um here);
    plyfile, a standard reader, loads the same standard layout with the comment beside it."""
    from plyfile import PlyData

    g = _far_gaussians(rng, origin)
    with pytest.warns(ScubeSimWarning, match=r"past what float32 holds .* header comment 'scube_sim_origin'"):
        path = write_3dgs_ply(tmp_path / "far.ply", g)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # our own file: nothing to warn about on reading
        h = read_3dgs_ply(path)
    assert np.abs(h.means).max() < 200  # local, not 1e6
    assert_same_gaussians(g, h, pos_atol=1e-5)
    ply = PlyData.read(str(path))
    (comment,) = ply.comments
    shift = np.array([float(w) for w in comment.split()[1:]])
    assert comment.startswith("scube_sim_origin ") and np.all(shift == np.round(shift))
    v = ply["vertex"].data
    assert v["x"].dtype == np.float32 and np.abs(v["x"]).max() < 200
    np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], 1) + shift, g.means + g.origin, rtol=0, atol=1e-5)
    # what float32 world coordinates would have lost, for comparison
    assert np.abs((g.means + g.origin).astype(np.float32).astype(np.float64) - (g.means + g.origin)).max() > 0.01


def test_a_third_party_far_file_warns_that_it_is_quantised(tmp_path, rng):
    from plyfile import PlyData, PlyElement

    g = _far_gaussians(rng, [0, 0, 0])
    path = write_3dgs_ply(tmp_path / "near.ply", g)
    v = PlyData.read(str(path))["vertex"].data.copy()
    v["x"] += np.float32(3e6)  # a float32 file written at 3e6 m, no origin comment
    PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "far.ply"))
    with pytest.warns(ScubeSimWarning, match=r"far\.ply: float32 positions reach 3e\+06 m .* quantised to 0.25 m"):
        read_3dgs_ply(tmp_path / "far.ply")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_3dgs_ply(path)  # near the origin: silent, and written as plain world coordinates
    assert PlyData.read(str(path)).comments == []


def test_a_bad_origin_comment_is_named(tmp_path, rng):
    g = _far_gaussians(rng, [2e6, 0, 0])
    with pytest.warns(ScubeSimWarning):
        path = write_3dgs_ply(tmp_path / "far.ply", g)
    data = path.read_bytes()
    start = data.index(b"comment scube_sim_origin")
    end = data.index(b"\n", start)
    path.write_bytes(data[:start] + b"comment scube_sim_origin 1 nan" + b" " * (end - start - 30) + data[end:])
    with pytest.raises(InputError, match=r"far\.ply: header comment 'scube_sim_origin': expected three finite"):
        read_3dgs_ply(path)


def test_opacity_extremes_stay_finite(tmp_path):
    g = Gaussians(means=np.zeros((3, 3)), scales=np.full((3, 3), 0.1), quats=np.tile([1.0, 0, 0, 0], (3, 1)),
                  opacities=np.array([0.0, 0.5, 1.0]), sh_dc=np.zeros((3, 3), np.float32))
    h = read_3dgs_ply(write_3dgs_ply(tmp_path / "o.ply", g))
    np.testing.assert_allclose(h.opacities, [0, 0.5, 1], atol=1e-6)


def test_voxsplat_roundtrip(splat_dir, tmp_path):
    path = require(splat_dir / DONUT)
    vs = read_splat_file(path)
    assert vs.num_gaussians == 45624 and vs.metadata["num_dropped"] == 0
    assert vs.metadata["source_sh_degree"] == 0
    g = vs.gaussians()
    src = read_3dgs_ply(path)
    # the VoxSplat holds offsets as atanh(d / r) in float32: positions agree to float32 on the
    # voxel scale (r = 3 voxels), plus the file's own float32 rounding
    tol = 8 * np.finfo(np.float32).eps * (3 * vs.voxel_size) + _pos_atol(src)
    order = np.lexsort((src.means + src.origin).T)
    order_g = np.lexsort((g.means + g.origin).T)
    np.testing.assert_allclose((g.means + g.origin)[order_g], (src.means + src.origin)[order], rtol=0, atol=tol)
    h = read_3dgs_ply(write_3dgs_ply(tmp_path / "vs.ply", g))
    assert_same_gaussians(g, h, tol)


def test_read_splat_file_explicit_voxel_and_cap(splat_dir):
    path = require(splat_dir / DONUT)
    vs = read_splat_file(path, voxel_size=0.02, max_per_voxel=4)
    assert vs.voxel_size == 0.02 and vs.gaussians_per_voxel == 4
    assert vs.metadata["num_dropped"] == 45624 - vs.num_gaussians > 0


def test_default_voxel_size_median_occupancy(splat_dir):
    g = read_3dgs_ply(require(splat_dir / DONUT))
    v = default_voxel_size(g)
    assert 0.1 * 0.21 / 100 < v < 0.21  # somewhere inside a 0.21-unit donut

    def median_at(size):
        _, counts = np.unique(np.floor(g.means / size).astype(np.int64), axis=0, return_counts=True)
        return np.median(counts)

    assert median_at(v) >= 4 and median_at(v / 1.02) < 4 + 1


def test_default_voxel_size_degenerate():
    one = Gaussians(np.zeros((1, 3)), np.ones((1, 3)), np.tile([1.0, 0, 0, 0], (1, 1)), np.ones(1),
                    np.zeros((1, 3), np.float32))
    assert default_voxel_size(one) == 1.0


def test_missing_property_named(tmp_path, splat_dir):
    from plyfile import PlyData, PlyElement

    v = _raw(require(splat_dir / DONUT))[:10]
    keep = [n for n in v.dtype.names if n != "scale_1"]
    arr = np.empty(10, [(n, "f4") for n in keep])
    for n in keep:
        arr[n] = v[n]
    bad = tmp_path / "no_scale_1.ply"
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(bad))
    with pytest.raises(ValueError, match="'scale_1' is missing") as exc:
        read_3dgs_ply(bad)
    assert str(bad) in str(exc.value)


def test_extra_properties_and_no_normals_tolerated(tmp_path, splat_dir):
    from plyfile import PlyData, PlyElement

    v = _raw(require(splat_dir / INRIA))[:50]
    names = [n for n in v.dtype.names if n not in ("nx", "ny", "nz")] + ["semantic"]
    arr = np.zeros(50, [(n, "f8" if n == "x" else "f4") for n in names])  # a float64 x too
    for n in names[:-1]:
        arr[n] = v[n]
    path = tmp_path / "extra.ply"
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(path))
    g = read_3dgs_ply(path)
    assert len(g) == 50 and read_3dgs_ply_info(path).sh_degree == 3
    np.testing.assert_array_equal((g.means + g.origin)[:, 0], v["x"].astype(np.float64))


@pytest.mark.parametrize("cut", [1, 1000, None])
def test_truncated_file(splat_dir, tmp_path, cut):
    src = require(splat_dir / DONUT)
    path = tmp_path / "cut.ply"
    shutil.copy(src, path)
    size = os.path.getsize(path)
    os.truncate(path, 200 if cut is None else size - cut)  # None: inside the header
    with pytest.raises(ValueError) as exc:
        read_3dgs_ply(path)
    assert str(path) in str(exc.value)
    with pytest.raises(ValueError):
        read_splat_file(path)


def test_write_is_atomic(tmp_path, splat_dir, monkeypatch):
    import plyfile

    g = read_3dgs_ply(require(splat_dir / DONUT))
    real_write = plyfile.PlyData.write

    def half_write(self, stream):
        stream.write(b"ply\nformat binary_little_endian 1.0\n")
        raise OSError("disk full")

    monkeypatch.setattr(plyfile.PlyData, "write", half_write)
    with pytest.raises(OSError, match="disk full"):
        write_3dgs_ply(tmp_path / "g.ply", g)
    assert os.listdir(tmp_path) == []
    monkeypatch.setattr(plyfile.PlyData, "write", real_write)


@pytest.mark.parametrize("prop, value", [("rot_2", np.nan), ("scale_0", np.inf), ("x", -np.inf), ("opacity", np.nan),
                                         ("f_dc_1", np.nan)])
def test_non_finite_raw_values_are_refused_before_the_activations_hide_them(tmp_path, prop, value):
    """A NaN quaternion would normalise to the identity and an infinite scale logit clip to a
    10 km Gaussian: the raw property is refused, named with the count and the first vertex."""
    from plyfile import PlyData, PlyElement

    g = Gaussians(means=np.arange(12.0).reshape(4, 3), scales=np.full((4, 3), 0.1),
                  quats=np.tile([1.0, 0, 0, 0], (4, 1)), opacities=np.full(4, 0.5), sh_dc=np.zeros((4, 3), np.float32))
    ok = write_3dgs_ply(tmp_path / "ok.ply", g)
    v = _raw(ok).copy()
    v[prop][[1, 3]] = value
    bad = tmp_path / "bad.ply"
    PlyData([PlyElement.describe(v, "vertex")]).write(str(bad))
    with pytest.raises(InputError, match=rf"bad\.ply: property '{prop}' is NaN or Inf at 2 vertices \(first: vertex 1\)"):
        read_3dgs_ply(bad)
    assert len(read_3dgs_ply(ok)) == 4
