"""NuScenesDataset on the real mmdetection3d nuScenes demo keyframe (../shared/data/nuscenes-mmdet3d-demo).

Figures the README gives: 34 688 points, six 1600x900 images, 69 boxes; ``K @ lidar2cam`` puts
3 067 (CAM_FRONT) to 4 826 (CAM_BACK) points in the images; the per-camera pose differs from
``ego2global @ cam2ego`` by the ego motion between LiDAR and camera time (0.33 m for CAM_FRONT).
"""

from __future__ import annotations

import collections
import pickle
import shutil

import numpy as np
import pytest

from scube_sim.camera.model import K_PIXEL_CENTRE_SHIFT as PIXEL_CENTRE_SHIFT
from scube_sim.datasets import DatasetError, open_dataset, points_in_boxes
from scube_sim.datasets.nuscenes import NuScenesDataset
from scube_sim.io.safe_pickle import load_pickle
from scube_sim.labels import LABEL_IDS
from scube_sim.transforms import invert_pose, transform_points
from tests.conftest import require

DEMO = "nuscenes-mmdet3d-demo"
PKL = "n015-2018-07-24-11-22-45+0800.pkl"
BIN = "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"


@pytest.fixture(scope="module")
def root(shared_data):
    return require(shared_data / DEMO / PKL).parent


@pytest.fixture(scope="module")
def info(root):
    return load_pickle(root / PKL)["data_list"][0]


@pytest.fixture(scope="module")
def sample(root):
    return open_dataset("nuscenes", root)[0]


def _in_image(uv, z, intr):
    return (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < intr.width) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.height)


def test_counts_shapes_and_sweep(root, info, sample):
    ds = NuScenesDataset(root)
    assert len(ds) == 1 and ds.name == "nuscenes" and ds.poses_from_icp is False
    sw = sample.sweep("LIDAR_TOP")
    assert len(sw) == 34_688 and sw.points.shape == (34_688, 3)
    assert sw.intensity.dtype == np.float32 and sw.intensity_max == 255.0
    assert 0 <= sw.intensity.min() and sw.intensity.max() <= 255
    assert sw.ring.dtype == np.int16 and set(np.unique(sw.ring)) == set(range(32))
    assert sw.motion_compensated
    e2g, l2e = np.array(info["ego2global"]), np.array(info["lidar_points"]["lidar2ego"])
    np.testing.assert_allclose(sw.sensor_to_world, e2g @ l2e)
    np.testing.assert_allclose(sample.ego_pose, e2g)
    assert sample.timestamp == sw.timestamp == pytest.approx(1532402927.647951)
    spec = sample.lidars["LIDAR_TOP"]
    assert spec.config.name == "HDL-32E" and spec.config.pattern.channels.count == 32
    np.testing.assert_allclose(spec.sensor_to_ego, l2e)
    # world coordinates near the ego translation (411.3, 1180.9) of the README
    assert np.linalg.norm(np.median(sw.world_points()[:, :2], axis=0) - [411.3, 1180.9]) < 10

    fr = sample.frames
    assert len(fr) == 6 and fr.names[0] == "CAM_FRONT"
    assert fr.timestamp == sample.timestamp and fr.metadata["token"] == "ca9a282c9e77460f8360f564131a8af5"
    for im in fr.images:
        assert im.image.shape == (900, 1600, 3) and im.image.dtype == np.uint8
        assert im.timestamp == pytest.approx(info["images"][im.name]["timestamp"])
    front = fr["CAM_FRONT"].intrinsics
    assert (front.fx, front.fy) == pytest.approx((1266.4172, 1266.4172))
    assert (front.cx, front.cy) == pytest.approx((816.26702 + 0.5, 491.50707 + 0.5))  # pixel centres at +0.5
    assert len(sample.boxes) == 69


def test_projection_counts_match_readme(info, sample):
    """Each camera sees the sweep as the README's ``K @ lidar2cam`` does, through Frames alone."""
    world = sample.sweep().world_points()
    lidar = sample.sweep().points
    counts = {}
    for im in sample.frames.images:
        uv, z = im.intrinsics.project(transform_points(invert_pose(im.cam_to_world), world))
        inside = _in_image(uv, z, im.intrinsics)
        counts[im.name] = int(inside.sum())
        # same pixels as the dataset's own K @ lidar2cam (up to our +0.5 pixel-centre convention)
        c = info["images"][im.name]
        q = lidar @ np.array(c["lidar2cam"])[:3, :3].T + np.array(c["lidar2cam"])[:3, 3]
        ref = q @ np.array(c["cam2img"]).T
        ref = ref[:, :2] / ref[:, 2:]
        assert np.abs(uv[inside] - PIXEL_CENTRE_SHIFT - ref[inside]).max() < 0.01
    # measured: FRONT 3060, FRONT_RIGHT 3079, FRONT_LEFT 3701, BACK 4825, BACK_LEFT 4096, BACK_RIGHT 3376
    assert counts["CAM_FRONT"] == pytest.approx(3067, rel=0.02)
    assert counts["CAM_BACK"] == pytest.approx(4826, rel=0.02)
    for name, n in counts.items():
        assert 2500 < n < 5500, (name, n)  # each camera sees a 9-14 % slice of the 360-degree sweep


