"""TRI DGP adapter on the DGP unit-test scene_02 (3 samples x 6 cameras + 1 LiDAR, boxes), checked
against the figures its README states (../shared/data/tri-dgp-test-scene_02/README.md)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from scube_sim.datasets import DatasetError, open_dataset, points_in_boxes
from scube_sim.datasets.base import frames_with_context
from scube_sim.datasets.origins import MergedCloudError, check_origin, require_single_origin
from scube_sim.datasets.tri_dgp import TriDgpDataset
from scube_sim.labels import LABEL_IDS
from scube_sim.transforms import invert_pose, transform_points
from tests.conftest import require

SCENE = "tri-dgp-test-scene_02"
CAMERAS = ["CAMERA_01", "CAMERA_05", "CAMERA_06", "CAMERA_07", "CAMERA_08", "CAMERA_09"]


@pytest.fixture(scope="module")
def root(shared_data):
    return require(shared_data / SCENE)


@pytest.fixture(scope="module")
def ds(root):
    return open_dataset("tri_dgp", root)


@pytest.fixture(scope="module")
def samples(ds):
    return [ds[i] for i in range(len(ds))]


def test_three_samples_of_six_cameras_at_full_size(ds, samples):
    assert isinstance(ds, TriDgpDataset) and len(ds) == 3
    for s in samples:
        assert s.frames.names == CAMERAS
        for im in s.frames.images:
            assert im.image.shape == (1216, 1936, 3) and im.image.dtype == np.uint8
            assert (im.intrinsics.width, im.intrinsics.height, im.intrinsics.model) == (1936, 1216, "pinhole")
        assert len(s.sweeps) == 1 and s.sweep().sensor == "LIDAR"
    assert [len(s.sweep()) for s in samples] == [47230, 49469, 48620]  # the README's counts
    assert samples[0].frames["CAMERA_01"].intrinsics.fx == pytest.approx(2181.530254382263)


def test_times_are_relative_and_each_camera_has_its_own(samples):
    """Samples 1 s apart; each image 82-92 ms before its LiDAR frame (the README's example: 91 ms),
    seconds since the earliest datum (the stored epoch is shifted to 2464)."""
    assert min(im.timestamp for im in samples[0].frames.images) == 0.0
    assert np.diff([s.timestamp for s in samples]) == pytest.approx([1.0, 1.0], abs=0.02)
    for s in samples:
        assert s.sweep().timestamp == s.timestamp == s.frames.timestamp
        for im in s.frames.images:
            assert 0.08 < s.timestamp - im.timestamp < 0.095
    assert samples[0].metadata["timestamp_us"] == 15616458250027900  # the LiDAR file's name


def test_lidar_poses_step_about_1_26_m(samples):
    steps = np.linalg.norm(np.diff([s.sweep().sensor_to_world[:3, 3] for s in samples], axis=0), axis=1)
    assert steps == pytest.approx([1.26, 1.26], abs=0.03)
    for s in samples:  # the LIDAR extrinsic is identity: the ego pose is the LiDAR datum's
        np.testing.assert_allclose(s.ego_pose, s.sweep().sensor_to_world, atol=1e-12)
        np.testing.assert_array_equal(s.lidars["LIDAR"].sensor_to_ego, np.eye(4))
        assert s.lidars["LIDAR"].config.range.max_m >= 231.3  # the farthest return of the scene


def test_projection_lands_the_readme_counts(samples):
    """README: K @ inv(T_world_cam) @ T_world_lidar puts 5 157 points of sample 0 in CAMERA_01 and
    11 916 in CAMERA_05. Through our camera model: 5 155 and 11 917, since `Intrinsics.from_k`
    moves DGP's OpenCV principal point by half a pixel (our pixel centres sit at + 0.5) and the
    README counted the window [0, W) x [0, H) in OpenCV pixels: points within half a pixel of
    an edge change sides. Tolerance 0.1 %."""
    s = samples[0]
    world = s.sweep().world_points()
    for cam, want in (("CAMERA_01", 5157), ("CAMERA_05", 11916)):
        im = s.frames[cam]
        uv, z = im.intrinsics.project(transform_points(invert_pose(im.cam_to_world), world))
        with np.errstate(invalid="ignore"):
            inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 1936) & (uv[:, 1] >= 0) & (uv[:, 1] < 1216)
        assert abs(int(inside.sum()) - want) <= max(5, want // 1000), (cam, int(inside.sum()))


def test_boxes_of_the_first_lidar_frame(samples):
    s = samples[0]
    assert len(s.boxes) == 13
    assert {b.category for b in s.boxes} == {"Car", "Truck"}
    assert {b.label for b in s.boxes} == {LABEL_IDS["car"], LABEL_IDS["truck"]}
    assert all(b.track_id for b in s.boxes) and all(np.all(np.isnan(b.velocity)) for b in s.boxes)
    # Centre pose, length along the box x: the points inside follow the annotation's num_points
    # (the stored cloud is thinner than the one annotated: 16-20 % of them for the boxes with 100 or more;
    # read as bottom centres, or with length and width swapped, under 7 %).
    idx = points_in_boxes(s.sweep().world_points(), s.boxes)
    for k, want in enumerate(s.metadata["num_lidar_pts"]):
        got = int((idx == k).sum())
        assert got <= want
        if want == 0:
            assert got == 0
        if want >= 100:
            assert 0.1 * want <= got, (k, got, want)


def test_one_log_and_context_within_it(root, ds, samples):
    assert {s.log for s in samples} == {SCENE}  # the scene JSON's name is empty: its folder's
    frames = frames_with_context(ds, 1, 1)
    assert [c.offset for c in frames.context] == [-1, 1]
    assert all(len(c) == 6 and c.log == SCENE for c in frames.context)


def test_the_sweep_looks_merged_and_is_flagged(samples):
    """Stored in the vehicle frame (origin on the road) with no per-point sensor: the check
    flags it; the adapter leaves it single-origin (module docstring)."""
    sw = samples[0].sweep()
    assert not sw.merged
    c = check_origin(sw)
    assert c.seen_through > 0.4 and c.origin_height_m < 0.3 and len(c.reasons) == 2
    with pytest.raises(MergedCloudError, match=r"sweep 'LIDAR' \(.*15616458250027900\.npz\) looks merged"):
        require_single_origin(sw, "tri sample 0")


def _scene_json(root):
    return next(root.glob("scene*.json"))


def test_missing_calibration_names_the_file(root, tmp_path):
    shutil.copy(_scene_json(root), tmp_path)
    with pytest.raises(DatasetError, match=r"calibration/64b9fde6360457d8beddcfb06c512fec6e2989d8\.json: missing "
                                           r"calibration \(the samples\[0\]\.calibration_key"):
        open_dataset("tri_dgp", tmp_path)


def test_errors_name_the_file_and_key(root, tmp_path):
    shutil.copytree(root / "calibration", tmp_path / "calibration")
    shutil.copytree(root / "ontology", tmp_path / "ontology")
    scene = json.loads(_scene_json(root).read_text())
    del scene["data"][0]["datum"]["point_cloud"]["pose"]["rotation"]
    (tmp_path / "scene_x.json").write_text(json.dumps(scene))
    with pytest.raises(DatasetError, match=r"scene_x\.json: missing key data\[0\]\.datum\.point_cloud\.pose\.rotation"):
        open_dataset("tri_dgp", tmp_path)


def test_a_folder_of_scenes_is_one_log_each(root, tmp_path):
    for name in ("a", "b"):
        d = tmp_path / name
        d.mkdir()
        shutil.copy(_scene_json(root), d)
        for sub in ("calibration", "ontology", "point_cloud", "rgb", "bounding_box_3d"):
            (d / sub).symlink_to(root / sub)
    ds = TriDgpDataset(tmp_path, load_images=False)
    assert len(ds) == 6 and [ds[i].log for i in (0, 2, 3, 5)] == ["a", "a", "b", "b"]
    assert ds[3].frames is None and len(ds[3].sweep()) == 47230
    ds = TriDgpDataset(tmp_path)
    assert [c.offset for c in frames_with_context(ds, 2, 1).context] == [-1]  # not across the scene boundary
