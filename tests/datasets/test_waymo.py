"""Waymo frame adapter on the real pvps test frame (5 JPEGs, calibrations, 75 labels) and the
mmdetection3d val frame (no images, 18 labels)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from scube_sim.camera.model import Intrinsics
from scube_sim.camera.rig import BODY_FROM_OPTICAL
from scube_sim.datasets import DatasetError, open_dataset
from scube_sim.datasets.waymo import WaymoFrameDataset
from scube_sim.labels import LABEL_IDS
from scube_sim.transforms import invert_pose, transform_points
from tests.conftest import require

FRAME = "waymo-open-dataset-frame"
SIZES = {"FRONT": (1920, 1280), "FRONT_LEFT": (1920, 1280), "FRONT_RIGHT": (1920, 1280),
         "SIDE_LEFT": (1920, 886), "SIDE_RIGHT": (1920, 886)}


@pytest.fixture(scope="module")
def root(shared_data):
    return require(shared_data / FRAME)


@pytest.fixture(scope="module")
def meta(root):
    return json.loads(require(root / "frame_metadata.json").read_text())


@pytest.fixture(scope="module")
def sample(root):
    return WaymoFrameDataset(root)[0]


def test_one_sample_with_five_images_of_the_readme_sizes(root, sample, meta):
    ds = open_dataset("waymo", root)
    assert isinstance(ds, WaymoFrameDataset) and len(ds) == 1
    assert sample.timestamp == meta["timestamp_micros"] * 1e-6
    np.testing.assert_array_equal(sample.ego_pose, meta["vehicle_pose_vehicle_to_global_4x4"])
    assert sample.sweeps == []  # the extract has no range images
    assert {im.name: (im.image.shape[1], im.image.shape[0]) for im in sample.frames.images} == SIZES
    times = {im["name"]: im["pose_timestamp_s"] for im in meta["images"]}
    for im in sample.frames.images:
        assert im.image.dtype == np.uint8 and im.image.shape[2] == 3
        assert im.timestamp == times[im.name]
        assert im.intrinsics.model == "opencv" and len(im.intrinsics.dist) == 5
    assert sample.frames.timestamp == sample.timestamp
    np.testing.assert_array_equal(sample.frames.ego_pose, sample.ego_pose)


def test_camera_poses_follow_the_waymo_camera_frame(sample, meta):
    """cam_to_world = vehicle pose at the image @ camera-to-vehicle @ BODY_FROM_OPTICAL: the
    OpenCV optical axis is Waymo's camera x axis."""
    front = sample.frames["FRONT"]
    calib = next(c for c in meta["camera_calibrations"] if c["name"] == "FRONT")
    image = next(i for i in meta["images"] if i["name"] == "FRONT")
    want = (np.asarray(image["pose_vehicle_to_global_4x4_at_image"])
            @ np.asarray(calib["extrinsic_camera_to_vehicle_4x4"]) @ BODY_FROM_OPTICAL)
    np.testing.assert_allclose(front.cam_to_world, want, atol=1e-12)
    # FRONT looks along the vehicle's +x; SIDE_LEFT roughly along +y (left).
    for cam, axis in (("FRONT", [1, 0, 0]), ("SIDE_LEFT", [0, 1, 0])):
        cam_to_ego = invert_pose(sample.ego_pose) @ sample.frames[cam].cam_to_world
        assert cam_to_ego[:3, 2] @ axis > 0.6, cam


def waymo_visible(intr: Intrinsics, points_cam: np.ndarray) -> np.ndarray:
    """Inside the image as Waymo's CameraModel decides it (wdl_limited/camera/camera_model.cc):
    in front, radial distortion factor within [0.8, 1.2] (beyond it the polynomial folds far
    off-axis points back into the image), pixel in [0, W) x [0, H)."""
    uv, z = intr.project(points_cam)
    with np.errstate(divide="ignore", invalid="ignore"):
        r2 = (points_cam[:, 0] ** 2 + points_cam[:, 1] ** 2) / z ** 2
    k1, k2, _, _, k3 = intr.dist
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return ((z > 0) & (radial >= 0.8) & (radial <= 1.2) & (uv[:, 0] >= 0) & (uv[:, 0] < intr.width)
            & (uv[:, 1] >= 0) & (uv[:, 1] < intr.height))


def test_twelve_box_centres_project_into_front(sample):
    front = sample.frames["FRONT"]
    centres = np.array([b.center for b in sample.boxes])
    cam = transform_points(invert_pose(front.cam_to_world), centres)
    inside = waymo_visible(front.intrinsics, cam)
    assert inside.sum() == 12
    # Our lens model refuses points beyond the distortion's fold by itself: the same 12.
    uv, z = front.intrinsics.project(cam)
    ours = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < front.intrinsics.width) & (uv[:, 1] >= 0) \
        & (uv[:, 1] < front.intrinsics.height)
    np.testing.assert_array_equal(inside, ours)
    # The pinhole part alone (the README's check) agrees.
    pin = Intrinsics(front.intrinsics.width, front.intrinsics.height, front.intrinsics.fx, front.intrinsics.fy,
                     front.intrinsics.cx, front.intrinsics.cy)
    uv, z = pin.project(cam)
    in_pin = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < pin.width) & (uv[:, 1] >= 0) & (uv[:, 1] < pin.height)
    np.testing.assert_array_equal(inside, in_pin)
    labels = [sample.boxes[i].category for i in np.flatnonzero(inside)]
    assert {k: labels.count(k) for k in set(labels)} == {"TYPE_VEHICLE": 5, "TYPE_SIGN": 4, "TYPE_PEDESTRIAN": 3}
    # The two pedestrians crossing 8-9 m ahead are in the lower left of the image (checked by eye
    # with the boxes drawn: every box lands on its object).
    near = inside & (cam[:, 2] < 10)
    uv, _ = front.intrinsics.project(cam[near])
    assert near.sum() == 2 and np.all(uv[:, 0] < 960) and np.all(uv[:, 1] > 640)