def test_camera_poses_include_ego_motion(root, sample):
    """cam_to_world is the camera at its own time: it differs from ego2global @ cam2ego (the camera
    where the ego was at the LiDAR time) by the ego's travel, ~9.3 m/s x the time offset."""
    ds = NuScenesDataset(root, load_images=False)
    speed = 0.33 / 0.0355  # README: 0.33 m for CAM_FRONT, 35 ms before the LiDAR
    for im in sample.frames.images:
        static = ds.camera_pose_from_cam2ego(0, im.name)
        shift = np.linalg.norm(im.cam_to_world[:3, 3] - static[:3, 3])
        dt = sample.timestamp - im.timestamp
        assert shift == pytest.approx(speed * dt, abs=0.03), im.name
        angle = np.degrees(np.arccos(np.clip((np.trace(im.cam_to_world[:3, :3].T @ static[:3, :3]) - 1) / 2, -1, 1)))
        assert angle < 0.5  # nearly straight driving: the difference is a translation
    front = sample.frames["CAM_FRONT"].cam_to_world[:3, 3] - ds.camera_pose_from_cam2ego(0, "CAM_FRONT")[:3, 3]
    assert np.linalg.norm(front) == pytest.approx(0.33, abs=0.01)


def test_boxes_agree_with_num_lidar_pts(sample):
    """Counting the sweep's points in each world Box reproduces nuScenes' num_lidar_pts.

    Measured: 60 of 69 exact, 67 of 69 within max(2, 5 %); the two others overlap another box
    (points_in_boxes gives a point to the first box only) or have points on a face: a barrier
    45 vs 50 and an unlabelled object 6 vs 10. Totals 990 vs 1009."""
    world = sample.sweep().world_points()
    nlp = np.array(sample.metadata["num_lidar_pts"])
    idx = points_in_boxes(world, sample.boxes)
    counts = np.bincount(idx[idx >= 0], minlength=len(sample.boxes))
    ok = np.abs(counts - nlp) <= np.maximum(2, 0.05 * nlp)
    assert ok.mean() >= 0.9, list(zip(counts[~ok], nlp[~ok]))
    assert np.sum(counts == nlp) >= 0.8 * len(nlp)
    assert counts.sum() == pytest.approx(nlp.sum(), rel=0.03)

    # The info's z is the box centre, not the bottom: read as a bottom (boxes h/2 higher), the
    # boxes lose about half their points.
    raised = [type(b)(b.center + b.rotation[:, 2] * b.size[2] / 2, b.size, b.rotation, label=b.label, category=b.category) for b in sample.boxes]
    idx = points_in_boxes(world, raised)
    assert np.bincount(idx[idx >= 0], minlength=len(raised)).sum() < 0.6 * nlp.sum()


def test_box_labels_rotation_and_velocity(info, sample):
    by_label = {b.category: b.label for b in sample.boxes}
    assert by_label["car"] == LABEL_IDS["car"]
    assert by_label["barrier"] == LABEL_IDS["fence"]
    assert by_label["traffic_cone"] == LABEL_IDS["construction_cone"]
    assert by_label["construction_vehicle"] == LABEL_IDS["other_vehicle"]
    assert by_label["pedestrian"] == LABEL_IDS["pedestrian"]
    assert by_label.get("unknown", 0) == 0  # bbox_label_3d -1: a class outside the 10
    l2w = sample.sweep().sensor_to_world
    for b, ins in zip(sample.boxes, info["instances"]):
        x, y, z, length, width, height, yaw = ins["bbox_3d"]
        np.testing.assert_allclose(b.size, [length, width, height])
        np.testing.assert_allclose(b.rotation.T @ b.rotation, np.eye(3), atol=1e-6)
        # the box's length axis in the LiDAR frame points at yaw
        ax = l2w[:3, :3].T @ b.rotation[:, 0]
        assert np.arctan2(ax[1], ax[0]) == pytest.approx(np.arctan2(np.sin(yaw), np.cos(yaw)), abs=1e-6)
        np.testing.assert_allclose(transform_points(invert_pose(l2w), b.center[None])[0], [x, y, z], atol=1e-6)
        vx, vy = ins["velocity"]
        if np.isfinite(vx):
            assert b.velocity[2] == 0.0
            assert np.hypot(*b.velocity[:2]) == pytest.approx(np.hypot(vx, vy), rel=1e-3, abs=1e-3)
    moving = [b for b in sample.boxes if b.speed > 1.0]
    assert moving, "the keyframe has moving objects"


