"""Camera images decoded as they are (issue 46): `scube_sim.io.images.read_rgb`, the one reader
every dataset adapter uses. Files are written by PIL and by a PNG writer of our own below (zlib
and struct: 16-bit PNGs PIL cannot write); each expected value is computed from what was written
(a 16-bit value v reads back as v >> 8), and each adapter is given a 16-bit image and a huge one."""

from __future__ import annotations

import os
import shutil
import struct
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

import scube_sim.io.images as images_mod
from scube_sim.cli import app
from scube_sim.datasets import DatasetError, open_dataset
from scube_sim.errors import InputError
from scube_sim.io.images import MAX_PIXELS, read_rgb
from tests.conftest import REPO, one_line_error, shared_data_dir

runner = CliRunner()


# --- an independent PNG writer (any bit depth PNG allows) -----------------------------------------

def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png_bytes(arr: np.ndarray, depth: int = 16) -> bytes:
    """(H, W) grey, (H, W, 2) grey+alpha, (H, W, 3) RGB or (H, W, 4) RGBA -> PNG of `depth` bits
    per channel (8 or 16), filter 0, written from the spec."""
    a = np.asarray(arr)
    h, w = a.shape[:2]
    channels = 1 if a.ndim == 2 else a.shape[2]
    colour_type = {1: 0, 2: 4, 3: 2, 4: 6}[channels]
    rows = a.reshape(h, w * channels).astype(">u2" if depth == 16 else "u1").view(np.uint8).reshape(h, -1)
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows], axis=1).tobytes()
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, depth, colour_type, 0, 0, 0))
            + _chunk(b"IDAT", zlib.compress(raw, 1)) + _chunk(b"IEND", b""))


def header_only_png(w: int, h: int) -> bytes:
    """A PNG that states w x h pixels and holds none: only a reader that decodes from the header
    alone can say anything about it (what a huge camera image looks like to a header check)."""
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + _chunk(b"IDAT", zlib.compress(b"")) + _chunk(b"IEND", b""))


def header_only_jpeg(w: int, h: int) -> bytes:
    """A small real JPEG (PIL) whose SOF0 frame header is patched to state w x h."""
    import io

    buf = io.BytesIO()
    Image.new("RGB", (16, 8), (10, 20, 30)).save(buf, format="JPEG")
    b = bytearray(buf.getvalue())
    at = b.index(b"\xff\xc0")  # SOF0: marker, length (2), precision (1), height (2), width (2)
    b[at + 5:at + 9] = struct.pack(">HH", h, w)
    return bytes(b)


def ramp16(h: int, w: int, channels: int = 3, seed: int = 0) -> np.ndarray:
    """(h, w[, c]) uint16 spanning 0..65535 with every low byte present."""
    rng = np.random.default_rng(seed)
    a = rng.integers(0, 65536, size=(h, w, channels), dtype=np.uint16)
    a.reshape(-1)[:2] = (0, 65535)
    return a[..., 0] if channels == 1 else a


def write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def grey3(g: np.ndarray) -> np.ndarray:
    return np.repeat(np.asarray(g, np.uint8)[..., None], 3, axis=-1)


# --- modes and bit depths -------------------------------------------------------------------------

@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_16_bit_png_of_every_colour_type_reads_as_the_high_byte(tmp_path, channels):
    """grey, grey+alpha, 48-bit RGB, 64-bit RGBA: each channel v -> v >> 8 (never clipped to
    white), alpha dropped."""
    a = ramp16(5, 7, channels)
    got = read_rgb(write(tmp_path / "c.png", png_bytes(a)))
    hi = (a >> 8).astype(np.uint8)
    if channels <= 2:  # grey (+ alpha): the grey level in all three channels
        want = grey3(hi if channels == 1 else hi[..., 0])
    else:  # RGB (+ alpha)
        want = hi[..., :3]
    assert got.dtype == np.uint8 and got.shape == (5, 7, 3)
    np.testing.assert_array_equal(got, want)