def test_75_boxes_in_the_world_frame(sample, meta):
    assert len(sample.boxes) == 75
    counts = {}
    for b in sample.boxes:
        counts[b.category] = counts.get(b.category, 0) + 1
    assert counts == {"TYPE_VEHICLE": 37, "TYPE_SIGN": 25, "TYPE_PEDESTRIAN": 12, "TYPE_CYCLIST": 1}
    ids = {b.category: b.label for b in sample.boxes}
    assert ids == {"TYPE_VEHICLE": LABEL_IDS["car"], "TYPE_SIGN": LABEL_IDS["sign"],
                   "TYPE_PEDESTRIAN": LABEL_IDS["pedestrian"], "TYPE_CYCLIST": LABEL_IDS["bicyclist"]}
    lab, box = meta["laser_labels"][0], sample.boxes[0]
    back = invert_pose(sample.ego_pose) @ box.box_to_world()
    np.testing.assert_allclose(back[:3, 3], lab["center_xyz_vehicle_m"], atol=1e-9)
    assert np.arctan2(back[1, 0], back[0, 0]) == pytest.approx(lab["heading_rad"], abs=1e-12)
    np.testing.assert_array_equal(box.size, lab["length_width_height_m"])
    assert box.track_id == lab["id"] and np.all(np.isnan(box.velocity))


def test_top_lidar_model_from_the_beam_inclinations(sample, meta):
    assert set(sample.lidars) == {"TOP"}  # the short-range lasers publish only min/max inclination
    top = sample.lidars["TOP"]
    elev = np.array(top.config.pattern.channels.elevation_deg)
    assert top.config.channels == 64
    assert elev.min() == pytest.approx(-17.55, abs=0.01) and elev.max() == pytest.approx(2.50, abs=0.01)
    calib = next(c for c in meta["laser_calibrations"] if c["name"] == "TOP")
    np.testing.assert_array_equal(top.sensor_to_ego, calib["extrinsic_laser_to_vehicle_4x4"])
    np.testing.assert_allclose(top.config.mount.matrix(), top.sensor_to_ego, atol=1e-9)


def test_val_frame_has_no_images(root):
    s = WaymoFrameDataset(require(root / "mmdet3d_tests_val"))[0]
    assert s.frames is None and len(s.boxes) == 18 and s.sweeps == []
    assert {b.category for b in s.boxes} == {"TYPE_SIGN", "TYPE_VEHICLE"}
    assert s.lidars["TOP"].config.channels == 64


def test_load_images_false_and_json_path(root):
    s = WaymoFrameDataset(root / "frame_metadata.json", load_images=False)[0]
    assert s.frames is None and len(s.boxes) == 75


def edited_copy(root, tmp_path, edit, load_images=False):
    """A copy of frame_metadata.json (no images) changed by `edit`."""
    meta = json.loads((root / "frame_metadata.json").read_text())
    edit(meta)
    (tmp_path / "frame_metadata.json").write_text(json.dumps(meta))
    return WaymoFrameDataset(tmp_path, load_images=load_images)


def test_missing_image_is_named(root, tmp_path):
    with pytest.raises(DatasetError, match=r"FRONT\.jpg: missing image of camera FRONT"):
        edited_copy(root, tmp_path, lambda m: None, load_images=True)[0]


def test_bad_entries_name_the_file_and_key(root, tmp_path):
    def bad_type(m):
        m["laser_labels"][3]["type"] = "TYPE_TRAIN"

    def bad_pose(m):
        m["vehicle_pose_vehicle_to_global_4x4"] = m["vehicle_pose_vehicle_to_global_4x4"][:3]

    def no_center(m):
        del m["laser_labels"][0]["center_xyz_vehicle_m"]

    for edit, pattern in (
        (bad_type, r"frame_metadata\.json: laser_labels\[3\]\.type is 'TYPE_TRAIN'"),
        (bad_pose, r"frame_metadata\.json: vehicle_pose_vehicle_to_global_4x4 has shape \(3, 4\), expected \(4, 4\)"),
        (no_center, r"frame_metadata\.json: missing laser_labels\[0\] key 'center_xyz_vehicle_m'"),
    ):
        with pytest.raises(DatasetError, match=pattern):
            edited_copy(root, tmp_path, edit)[0]
    with pytest.raises(DatasetError, match=r"frame_metadata\.json: missing Waymo frame metadata"):
        WaymoFrameDataset(tmp_path / "nothing")


def test_numeric_label_types_are_accepted(root, tmp_path):
    def numeric(m):
        for lab in m["laser_labels"]:
            lab["type"] = {"TYPE_VEHICLE": 1, "TYPE_PEDESTRIAN": 2, "TYPE_SIGN": 3, "TYPE_CYCLIST": 4}[lab["type"]]
    s = edited_copy(root, tmp_path, numeric)[0]
    assert sum(b.category == "TYPE_CYCLIST" for b in s.boxes) == 1
