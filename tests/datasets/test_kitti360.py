"""KITTI-360 adapter: the 20-frame excerpt (../shared/data/kitti360-2013_05_28-seq, layout (b), no
poses) and a synthetic minimal copy of KITTI-360's own layout (a) with a poses.txt.

README figures: 20 frames, 1408x376 images, 111 883-122 432 points per sweep, ~10 m/s at 10 Hz,
27 707 returns of frame 3000 project into the image (P_rect_00 @ R_rect_00 @ inv(cam_to_velo)).
"""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from scube_sim.datasets import DatasetError, open_dataset
from scube_sim.datasets.base import frames_with_context
from scube_sim.datasets.kitti360 import Kitti360Dataset
from scube_sim.transforms import transform_points
from tests.conftest import require

SEQ = "kitti360-2013_05_28-seq"


@pytest.fixture(scope="module")
def seq_root(shared_data):
    return require(shared_data / SEQ / "data" / "calibration" / "perspective.txt").parents[2]


@pytest.fixture(scope="module")
def seq(seq_root):
    return open_dataset("kitti360", seq_root, poses="identity")  # no ICP: calibration and files only


@pytest.fixture(scope="module")
def seq_icp(seq_root):
    return open_dataset("kitti360", seq_root, count=3)  # ICP of 3 sweeps (~3 s; all 20 take ~16 s)


def _inside(im, world):
    uv, z = im.intrinsics.project(transform_points(np.linalg.inv(im.cam_to_world), world))
    w, h = im.intrinsics.width, im.intrinsics.height
    return (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)


# --- the excerpt (layout b) --------------------------------------------------------------------

def test_excerpt_samples(seq, seq_root):
    assert isinstance(seq, Kitti360Dataset) and len(seq) == 20 and seq.layout == "excerpt"
    samples = list(seq)
    assert [s.name for s in samples] == [f"{3000 + k:010d}" for k in range(20)]
    assert {s.log for s in samples} == {SEQ}
    np.testing.assert_allclose(np.diff([s.timestamp for s in samples]), 0.1, atol=1e-9)  # 10 Hz
    for s in samples[:3]:
        im = s.frames.images[0]
        assert im.name == "image_00" and im.image.shape == (376, 1408, 3)
        assert (im.intrinsics.width, im.intrinsics.height) == (1408, 376)
        assert s.frames.metadata["ego_height_m"] == pytest.approx(1.73)
        sw = s.sweep()
        assert 111_883 <= len(sw) <= 122_432 and sw.intensity.dtype == np.float32
        assert 0 <= sw.intensity.min() and sw.intensity.max() <= 1
        assert s.lidars["velodyne"].config.name.upper().replace("-", "") == "HDL64E"
        assert "10 Hz" in s.metadata["timestamps"]
    # root may be the folder holding data/ or data/ itself
    assert open_dataset("kitti360", seq_root / "data", poses="identity").logs == [SEQ]


def test_excerpt_projection_matches_readme(seq):
    """The README's independent check: 27 707 returns of frame 3000 land in the image."""
    s = seq[0]
    n = int(_inside(s.frames.images[0], s.sweep().world_points()).sum())
    assert n == pytest.approx(27_707, rel=0.005)
    # the camera sits ~0.8 m ahead of the Velodyne, looking forward (+x)
    cam = s.frames.images[0].cam_to_world
    assert cam[0, 3] == pytest.approx(0.80, abs=0.01) and cam[:3, 2] @ [1, 0, 0] > 0.99


def test_excerpt_poses_estimated(seq_icp):
    assert seq_icp.poses_from_icp and len(seq_icp) == 3
    samples = list(seq_icp)
    for s in samples:
        assert s.metadata["poses"].startswith("estimated:")
    np.testing.assert_allclose(samples[0].ego_pose, np.eye(4))
    pos = np.array([s.ego_pose[:3, 3] for s in samples])
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert np.all((steps > 0.9) & (steps < 1.1)), steps  # ~10 m/s at 10 Hz
    assert np.all(np.diff(pos[:, 0]) > 0.9)  # forward
    assert samples[1].metadata["icp_fitness"] > 0.5
    ctx = frames_with_context(seq_icp, 1, 1)
    assert [c.offset for c in ctx.context] == [-1, 1] and all(c.log == SEQ for c in ctx.context)


# --- a synthetic copy of KITTI-360's layout (a) --------------------------------------------------

DRIVE = "2013_05_28_drive_0000_sync"
W, H = 32, 12


def _rot(axis, deg):
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    i, j = [(1, 2), (0, 2), (0, 1)][axis]
    r = np.eye(3)
    r[i, i] = r[j, j] = c
    r[i, j], r[j, i] = -s, s
    return r


def _line(m):
    return " ".join(repr(float(v)) for v in np.asarray(m).ravel())