def test_16_bit_grey_written_by_pil_reads_as_the_high_byte_in_both_byte_orders(tmp_path):
    """PIL writes uint16 as an I;16 PNG and an I;16B TIFF; PIL's own convert('RGB') clips these
    to 255 (the all-white image of the issue)."""
    g = (np.arange(256 * 3, dtype=np.uint32).reshape(3, 256) * 257 // 3).astype(np.uint16)  # 0 .. 65535
    Image.fromarray(g).save(tmp_path / "g.png")
    Image.fromarray(g.astype(">u2")).save(tmp_path / "gb.tif")
    with Image.open(tmp_path / "g.png") as im, Image.open(tmp_path / "gb.tif") as imb:
        assert (im.mode, imb.mode) == ("I;16", "I;16B")
        assert (np.asarray(im.convert("RGB")) == 255).mean() > 0.9  # what PIL alone makes of it
    for name in ("g.png", "gb.tif"):
        np.testing.assert_array_equal(read_rgb(tmp_path / name), grey3(g >> 8))
    # 8-bit content stored as 16-bit (k * 257) reads back exactly
    k = np.arange(256, dtype=np.uint16).reshape(16, 16)
    Image.fromarray(k * 257).save(tmp_path / "k.png")
    np.testing.assert_array_equal(read_rgb(tmp_path / "k.png"), grey3(k))


def test_32_bit_integer_grey_in_16_bit_range_reads_as_16_bit_and_wider_is_refused(tmp_path):
    g = np.array([[0, 256, 65535], [1000, 40000, 511]], np.int32)
    Image.fromarray(g).save(tmp_path / "i.tif")
    with Image.open(tmp_path / "i.tif") as im:
        assert im.mode == "I"
    np.testing.assert_array_equal(read_rgb(tmp_path / "i.tif"), grey3(g >> 8))
    Image.fromarray(np.array([[0, 70000]], np.int32)).save(tmp_path / "wide.tif")
    with pytest.raises(InputError, match=r"wide\.tif: 32-bit integer pixels from 0 to 70000: not an 8- or 16-bit"):
        read_rgb(tmp_path / "wide.tif")
    Image.fromarray(np.array([[0.0, 0.5]], np.float32)).save(tmp_path / "f.tif")
    with pytest.raises(InputError, match=r"f\.tif: 32-bit float pixels \(PIL mode F\) have no white level"):
        read_rgb(tmp_path / "f.tif")


def test_8_bit_modes(tmp_path):
    rgb = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3) * 3
    alpha = np.full((4, 6), 0, np.uint8)  # fully transparent: the colours are still used as stored
    g = rgb[..., 0]
    cases = {
        "rgb.png": (Image.fromarray(rgb), rgb),
        "rgba.png": (Image.fromarray(np.dstack([rgb, alpha])), rgb),
        "l.png": (Image.fromarray(g), grey3(g)),
        "la.png": (Image.merge("LA", [Image.fromarray(g), Image.fromarray(alpha)]), grey3(g)),
        "bits.png": (Image.fromarray(g > 100), grey3(np.where(g > 100, 255, 0))),
    }
    palette = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [7, 8, 9]], np.uint8)
    idx = (np.arange(24).reshape(4, 6) % 4).astype(np.uint8)
    p = Image.frombytes("P", (6, 4), idx.tobytes())
    p.putpalette(palette.ravel().tolist())
    cases["p.png"] = (p, palette[idx])
    for name, (im, want) in cases.items():
        im.save(tmp_path / name)
        np.testing.assert_array_equal(read_rgb(tmp_path / name), want, err_msg=name)
    with Image.open(tmp_path / "bits.png") as im, Image.open(tmp_path / "p.png") as ip, \
            Image.open(tmp_path / "la.png") as ila:
        assert (im.mode, ip.mode, ila.mode) == ("1", "P", "LA")


