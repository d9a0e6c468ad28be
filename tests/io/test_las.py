"""LAS 1.4 / LAZ: our writer and reader against laspy's own raw read (integer coordinates, header
scale and offset, uint16 intensity, extra-bytes dimensions) with the expected values computed here
from the documented mappings."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.io.las import INTENSITY_SCALE, read_las, write_las

laspy = pytest.importorskip("laspy")

DTYPE = np.dtype([
    ("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4"), ("ring", "u2"), ("time", "f4"),
    ("range", "f4"), ("azimuth", "f4"), ("label", "i2"), ("instance", "i4"), ("column", "i4"), ("return_id", "u1"),
])
ORIGIN = np.array([512345.678, 4234567.891, 45.25])  # a UTM-sized float64 origin
EXTRAS = ("ring", "time", "range", "azimuth", "label", "instance", "column")


@pytest.fixture
def points(rng):
    n = 2000
    p = np.zeros(n, DTYPE)
    p["x"], p["y"] = rng.uniform(-120, 120, (2, n)).astype(np.float32)
    p["z"] = rng.uniform(-3, 12, n).astype(np.float32)
    p["intensity"] = rng.random(n, dtype=np.float32)
    p["ring"] = rng.integers(0, 64, n)
    p["column"] = rng.integers(0, 2048, n)
    p["time"] = np.linspace(0, 0.1, n, dtype=np.float32)
    p["range"] = np.hypot(p["x"], p["y"])
    p["azimuth"] = np.arctan2(p["y"], p["x"])
    p["label"] = rng.integers(-1, 26, n)
    p["instance"] = rng.integers(0, 40, n)
    # a second return right behind the first in the same pulse
    p[1] = p[0]
    p["return_id"][1] = 1
    return p


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_laspy_reads_what_we_wrote(tmp_path, points, suffix):
    scale = 0.001
    path = write_las(tmp_path / f"a{suffix}", points, origin=ORIGIN, scale=scale)
    las = laspy.read(path)
    h = las.header
    assert (h.version.major, h.version.minor, h.point_format.id) == (1, 4, 6)
    assert h.global_encoding.wkt
    np.testing.assert_array_equal(h.offsets, ORIGIN)
    np.testing.assert_array_equal(h.scales, [scale] * 3)
    for axis, f in zip("XYZ", "xyz"):  # the integers come from the local coordinates alone
        np.testing.assert_array_equal(np.asarray(las[axis]), np.round(points[f].astype(np.float64) / scale))
        world = ORIGIN["xyz".index(f)] + points[f].astype(np.float64)
        assert np.max(np.abs(np.asarray(getattr(las, f)) - world)) <= scale / 2 + 1e-9
    np.testing.assert_array_equal(las.intensity, np.round(points["intensity"].astype(np.float64) * 65535))
    np.testing.assert_array_equal(las.return_number, points["return_id"] + 1)
    assert las.number_of_returns[0] == las.number_of_returns[1] == 2 and np.all(las.number_of_returns[2:] >= 1)
    assert set(EXTRAS) <= set(las.point_format.extra_dimension_names)
    for name in EXTRAS:
        assert np.asarray(las[name]).dtype == points.dtype[name], name
        np.testing.assert_array_equal(np.asarray(las[name]), points[name], err_msg=name)
    if suffix == ".laz":
        assert b"laszip encoded" in path.read_bytes()[:4096]  # LAZ's VLR
        assert path.stat().st_size < write_las(tmp_path / "b.las", points).stat().st_size


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_our_reader_matches_laspys_raw_read(tmp_path, points, suffix):
    path = write_las(tmp_path / f"a{suffix}", points, origin=ORIGIN)
    got, origin = read_las(path)
    las = laspy.read(path)
    np.testing.assert_array_equal(origin, las.header.offsets)
    for axis, f, s in zip("XYZ", "xyz", las.header.scales):
        np.testing.assert_array_equal(got[f], np.asarray(las[axis], np.float64) * s)
        assert np.max(np.abs(got[f] - points[f])) <= 0.0005 + 1e-6
    np.testing.assert_allclose(got["intensity"], points["intensity"], atol=0.5 / 65535 + 1e-7)
    np.testing.assert_array_equal(got["return_id"], points["return_id"])
    for name in EXTRAS:
        np.testing.assert_array_equal(got[name], points[name], err_msg=name)
    assert set(got.dtype.names) == set(DTYPE.names)
    world, zero = read_las(path, world=True)
    np.testing.assert_array_equal(zero, 0)
    np.testing.assert_allclose(world["x"], np.asarray(las.x), rtol=0, atol=1e-9)


def test_intensity_scale_is_recorded_and_clipped(tmp_path):
    p = np.zeros(4, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4")])
    p["intensity"] = [0, 100, 255, 300]  # KITTI-style 0..255, one out of range
    path = write_las(tmp_path / "i.las", p, intensity_max=255.0)
    np.testing.assert_array_equal(laspy.read(path).intensity, [0, round(100 / 255 * 65535), 65535, 65535])
    got, _ = read_las(path)
    np.testing.assert_allclose(got["intensity"], [0, 100, 255, 255], atol=255 / (2 * INTENSITY_SCALE) + 1e-5)


def test_standard_dimensions_and_point_format_7(tmp_path, rng):
    p = np.zeros(5, [("x", "f8"), ("y", "f8"), ("z", "f8"), ("classification", "u1"), ("gps_time", "f8"),
                     ("red", "u2"), ("green", "u2"), ("blue", "u2"), ("flag", "?"), ("h", "f2")])
    p["classification"] = [2, 6, 5, 2, 9]
    p["gps_time"] = 1e9 + np.arange(5) * 0.1
    p["red"], p["green"], p["blue"] = rng.integers(0, 65535, (3, 5))
    p["flag"] = [True, False, True, True, False]
    p["h"] = [0.5, 1, 2, 4, 8]
    path = write_las(tmp_path / "c.las", p)
    las = laspy.read(path)
    assert las.header.point_format.id == 7
    np.testing.assert_array_equal(las.classification, p["classification"])
    np.testing.assert_array_equal(las.gps_time, p["gps_time"])
    np.testing.assert_array_equal(las.red, p["red"])
    np.testing.assert_array_equal(las["flag"], p["flag"].astype(np.uint8))
    assert np.asarray(las["h"]).dtype == np.float32
    got, _ = read_las(path)
    for name in ("classification", "gps_time", "red", "green", "blue"):
        np.testing.assert_array_equal(got[name], p[name], err_msg=name)


def test_plain_array_and_determinism(tmp_path, rng):
    xyz = rng.normal(0, 10, (50, 3))
    a = write_las(tmp_path / "a.las", xyz).read_bytes()
    assert write_las(tmp_path / "b.las", xyz).read_bytes() == a
    got, _ = read_las(tmp_path / "a.las")
    np.testing.assert_allclose(got["x"], xyz[:, 0], atol=0.0005 + 1e-12)


@pytest.mark.parametrize("mutate, kwargs, message", [
    (lambda p: p.__setitem__("x", np.float32(3e6)), {}, r"'?x'?.*past int32 at scale 0.001"),
    (lambda p: p.__setitem__("z", np.nan), {}, "'z' has NaN"),
    (lambda p: None, {"point_format": 3}, "point_format must be 6 or 7"),
    (lambda p: None, {"scale": 0.0}, "scale must be > 0"),
    (lambda p: p.__setitem__("return_id", 20), {}, "return_id must be 0..14"),
])
def test_write_errors_leave_no_file(tmp_path, points, mutate, kwargs, message):
    p = points[:10].copy()
    mutate(p)
    with pytest.raises(ValueError, match=message):
        write_las(tmp_path / "bad.las", p, **kwargs)
    assert not list(tmp_path.iterdir())


def test_fields_that_cannot_be_stored(tmp_path):
    sub = np.zeros(2, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("hist", "u2", (4,))])
    with pytest.raises(ValueError, match="'hist' has shape"):
        write_las(tmp_path / "a.las", sub)
    cls = np.zeros(2, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("classification", "i4")])
    cls["classification"] = [1, 300]
    with pytest.raises(ValueError, match="'classification'.*do not fit"):
        write_las(tmp_path / "a.las", cls)


def test_read_errors_name_the_file(tmp_path):
    bad = tmp_path / "bad.las"
    bad.write_bytes(b"not a las file at all")
    with pytest.raises(ValueError, match="not a readable LAS") as exc:
        read_las(bad)
    assert str(bad) in str(exc.value)
    with pytest.raises(FileNotFoundError, match="no such LAS"):
        read_las(tmp_path / "missing.laz")
