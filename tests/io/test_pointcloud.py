"""Point-cloud writers/readers: PCD, PLY, KITTI .bin, .npz."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from scube_sim.io import pointcloud as pc
from scube_sim.io.pointcloud import (
    pcd_header,
    read_kitti_bin,
    read_npz,
    read_pcd,
    read_ply_points,
    read_points,
    write_kitti_bin,
    write_npz,
    write_pcd,
    write_ply_points,
    write_points,
)
from tests.conftest import require

LIDAR_DTYPE = np.dtype([
    ("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4"), ("ring", "u2"), ("time", "f4"),
    ("range", "f4"), ("azimuth", "f4"), ("label", "i2"), ("column", "i4"), ("return_id", "u1"),
])


@pytest.fixture
def lidar_points(rng) -> np.ndarray:
    n = 1000
    p = np.empty(n, LIDAR_DTYPE)
    p["x"], p["y"], p["z"] = rng.normal(0, 30, (3, n)).astype(np.float32)
    p["intensity"] = rng.random(n, dtype=np.float32)
    p["ring"] = rng.integers(0, 64, n)
    p["time"] = np.linspace(0, 0.1, n, dtype=np.float32)
    p["range"] = np.sqrt(p["x"] ** 2 + p["y"] ** 2 + p["z"] ** 2)
    p["azimuth"] = np.arctan2(p["y"], p["x"])
    p["label"] = rng.integers(-1, 26, n)
    p["column"] = rng.integers(0, 2048, n)
    p["return_id"] = rng.integers(0, 2, n)
    return p


def assert_same_points(a: np.ndarray, b: np.ndarray) -> None:
    assert a.dtype.names == b.dtype.names
    assert a.shape == b.shape
    for name in a.dtype.names:
        assert a.dtype[name].base.newbyteorder("=") == b.dtype[name].base.newbyteorder("="), name
        # bit-exact, NaN payloads and -0.0 included
        x = np.ascontiguousarray(a[name].astype(a[name].dtype.newbyteorder("=")))
        y = np.ascontiguousarray(b[name].astype(b[name].dtype.newbyteorder("=")))
        assert x.tobytes() == y.tobytes(), name


# --- PCD -------------------------------------------------------------------------------------

def test_pcd_roundtrip_and_header(tmp_path, lidar_points):
    path = write_pcd(tmp_path / "a.pcd", lidar_points, viewpoint=[1, 2, 3, 1, 0, 0, 0])
    assert_same_points(read_pcd(path), lidar_points)
    h = pcd_header(path)
    assert h["FIELDS"] == list(LIDAR_DTYPE.names)
    assert h["TYPE"] == ["F", "F", "F", "F", "U", "F", "F", "F", "I", "I", "U"]
    assert h["SIZE"] == ["4", "4", "4", "4", "2", "4", "4", "4", "2", "4", "1"]
    assert h["POINTS"] == ["1000"] and h["DATA"] == ["binary"]
    assert [float(v) for v in h["VIEWPOINT"]] == [1, 2, 3, 1, 0, 0, 0]


def test_pcd_read_by_open3d(tmp_path, lidar_points):
    o3d = pytest.importorskip("open3d")
    path = write_pcd(tmp_path / "a.pcd", lidar_points)
    cloud = o3d.t.io.read_point_cloud(str(path))
    xyz = np.stack([lidar_points[f] for f in "xyz"], 1)
    np.testing.assert_array_equal(cloud.point.positions.numpy(), xyz)
    for field in ("intensity", "ring", "label", "column", "return_id", "time"):
        got = cloud.point[field].numpy().reshape(-1)
        assert got.dtype == lidar_points[field].dtype, field
        np.testing.assert_array_equal(got, lidar_points[field])


def test_pcd_viewpoint_from_pose(tmp_path, lidar_points):
    from scube_sim.transforms import pose_from_xyz_rpy, rotmat_to_quat

    pose = pose_from_xyz_rpy([1e6, -2.5, 3.25], [0, 0, 90])
    path = write_pcd(tmp_path / "a.pcd", lidar_points[:3], viewpoint=pose)
    vp = np.array(pcd_header(path)["VIEWPOINT"], float)
    np.testing.assert_array_equal(vp[:3], pose[:3, 3])
    np.testing.assert_allclose(vp[3:], rotmat_to_quat(pose[:3, :3]), atol=1e-15)


def test_pcd_bool_half_bigendian_subarray(tmp_path):
    dt = np.dtype([("x", ">f8"), ("ok", "?"), ("h", "f2"), ("hist", "<u2", (3,))])
    a = np.zeros(4, dt)
    a["x"] = [1.5, -2, np.nan, 1e300]
    a["ok"] = [True, False, True, True]
    a["h"] = [0.5, 65504, -1, 0]
    a["hist"] = np.arange(12).reshape(4, 3)
    path = write_pcd(tmp_path / "a.pcd", a)
    b = read_pcd(path)
    assert pcd_header(path)["COUNT"] == ["1", "1", "1", "3"]
    np.testing.assert_array_equal(b["x"], a["x"])
    assert b["ok"].dtype == np.uint8 and b["ok"].tolist() == [1, 0, 1, 1]
    assert b["h"].dtype == np.float32 and b["h"].tolist() == a["h"].astype(np.float32).tolist()
    assert b["hist"].shape == (4, 3) and np.array_equal(b["hist"], a["hist"])


def test_pcd_organized(tmp_path, lidar_points):
    grid = lidar_points[:64 * 10].reshape(64, 10)
    path = write_pcd(tmp_path / "o.pcd", grid)
    h = pcd_header(path)
    assert h["WIDTH"] == ["10"] and h["HEIGHT"] == ["64"]
    assert_same_points(read_pcd(path), grid.reshape(-1))


def test_pcd_ascii_and_padding(tmp_path):
    text = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z _ rgb label\nSIZE 4 4 4 1 4 2\nTYPE F F F U U I\n"
        "COUNT 1 1 1 4 1 1\nWIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n"
        "1.5 2 3 0 0 0 0 16711680 -7\nnan 0 -1e3 0 0 0 0 255 12\n"
    )
    (tmp_path / "a.pcd").write_text(text)
    a = read_pcd(tmp_path / "a.pcd")
    assert a.dtype.names == ("x", "y", "z", "rgb", "label")
    assert a["x"][0] == 1.5 and np.isnan(a["x"][1]) and a["z"][1] == -1000
    assert a["rgb"].tolist() == [16711680, 255] and a["label"].tolist() == [-7, 12]


def test_pcd_binary_with_padding_written_by_hand(tmp_path):
    # PCL's PointXYZ layout: x y z then 4 padding bytes
    body = np.zeros(3, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("pad", "<u4")])
    body["x"] = [1, 2, 3]
    header = (b"VERSION .7\nFIELDS x y z _\nSIZE 4 4 4 1\nTYPE F F F U\nCOUNT 1 1 1 4\n"
              b"WIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA binary\n")
    (tmp_path / "p.pcd").write_bytes(header + body.tobytes())
    a = read_pcd(tmp_path / "p.pcd")
    assert a.dtype.names == ("x", "y", "z") and a["x"].tolist() == [1, 2, 3]


@pytest.mark.parametrize("mutate, message", [
    (lambda h: h.replace(b"TYPE F F F F", b"TYPE F F F"), "FIELDS/SIZE/TYPE/COUNT"),
    (lambda h: h.replace(b"POINTS 10", b"POINTS 11"), "POINTS 11 != WIDTH"),
    (lambda h: h.replace(b"WIDTH 10", b"WIDTH ten"), "WIDTH must be integers"),
    (lambda h: h.replace(b"SIZE 4 4 4 4", b"SIZE 4 4 4 3"), "TYPE F SIZE 3"),
    (lambda h: h.replace(b"FIELDS", b"FIELDZ"), "missing FIELDS"),
    (lambda h: h.replace(b"DATA binary", b"DATA binary_compressed"), "binary_compressed"),
    (lambda h: h.replace(b"DATA binary\n", b""), "no DATA line"),
])
def test_pcd_malformed_header(tmp_path, mutate, message):
    pts = np.zeros(10, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4")])
    raw = write_pcd(tmp_path / "good.pcd", pts).read_bytes()
    split = raw.index(b"DATA binary\n") + len(b"DATA binary\n")
    bad = tmp_path / "bad.pcd"
    bad.write_bytes(mutate(raw[:split]) + (raw[split:] if b"DATA" in mutate(raw[:split]) else b""))
    with pytest.raises(ValueError, match=message) as exc:
        read_pcd(bad)
    assert str(bad) in str(exc.value)


def test_pcd_truncated(tmp_path, lidar_points):
    path = write_pcd(tmp_path / "a.pcd", lidar_points)
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(ValueError, match="truncated") as exc:
        read_pcd(path)
    assert str(path) in str(exc.value)


def test_pcd_rejects_unwritable_fields(tmp_path):
    with pytest.raises(ValueError, match="'c'.*complex"):
        write_pcd(tmp_path / "a.pcd", np.zeros(2, [("x", "f4"), ("c", "c8")]))
    with pytest.raises(ValueError, match="'a b'"):
        write_pcd(tmp_path / "a.pcd", np.zeros(2, [("a b", "f4")]))
    assert not list(tmp_path.iterdir())


_SCALARS = ["<f4", ">f4", "<f8", "<u1", "<u2", ">u2", "<u4", "<u8", "i1", "<i2", "<i4", ">i8", "<i8"]
_names = st.from_regex(r"[A-Za-z][A-Za-z0-9_]{0,7}", fullmatch=True)


@st.composite
def structured_arrays(draw):
    names = draw(st.lists(_names, min_size=1, max_size=8, unique=True))
    dt = np.dtype([(n, draw(st.sampled_from(_SCALARS))) for n in names])
    n = draw(st.integers(0, 40))
    return draw(hnp.arrays(dt, n))


@given(structured_arrays())
def test_pcd_roundtrip_property(tmp_path_factory, a):
    path = tmp_path_factory.mktemp("pcd") / "r.pcd"
    write_pcd(path, a)
    assert_same_points(read_pcd(path), a)


# --- PCD binary_compressed (LZF) -----------------------------------------------------------------

def test_pcd_compressed_roundtrip_and_header(tmp_path, lidar_points):
    pytest.importorskip("lzf")
    path = write_pcd(tmp_path / "c.pcd", lidar_points, data="binary_compressed")
    assert pcd_header(path)["DATA"] == ["binary_compressed"]
    assert_same_points(read_pcd(path), lidar_points)
    assert path.stat().st_size < write_pcd(tmp_path / "b.pcd", lidar_points).stat().st_size


def test_pcd_compressed_read_by_open3d(tmp_path, lidar_points):
    pytest.importorskip("lzf")
    o3d = pytest.importorskip("open3d")
    path = write_pcd(tmp_path / "c.pcd", lidar_points, data="binary_compressed")
    cloud = o3d.t.io.read_point_cloud(str(path))
    xyz = np.stack([lidar_points[f] for f in "xyz"], 1)
    np.testing.assert_array_equal(cloud.point.positions.numpy(), xyz)
    for field in ("intensity", "ring", "label", "column", "return_id", "time"):
        got = cloud.point[field].numpy().reshape(-1)
        assert got.dtype == lidar_points[field].dtype, field
        np.testing.assert_array_equal(got, lidar_points[field])


def test_pcd_compressed_read_by_pypcd4(tmp_path, lidar_points):
    pytest.importorskip("lzf")
    pypcd4 = pytest.importorskip("pypcd4")
    path = write_pcd(tmp_path / "c.pcd", lidar_points, data="binary_compressed")
    cloud = pypcd4.PointCloud.from_path(path)
    assert tuple(cloud.fields) == LIDAR_DTYPE.names
    got = cloud.numpy()
    for i, name in enumerate(LIDAR_DTYPE.names):
        np.testing.assert_array_equal(got[:, i], lidar_points[name].astype(np.float64), err_msg=name)


def test_pcd_compressed_written_by_others(tmp_path, lidar_points):
    pytest.importorskip("lzf")
    o3d = pytest.importorskip("open3d")
    xyz = np.stack([lidar_points[f] for f in "xyz"], 1)
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(xyz))
    cloud.point["intensity"] = o3d.core.Tensor(np.ascontiguousarray(lidar_points["intensity"][:, None]))
    path = tmp_path / "o3d.pcd"
    assert o3d.t.io.write_point_cloud(str(path), cloud, write_ascii=False, compressed=True)
    assert pcd_header(path)["DATA"] == ["binary_compressed"]
    a = read_pcd(path)
    np.testing.assert_array_equal(np.stack([a[f] for f in "xyz"], 1), xyz)
    np.testing.assert_array_equal(a["intensity"], lidar_points["intensity"])

    pypcd4 = pytest.importorskip("pypcd4")
    names = ("x", "y", "z", "intensity", "ring", "label")
    pc4 = pypcd4.PointCloud.from_points([lidar_points[n] for n in names], names,
                                        [lidar_points.dtype[n] for n in names])
    pc4.save(tmp_path / "pypcd4.pcd", encoding=pypcd4.Encoding.BINARY_COMPRESSED)
    b = read_pcd(tmp_path / "pypcd4.pcd")
    for n in names:
        np.testing.assert_array_equal(b[n], lidar_points[n], err_msg=n)


def test_pcd_compressed_padding_organised_subarray_and_incompressible(tmp_path, rng):
    pytest.importorskip("lzf")
    a = np.zeros((8, 5), [("x", "<f8"), ("hist", "<u2", (3,)), ("ok", "?")])
    a["x"] = rng.normal(size=(8, 5))  # random bits: LZF cannot shrink them
    a["hist"] = rng.integers(0, 60000, (8, 5, 3))
    a["ok"] = rng.random((8, 5)) > 0.5
    path = write_pcd(tmp_path / "o.pcd", a, data="binary_compressed")
    assert pcd_header(path)["HEIGHT"] == ["8"]
    b = read_pcd(path)
    np.testing.assert_array_equal(b["x"], a["x"].reshape(-1))
    np.testing.assert_array_equal(b["hist"], a["hist"].reshape(-1, 3))
    np.testing.assert_array_equal(b["ok"], a["ok"].reshape(-1))
    # PCL's padding field "_" takes its own block in the field-by-field layout
    import lzf

    n = 3
    blocks = np.array([1, 2, 3], "<f4").tobytes() + bytes(4 * n) + np.array([7, 8, 9], "<i2").tobytes()
    comp = lzf.compress(blocks, len(blocks) + 64)
    header = (b"VERSION .7\nFIELDS x _ label\nSIZE 4 1 2\nTYPE F U I\nCOUNT 1 4 1\n"
              b"WIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA binary_compressed\n")
    (tmp_path / "p.pcd").write_bytes(header + len(comp).to_bytes(4, "little") + len(blocks).to_bytes(4, "little") + comp)
    c = read_pcd(tmp_path / "p.pcd")
    assert c.dtype.names == ("x", "label") and c["x"].tolist() == [1, 2, 3] and c["label"].tolist() == [7, 8, 9]


def test_pcd_compressed_empty(tmp_path):
    empty = np.zeros(0, [("x", "f4"), ("y", "f4"), ("z", "f4")])
    path = write_pcd(tmp_path / "e.pcd", empty, data="binary_compressed")
    assert read_pcd(path).shape == (0,)


@pytest.mark.parametrize("damage, message", [
    (lambda raw, start: raw[:start + 4], "truncated.*size words"),
    (lambda raw, start: raw[:-10], "truncated.*compressed bytes announced"),
    (lambda raw, start: raw[:start + 8] + bytes(len(raw) - start - 8), "corrupt.*LZF"),
    (lambda raw, start: raw[:start + 4] + (1).to_bytes(4, "little") + raw[start + 8:], "holds 1 bytes"),
])
def test_pcd_compressed_damaged(tmp_path, lidar_points, damage, message):
    pytest.importorskip("lzf")
    path = write_pcd(tmp_path / "c.pcd", lidar_points, data="binary_compressed")
    raw = path.read_bytes()
    start = raw.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    path.write_bytes(damage(raw, start))
    with pytest.raises(ValueError, match=message) as exc:
        read_pcd(path)
    assert str(path) in str(exc.value)


def test_pcd_write_rejects_unknown_data_kind(tmp_path, lidar_points):
    with pytest.raises(ValueError, match="'ascii'"):
        write_pcd(tmp_path / "a.pcd", lidar_points, data="ascii")
    assert not list(tmp_path.iterdir())


@given(structured_arrays())
def test_pcd_compressed_roundtrip_property(tmp_path_factory, a):
    pytest.importorskip("lzf")
    path = tmp_path_factory.mktemp("pcdc") / "r.pcd"
    write_pcd(path, a, data="binary_compressed")
    assert_same_points(read_pcd(path), a)


# --- PLY -------------------------------------------------------------------------------------

def test_ply_roundtrip_plyfile(tmp_path, lidar_points):
    from plyfile import PlyData

    path = write_ply_points(tmp_path / "a.ply", lidar_points)
    ply = PlyData.read(str(path))
    assert ply.header.splitlines()[1] == "format binary_little_endian 1.0"
    v = ply["vertex"].data
    assert v.dtype.names == LIDAR_DTYPE.names
    for name in LIDAR_DTYPE.names:
        np.testing.assert_array_equal(v[name], lidar_points[name])
    assert_same_points(read_ply_points(path), lidar_points)


def test_ply_type_mapping(tmp_path):
    a = np.zeros(3, [("x", "f2"), ("ok", "?"), ("id", "i8"), ("big", "u8")])
    a["id"] = [-5, 0, 2**31 - 1]
    b = read_ply_points(write_ply_points(tmp_path / "a.ply", a))
    assert [b.dtype[n].str[1:] for n in b.dtype.names] == ["f4", "u1", "i4", "u4"]
    assert b["id"].tolist() == [-5, 0, 2**31 - 1]
    a["big"][0] = 2**40
    with pytest.raises(ValueError, match="'big'.*64-bit"):
        write_ply_points(tmp_path / "b.ply", a)


def test_ply_truncated(tmp_path, lidar_points):
    path = write_ply_points(tmp_path / "a.ply", lidar_points)
    path.write_bytes(path.read_bytes()[:-7])
    with pytest.raises(ValueError, match="truncated") as exc:
        read_ply_points(path)
    assert str(path) in str(exc.value)


# --- KITTI .bin ------------------------------------------------------------------------------

def test_kitti_bin_roundtrip(tmp_path, lidar_points):
    path = write_kitti_bin(tmp_path / "a.bin", lidar_points)
    raw = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    expected = np.stack([lidar_points[f] for f in ("x", "y", "z", "intensity")], 1)
    np.testing.assert_array_equal(raw, expected)
    back = read_kitti_bin(path)
    assert back.dtype.names == ("x", "y", "z", "intensity")
    np.testing.assert_array_equal(np.stack([back[f] for f in back.dtype.names], 1), expected)


def test_kitti_bin_without_intensity(tmp_path):
    xyz = np.arange(9, dtype=np.float64).reshape(3, 3)
    back = read_kitti_bin(write_kitti_bin(tmp_path / "a.bin", xyz))
    assert back["x"].tolist() == [0, 3, 6] and back["intensity"].tolist() == [0, 0, 0]


def test_kitti_real_file(shared_data, tmp_path):
    src = require(shared_data / "kitti-object-000008" / "000008.bin")
    ref = np.fromfile(src, dtype=np.float32).reshape(-1, 4)
    pts = read_kitti_bin(src)
    assert pts.shape == (17238,)  # README
    np.testing.assert_array_equal(np.stack([pts[f] for f in pts.dtype.names], 1), ref)
    assert 2.85 <= pts["x"].min() and pts["x"].max() <= 76.85  # README: x in [2.9, 76.8] (rounded)
    assert 0 <= pts["intensity"].min() and pts["intensity"].max() <= 1
    # and it survives our writer byte for byte
    assert write_kitti_bin(tmp_path / "k.bin", pts).read_bytes() == src.read_bytes()


def test_kitti_bin_truncated(tmp_path, lidar_points):
    path = write_kitti_bin(tmp_path / "a.bin", lidar_points)
    path.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(ValueError, match="truncated") as exc:
        read_kitti_bin(path)
    assert str(path) in str(exc.value)


# --- npz -------------------------------------------------------------------------------------

def test_npz_roundtrip_with_meta(tmp_path, lidar_points):
    pose = np.eye(4)
    path = write_npz(tmp_path / "a.npz", lidar_points, frame=7, sensor="hdl64e", pose=pose,
                     info={"rings": 64, "names": ["a", "b"]})
    with np.load(path, allow_pickle=False) as z:  # readable without pickle
        assert z["points"].dtype == lidar_points.dtype
    pts, meta = read_npz(path)
    assert_same_points(pts, lidar_points)
    assert meta["frame"] == 7 and meta["sensor"] == "hdl64e"
    np.testing.assert_array_equal(meta["pose"], pose)
    assert meta["info"] == {"rings": 64, "names": ["a", "b"]}


def test_npz_rejects_pickle_only_meta(tmp_path, lidar_points):
    with pytest.raises(ValueError, match="'thing'.*pickle"):
        write_npz(tmp_path / "a.npz", lidar_points, thing=object())
    assert not list(tmp_path.iterdir())


def test_npz_truncated(tmp_path, lidar_points):
    path = write_npz(tmp_path / "a.npz", lidar_points)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(ValueError) as exc:
        read_npz(path)
    assert str(path) in str(exc.value)


# --- dispatch and atomicity ------------------------------------------------------------------

@pytest.mark.parametrize("suffix", [".pcd", ".ply", ".npz"])
def test_write_points_dispatch(tmp_path, lidar_points, suffix):
    path = write_points(tmp_path / f"a{suffix}", lidar_points)
    assert_same_points(read_points(path), lidar_points)


def test_write_points_bin_and_unknown(tmp_path, lidar_points):
    back = read_points(write_points(tmp_path / "a.bin", lidar_points))
    np.testing.assert_array_equal(back["intensity"], lidar_points["intensity"])
    with pytest.raises(ValueError, match=r"unknown point-cloud suffix '\.xyz'"):
        write_points(tmp_path / "a.xyz", lidar_points)


def test_atomic_write_leaves_nothing_on_error(tmp_path, lidar_points, monkeypatch):
    target = tmp_path / "a.pcd"

    def boom(points, packed):
        raise RuntimeError("disk full")

    monkeypatch.setattr(pc, "_pcd_body", boom)  # fails after the header went into the temp file
    with pytest.raises(RuntimeError, match="disk full"):
        write_pcd(target, lidar_points)
    assert os.listdir(tmp_path) == []


def test_atomic_write_keeps_old_file_on_error(tmp_path, lidar_points, monkeypatch):
    target = write_pcd(tmp_path / "a.pcd", lidar_points)
    before = target.read_bytes()
    monkeypatch.setattr(pc, "_pcd_body", lambda p, d: (_ for _ in ()).throw(RuntimeError("x")))
    with pytest.raises(RuntimeError):
        write_pcd(target, lidar_points[:5])
    assert target.read_bytes() == before
    assert os.listdir(tmp_path) == ["a.pcd"]