def test_cmyk_without_black_is_255_minus_cyan_magenta_yellow_and_full_black_is_black(tmp_path):
    c = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3) * 5
    for k, want in ((0, 255 - c), (255, np.zeros_like(c))):
        cmyk = np.dstack([c, np.full(c.shape[:2], k, np.uint8)])
        Image.frombytes("CMYK", (5, 4), cmyk.tobytes()).save(tmp_path / f"k{k}.tif")
        np.testing.assert_array_equal(read_rgb(tmp_path / f"k{k}.tif"), want)


def test_exif_orientation_is_ignored_pixels_as_stored(tmp_path):
    """A camera's intrinsics describe the stored layout: an orientation tag (6: rotate 90 degrees
    to display) changes nothing."""
    rgb = np.arange(3 * 5 * 3, dtype=np.uint8).reshape(3, 5, 3) * 5
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(rgb).save(tmp_path / "o.png", exif=exif)
    with Image.open(tmp_path / "o.png") as im:
        assert im.getexif()[0x0112] == 6
    np.testing.assert_array_equal(read_rgb(tmp_path / "o.png"), rgb)


def test_a_jpeg_reads_as_pils_own_decode(tmp_path):
    rgb = np.repeat((np.arange(24) * 10).astype(np.uint8)[None, :, None], 16, 0).repeat(3, 2)  # a smooth ramp
    Image.fromarray(rgb).save(tmp_path / "a.jpg", quality=95)
    got = read_rgb(tmp_path / "a.jpg")
    assert got.shape == (16, 24, 3) and np.abs(got.astype(int) - rgb).max() <= 8


# --- huge and unreadable files --------------------------------------------------------------------

@pytest.mark.parametrize(("name", "data", "pixels", "dims"), [
    ("huge.jpg", header_only_jpeg(16000, 12000), 192_000_000, ""),  # PIL's DecompressionBombError range
    ("huge.png", header_only_png(16000, 12000), 192_000_000, ""),
    ("big.png", header_only_png(10000, 8000), 80_000_000, "10000 x 8000 = "),  # above ours, below PIL's
])
def test_a_huge_image_is_refused_from_its_header_naming_file_and_pixels(tmp_path, name, data, pixels, dims):
    path = write(tmp_path / name, data)
    t = time.perf_counter()
    with pytest.raises(InputError) as err:
        read_rgb(path)
    assert time.perf_counter() - t < 1.0
    msg = str(err.value)
    assert type(err.value) is InputError and "\n" not in msg
    assert msg == (f"{path}: image of {dims}{pixels} pixels, more than the {MAX_PIXELS} this reader decodes; "
                   f"refused before decoding it (downscale the image and its intrinsics together)")
    assert "DecompressionBomb" not in msg and "decompression bomb" not in msg.lower()


def test_the_pixel_limit_is_inclusive(tmp_path):
    Image.new("RGB", (10, 10), (1, 2, 3)).save(tmp_path / "a.png")
    assert read_rgb(tmp_path / "a.png", max_pixels=100).shape == (10, 10, 3)
    with pytest.raises(InputError, match=r"a\.png: image of 10 x 10 = 100 pixels, more than the 99 "):
        read_rgb(tmp_path / "a.png", max_pixels=99)