def _write_kitti360(root, poses):
    cal = root / "calibration"
    cal.mkdir(parents=True)
    r_rect = _rot(2, 0.4) @ _rot(0, -0.2)
    (cal / "perspective.txt").write_text(
        "calib_time: 17-Feb-2016 14:23:48\n"
        f"S_rect_00: {W}.0 {H}.0\nR_rect_00: {_line(r_rect)}\n"
        f"P_rect_00: 20.0 0.0 16.0 0.0 0.0 20.0 6.0 0.0 0.0 0.0 1.0 0.0\n")
    velo_cam = np.eye(4)
    velo_cam[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]]) @ _rot(0, 3.0)  # camera axes -> x fwd, z up
    velo_cam[:3, 3] = [0.8, 0.3, -0.18]
    (cal / "calib_cam_to_velo.txt").write_text(_line(velo_cam[:3]) + "\n")
    pose_cam = np.eye(4)
    pose_cam[:3, :3] = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]]) @ _rot(1, 2.0)  # pose frame: x fwd, z down
    pose_cam[:3, 3] = [1.57, 0.0, -0.65]
    (cal / "calib_cam_to_pose.txt").write_text(
        "".join(f"image_0{k}: {_line(pose_cam[:3])}\n" for k in range(4)))
    img = root / "data_2d_raw" / DRIVE / "image_00" / "data_rect"
    velo = root / "data_3d_raw" / DRIVE / "velodyne_points" / "data"
    img.mkdir(parents=True)
    velo.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for n in range(3):
        Image.fromarray(np.full((H, W, 3), 40 * n, np.uint8)).save(img / f"{n:010d}.png")
        pts = np.c_[rng.uniform(-20, 20, (50, 3)), rng.uniform(0, 1, 50)].astype("<f4")
        pts.tofile(velo / f"{n:010d}.bin")
    (velo.parent / "timestamps.txt").write_text(
        "2013-05-28 09:57:31.995970538\n2013-05-28 09:57:32.100653634\n2013-05-28 09:57:32.205315418\n")
    pdir = root / "data_poses" / DRIVE
    pdir.mkdir(parents=True)
    (pdir / "poses.txt").write_text("".join(f"{n} {_line(p[:3])}\n" for n, p in poses.items()))
    return velo_cam, pose_cam, r_rect


@pytest.fixture
def kitti360_copy(tmp_path):
    poses = {}
    for n in (0, 1):  # frame 2 has no pose: left out
        p = np.eye(4)
        p[:3, :3] = _rot(2, 30.0 + 1.5 * n) @ _rot(0, 180.0)  # z down in a z-up world
        p[:3, 3] = [1234.5 + 1.01 * n, -987.25, 112.125]
        poses[n] = p
    velo_cam, pose_cam, r_rect = _write_kitti360(tmp_path, poses)
    return tmp_path, poses, velo_cam, pose_cam, r_rect


def test_layout_a_returns_file_poses(kitti360_copy):
    root, poses, velo_cam, pose_cam, r_rect = kitti360_copy
    ds = open_dataset("kitti360", root)
    assert ds.layout == "kitti360" and ds.logs == [DRIVE] and not ds.poses_from_icp
    assert len(ds) == 2 and ds.unposed == [(DRIVE, 2)]
    assert np.array_equal(ds.file_poses[DRIVE], np.stack([poses[0], poses[1]]))  # exactly as written
    r4 = np.eye(4)
    r4[:3, :3] = r_rect
    for n, s in enumerate(ds):
        assert s.log == DRIVE and s.name == f"{n:010d}" and s.metadata["poses"].startswith("file:")
        np.testing.assert_allclose(s.ego_pose, poses[n] @ pose_cam @ np.linalg.inv(velo_cam), atol=1e-12)
        # kitti360scripts' CameraPerspective: cam2world = pose @ camToPose @ inv(R_rect)
        np.testing.assert_allclose(s.frames.images[0].cam_to_world, poses[n] @ pose_cam @ np.linalg.inv(r4),
                                   atol=1e-9)
        np.testing.assert_allclose(s.sweep().sensor_to_world, s.ego_pose)
    assert ds[1].timestamp == pytest.approx(0.104683096)  # timestamps.txt, line = frame number
    # forced estimation ignores the file
    assert open_dataset("kitti360", root, poses="identity")[0].metadata["poses"].startswith("identity")


@pytest.mark.parametrize("name", ["perspective.txt", "calib_cam_to_velo.txt", "calib_cam_to_pose.txt"])
def test_layout_a_missing_calibration_file(kitti360_copy, name):
    root = kitti360_copy[0]
    path = root / "calibration" / name
    path.unlink()  # calib_cam_to_pose.txt: needed because the drive has a poses.txt
    with pytest.raises(DatasetError, match="missing KITTI-360 calibration file") as err:
        open_dataset("kitti360", root)
    assert str(path) in str(err.value)
    if name == "calib_cam_to_pose.txt":  # not needed where poses are not read from the file
        assert len(open_dataset("kitti360", root, poses="identity")) == 3


def test_layout_a_bad_content(kitti360_copy):
    root = kitti360_copy[0]
    persp = root / "calibration" / "perspective.txt"
    good = persp.read_text()
    persp.write_text("\n".join(ln for ln in persp.read_text().splitlines() if not ln.startswith("P_rect_00")))
    with pytest.raises(DatasetError, match="missing key 'P_rect_00'") as err:
        open_dataset("kitti360", root)
    assert str(persp) in str(err.value)
    persp.write_text(good)
    poses = root / "data_poses" / DRIVE / "poses.txt"
    poses.write_text("0 1 0 0 0 0 1 0 0 0 0 1\n")  # 12 values: the frame number or a number is missing
    with pytest.raises(DatasetError, match="line 1: expected a frame number and 12 numbers") as err:
        open_dataset("kitti360", root)
    assert str(poses) in str(err.value)
    with pytest.raises(DatasetError, match="no drive 'nope'"):
        open_dataset("kitti360", root, drive="nope")


def test_not_a_kitti360_folder(tmp_path):
    with pytest.raises(DatasetError, match="not a KITTI-360 folder"):
        open_dataset("kitti360", tmp_path)