def test_load_images_false_skips_frames(root):
    s = NuScenesDataset(root, load_images=False)[0]
    assert s.frames is None and len(s.sweep()) == 34_688 and len(s.boxes) == 69


# --- errors ----------------------------------------------------------------------------------

def _copy_demo(root, tmp_path, pkl=True):
    for f in root.iterdir():
        if f.name != "README.md" and (pkl or f.suffix != ".pkl"):
            (tmp_path / f.name).symlink_to(f)
    return tmp_path


def _write_pkl(path, obj):
    with open(path, "wb") as fh:
        pickle.dump(obj, fh)
    return path


def test_error_missing_data_list(root, tmp_path):
    _copy_demo(root, tmp_path, pkl=False)
    bad = _write_pkl(tmp_path / "bad.pkl", {"metainfo": {"categories": {"car": 0}}})
    with pytest.raises(DatasetError, match="data_list") as err:
        NuScenesDataset(tmp_path)
    assert str(bad) in str(err.value)


def test_error_lidar2ego_wrong_shape(root, tmp_path):
    _copy_demo(root, tmp_path, pkl=False)
    raw = load_pickle(root / PKL)
    raw["data_list"][0]["lidar_points"]["lidar2ego"] = np.eye(3).tolist()
    bad = _write_pkl(tmp_path / "bad.pkl", raw)
    with pytest.raises(DatasetError) as err:
        NuScenesDataset(tmp_path)
    msg = str(err.value)
    assert str(bad) in msg and "data_list[0].lidar_points.lidar2ego" in msg and "(3, 3)" in msg and "(4, 4)" in msg


def test_error_missing_nested_key(root, tmp_path):
    _copy_demo(root, tmp_path, pkl=False)
    raw = load_pickle(root / PKL)
    del raw["data_list"][0]["images"]["CAM_BACK"]["cam2img"]
    bad = _write_pkl(tmp_path / "bad.pkl", raw)
    with pytest.raises(DatasetError, match=r"missing key data_list\[0\]\.images\.CAM_BACK\.cam2img") as err:
        NuScenesDataset(tmp_path)
    assert str(bad) in str(err.value)


def test_error_pickle_with_foreign_class(root, tmp_path):
    """The restricted unpickler refuses anything but builtins and numpy: no code runs."""
    _copy_demo(root, tmp_path, pkl=False)
    raw = load_pickle(root / PKL)
    raw["metainfo"]["extra"] = collections.Counter("abc")
    bad = _write_pkl(tmp_path / "evil.pkl", raw)
    with pytest.raises(DatasetError) as err:
        NuScenesDataset(tmp_path)
    assert str(bad) in str(err.value) and "collections.Counter" in str(err.value)


def test_error_truncated_sweep(root, tmp_path):
    _copy_demo(root, tmp_path)
    (tmp_path / BIN).unlink()
    data = (root / BIN).read_bytes()
    (tmp_path / BIN).write_bytes(data[:-7])
    ds = NuScenesDataset(tmp_path, load_images=False)  # the pkl is fine; the sweep is read on access
    with pytest.raises(DatasetError, match="truncated") as err:
        ds[0]
    assert str(tmp_path / BIN) in str(err.value) and "20" in str(err.value)


def test_error_several_pkls_and_missing_file(root, tmp_path):
    _copy_demo(root, tmp_path)
    shutil.copy(root / PKL, tmp_path / "other.pkl")
    with pytest.raises(DatasetError, match="info="):
        NuScenesDataset(tmp_path)
    ds = NuScenesDataset(tmp_path, info="other.pkl", load_images=False)
    assert len(ds[0].sweep()) == 34_688
    (tmp_path / BIN).unlink()
    with pytest.raises(DatasetError, match="missing LiDAR sweep") as err:
        ds[0]
    assert BIN in str(err.value)