def _truncated_png(tmp_path):
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)).save(tmp_path / "f.png")
    b = (tmp_path / "f.png").read_bytes()
    return b[: len(b) // 2]


@pytest.mark.parametrize(("kind", "make", "needle"), [
    ("text", lambda d: b"hello, not an image\n", "not a readable image (cannot identify image file"),
    ("empty", lambda d: b"", "not a readable image"),
    ("truncated", _truncated_png, "not a readable image (PIL mode RGB: image file is truncated"),
    ("bad crc", lambda d: png_bytes(np.zeros((2, 2), np.uint16))[:29] + b"\0\0\0\0" + png_bytes(
        np.zeros((2, 2), np.uint16))[33:], "not a readable image"),
])
def test_an_unreadable_file_is_one_line_naming_it(tmp_path, kind, make, needle):
    path = write(tmp_path / "x.png", make(tmp_path))
    with pytest.raises(DatasetError) as err:
        read_rgb(path, error=DatasetError)
    assert str(err.value).startswith(f"{path}: {needle}") and "\n" not in str(err.value), str(err.value)
    with pytest.raises(InputError, match=r"nope\.png: no such image file"):
        read_rgb(tmp_path / "nope.png")


def test_no_reader_opens_images_itself():
    """Every file image the package decodes goes through read_rgb (augment's JPEG round trip of
    an in-memory buffer is not a file)."""
    offenders = []
    for py in (REPO / "scube_sim").rglob("*.py"):
        for n, line in enumerate(py.read_text(encoding="utf-8").splitlines(), 1):
            if "Image.open(" in line and py.name != "images.py" and "Image.open(buf)" not in line:
                offenders.append(f"{py.relative_to(REPO)}:{n}")
    assert offenders == []


# --- every adapter that reads camera images -------------------------------------------------------

SHARED = {  # adapter -> (folder under ../shared/data, options): sample 0 is read
    "kitti_object": ("kitti-object-000008", {}),
    "kitti_raw": ("kitti-raw-2011_09_26-udacity", {"poses": "identity"}),
    "kitti360": ("kitti360-2013_05_28-seq", {"poses": "identity", "count": 1}),
    "nuscenes": ("nuscenes-mmdet3d-demo", {}),
    "tri_dgp": ("tri-dgp-test-scene_02", {}),
    "waymo": ("waymo-open-dataset-frame", {}),
}


@pytest.fixture(scope="module")
def own_sets(tmp_path_factory) -> dict:
    """The adapters whose data the tests make: a folder dataset and a worlds dataset."""
    from scube_sim.datasets.folder import write_folder_dataset
    from scube_sim.worlds.dataset import generate_dataset
    from tests.converter.tiny_converter import TINY
    from tests.datasets.test_folder import synthetic_sample

    tmp = tmp_path_factory.mktemp("own")
    write_folder_dataset([synthetic_sample(np.random.default_rng(3))], tmp / "folder")
    generate_dataset(tmp / "worlds", "test", 1, TINY, progress=False)
    return {"folder": (tmp / "folder", {}), "worlds": (tmp / "worlds", {"split": "test", "eval_frames": False})}


def _source(adapter, own_sets):
    if adapter in own_sets:
        return own_sets[adapter]
    folder, options = SHARED[adapter]
    root = shared_data_dir() / folder
    if not root.is_dir():
        pytest.skip(f"third-party data folder {root} is absent")
    return root, options


def _images_read(monkeypatch, root, adapter, options):
    """(sample 0, the image files it read, in order)."""
    seen = []
    real = images_mod._open
    monkeypatch.setattr(images_mod, "_open", lambda path, *a: seen.append(path) or real(path, *a))
    sample = open_dataset(adapter, root, **options)[0]
    monkeypatch.setattr(images_mod, "_open", real)
    return sample, seen


def _mirror(src: Path, dst: Path) -> Path:
    """A copy of the tree whose files are links to the originals (cheap); replaced files are real."""
    shutil.copytree(src, dst, copy_function=os.symlink)
    return dst


def _replace(mirror: Path, src_root: Path, path: Path, data: bytes) -> Path:
    target = mirror / Path(path).relative_to(src_root)
    target.unlink()
    target.write_bytes(data)
    return target


@pytest.mark.parametrize("adapter", ["folder", "worlds", *SHARED])
def test_every_adapter_reads_16_bit_images_as_the_high_byte(adapter, own_sets, monkeypatch, tmp_path):
    """Sample 0's first image is replaced by a 48-bit RGB PNG and its second (where there is one)
    by a 16-bit grey PNG, of the originals' values times 256 plus a random low byte: the sample
    reads back the original pixels (the grey one: the red channel in all three)."""
    root, options = _source(adapter, own_sets)
    want, paths = _images_read(monkeypatch, root, adapter, options)
    assert paths, f"{adapter}: sample 0 read no image"
    mirror = _mirror(root, tmp_path / "m")
    rng = np.random.default_rng(7)
    originals = [im.image for im in want.frames.images]
    by_file = dict(zip(paths, originals))
    first, second = paths[0], (paths[1] if len(paths) > 1 else None)

    def low(a):  # a random low byte under each value
        return rng.integers(0, 256, a.shape, dtype=np.uint16)

    a = by_file[first].astype(np.uint16)
    _replace(mirror, root, first, png_bytes(a * 256 + low(a)))
    if second is not None:
        r = by_file[second][..., 0].astype(np.uint16)
        _replace(mirror, root, second, png_bytes(r * 256 + low(r)))
        by_file[second] = grey3(by_file[second][..., 0])
    got = open_dataset(adapter, mirror, **options)[0]
    assert len(got.frames.images) == len(originals)
    expected = [by_file[p] for p in paths]
    for g, w in zip(got.frames.images, expected):
        np.testing.assert_array_equal(g.image, w, err_msg=f"{adapter}: camera {g.name}")


@pytest.mark.parametrize("adapter", ["folder", "worlds", *SHARED])
def test_every_adapter_refuses_a_huge_image_naming_it(adapter, own_sets, monkeypatch, tmp_path):
    root, options = _source(adapter, own_sets)
    _, paths = _images_read(monkeypatch, root, adapter, options)
    mirror = _mirror(root, tmp_path / "m")
    huge = _replace(mirror, root, paths[0], header_only_jpeg(16000, 12000))
    with pytest.raises(DatasetError) as err:
        open_dataset(adapter, mirror, **options)[0]
    assert str(err.value).startswith(f"{huge}: image of 192000000 pixels, more than the {MAX_PIXELS}"), str(err.value)


def test_load_sample_of_a_worlds_folder_reads_through_the_same_reader(own_sets, tmp_path):
    from scube_sim.worlds.dataset import load_sample

    src = own_sets["worlds"][0] / "test" / "000000"
    mirror = _mirror(src, tmp_path / "s")
    name = min(p.name for p in src.glob("rgb_*.png"))
    rgb = read_rgb(src / name)
    _replace(mirror, src, src / name, png_bytes(rgb.astype(np.uint16) * 257))
    np.testing.assert_array_equal(load_sample(mirror)["images"][name], rgb)
    _replace(mirror, src, src / name, header_only_png(16000, 12000))
    with pytest.raises(InputError, match=r"rgb_.*\.png: image of 192000000 pixels"):
        load_sample(mirror)


# --- the command line -------------------------------------------------------------------------------

def test_export_of_a_16_bit_camera_image_writes_its_high_byte(own_sets, tmp_path):
    root = own_sets["folder"][0]
    mirror = _mirror(root, tmp_path / "in")
    src = next((root / "samples" / "000000").glob("CAM_A.*"))
    rgb = read_rgb(src)
    _replace(mirror, root, src, png_bytes(rgb.astype(np.uint16) * 256 + 255))
    out = tmp_path / "out"
    res = runner.invoke(app, ["datasets", "export", str(mirror), "--dataset", "folder", "-o", str(out)])
    assert res.exit_code == 0, res.output
    np.testing.assert_array_equal(read_rgb(out / "samples" / "000000" / src.name), rgb)


@pytest.mark.parametrize("data", [header_only_jpeg(16000, 12000), header_only_png(10000, 8000), b"GIF89a garbage"],
                         ids=["jpeg-192MP", "png-80MP", "not-an-image"])
def test_export_of_a_huge_or_unreadable_image_is_one_line_and_writes_nothing(own_sets, tmp_path, data):
    root = own_sets["folder"][0]
    mirror = _mirror(root, tmp_path / "in")
    src = next((root / "samples" / "000000").glob("CAM_A.*"))
    bad = _replace(mirror, root, src, data)
    out = tmp_path / "out"
    res = runner.invoke(app, ["datasets", "export", str(mirror), "--dataset", "folder", "-o", str(out)])
    one_line_error(res, f"error: {bad}: ")
    assert "Traceback" not in res.output and "DecompressionBomb" not in res.output
    assert not out.exists()
