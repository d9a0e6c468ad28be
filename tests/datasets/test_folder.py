"""The scube-sim-folder format: round trips (real AV2 sweeps, a synthetic sample with PNG images
and boxes), files readable by independent libraries, and errors naming the file and key."""

from __future__ import annotations

import re

import numpy as np
import pytest
import yaml
from PIL import Image

from scube_sim.camera.frames import CameraImage, Frames
from scube_sim.camera.model import Intrinsics
from scube_sim.datasets import Box, DatasetError, LidarSpec, LidarSweep, Sample, open_dataset
from scube_sim.datasets.folder import FolderDataset, write_folder_dataset
from scube_sim.lidar.config import load_lidar_config
from scube_sim.transforms import interpolate_poses, pose_from_xyz_rpy
from tests.conftest import look_at, require

AV2 = "argoverse2-sensor-log-7fab2350"


def smooth_image(rng, h, w) -> np.ndarray:
    """(h, w, 3) uint8 colour ramps with a random phase (JPEG-friendly, unlike noise)."""
    v, u = np.mgrid[0:h, 0:w]
    phase = rng.random(3) * 6.0
    rgb = [127.5 + 127.5 * np.sin(0.2 * u + 0.3 * v + p) for p in phase]
    return np.clip(np.stack(rgb, -1).round(), 0, 255).astype(np.uint8)


def synthetic_sample(rng, name="s0", t=10.0) -> Sample:
    """Two PNG-able cameras, a raw sweep with a pose stream, a compensated one, two boxes."""
    ego = pose_from_xyz_rpy([5.0, -2.0, 0.1], [0.5, -1.0, 30.0])
    intr_a = Intrinsics(40, 30, 35.0, 36.0, 20.5, 15.25, "opencv", (0.01, -0.02, 0.001, 0.0, 0.003))
    intr_b = Intrinsics(24, 16, 20.0, 20.0, 12.0, 8.0)
    images = [CameraImage("CAM_A", smooth_image(rng, 30, 40), intr_a,
                          ego @ look_at([1, 0, 1.5], [10, 0, 1.5]), t + 0.01),
              CameraImage("CAM_B", smooth_image(rng, 16, 24), intr_b,
                          ego @ look_at([0, 0.5, 1.5], [0, 10, 1.5]), t + 0.02)]
    mount = pose_from_xyz_rpy([1.2, 0.0, 1.8], [0.0, 0.0, 2.0])
    start, end = ego @ mount, pose_from_xyz_rpy([5.5, -1.7, 0.1], [0.5, -1.0, 31.0]) @ mount
    pose_fn = lambda times: interpolate_poses(start, end, (np.asarray(times) - t) / 0.1)  # noqa: E731
    n = 500
    raw = LidarSweep("lidar_top", rng.normal(0, 10, (n, 3)), start, t, intensity=rng.random(n).astype(np.float32),
                     intensity_max=1.0, ring=rng.integers(0, 32, n).astype(np.int16),
                     time_offset=np.sort(rng.random(n) * 0.1), motion_compensated=False, pose_fn=pose_fn)
    front = pose_from_xyz_rpy([3, 0, 0.5], [0, 0, 0])
    comp = LidarSweep("lidar.front", rng.normal(0, 5, (50, 3)), ego @ front, t,
                      intensity=rng.random(50).astype(np.float32) * 255, intensity_max=255.0)
    yaw20 = pose_from_xyz_rpy([0, 0, 0], [0, 0, 20])[:3, :3]
    boxes = [Box(np.array([12.0, 3.0, 0.9]), np.array([4.5, 1.9, 1.6]), yaw20, category="car", label=1,
                 velocity=np.array([2.0, 0.5, 0.0]), track_id="track-7"),
             Box(np.array([-4.0, 1.0, 0.8]), np.array([0.6, 0.6, 1.8]), np.eye(3), category="pedestrian", label=7)]
    lidars = {"lidar_top": LidarSpec("lidar_top", load_lidar_config("HDL-32E"), mount),
              "lidar.front": LidarSpec("lidar.front", load_lidar_config("VLP-16"), front)}
    metadata = {"source": "synthetic", "n": np.int64(3)}
    return Sample(name, t, ego, Frames(images, ego, t), [raw, comp], lidars, boxes, metadata)


def assert_same_sweep(got: LidarSweep, want: LidarSweep):
    assert got.sensor == want.sensor and got.timestamp == want.timestamp and got.motion_compensated
    np.testing.assert_array_equal(got.points, want.points)  # float64 .npz: exact
    np.testing.assert_array_equal(got.sensor_to_world, want.sensor_to_world)
    for f in ("intensity", "ring", "time_offset"):
        a, b = getattr(got, f), getattr(want, f)
        assert (a is None) == (b is None), f
        if a is not None:
            assert a.dtype == b.dtype, f
            np.testing.assert_array_equal(a, b, err_msg=f)
    assert got.intensity_max == want.intensity_max and got.pose_fn is None


def assert_same_sample(got: Sample, want: Sample):
    assert got.name == want.name and got.timestamp == want.timestamp
    np.testing.assert_array_equal(got.ego_pose, want.ego_pose)
    assert [w.sensor for w in got.sweeps] == [w.sensor for w in want.sweeps]
    for g, w in zip(got.sweeps, want.sweeps):
        assert_same_sweep(g, w.compensated())
    assert set(got.lidars) == set(want.lidars)
    for n, spec in want.lidars.items():
        assert got.lidars[n].config == spec.config
        np.testing.assert_array_equal(got.lidars[n].sensor_to_ego, spec.sensor_to_ego)
    assert len(got.boxes) == len(want.boxes)
    for g, w in zip(got.boxes, want.boxes):
        for f in ("center", "size", "rotation", "velocity"):
            np.testing.assert_array_equal(getattr(g, f), getattr(w, f), err_msg=f)
        assert (g.category, g.label, g.track_id) == (w.category, w.label, w.track_id)
    if want.frames is None:
        assert got.frames is None
        return
    assert got.frames.names == want.frames.names and got.frames.timestamp == want.frames.timestamp
    for g, w in zip(got.frames.images, want.frames.images):
        np.testing.assert_array_equal(g.image, w.image)  # PNG: lossless
        np.testing.assert_array_equal(g.cam_to_world, w.cam_to_world)
        assert g.intrinsics == w.intrinsics and g.timestamp == w.timestamp


@pytest.fixture(scope="module")
def av2(shared_data):
    from scube_sim.datasets.argoverse2 import Argoverse2Dataset

    return Argoverse2Dataset(require(shared_data / AV2))


def test_round_trip_of_the_real_argoverse2_log(av2, tmp_path):
    out = write_folder_dataset(av2, tmp_path / "av2")
    ds = open_dataset("folder", out)
    assert isinstance(ds, FolderDataset) and len(ds) == 2
    assert ds.dataset_name == "argoverse2" and ds.poses_from_icp is False
    for i in range(2):
        assert_same_sample(ds[i], av2[i])
    # Independent readers: numpy for the clouds, yaml for the sample file.
    s0 = av2[0]
    pts = np.load(out / "samples" / "000000" / "up_lidar.npz", allow_pickle=False)["points"]
    assert pts.dtype.names == ("x", "y", "z", "intensity", "ring", "time_offset")
    np.testing.assert_array_equal(np.stack([pts["x"], pts["y"], pts["z"]], 1), s0.sweeps[0].points)
    np.testing.assert_array_equal(pts["ring"], s0.sweeps[0].ring)
    doc = yaml.safe_load((out / "samples" / "000000" / "sample.yaml").read_text())
    np.testing.assert_array_equal(np.array(doc["ego_pose"]), s0.ego_pose)
    assert doc["sweeps"]["down_lidar"]["intensity_max"] == 255.0 and doc["timestamp"] == s0.timestamp
    top = yaml.safe_load((out / "dataset.yaml").read_text())
    assert top["format"] == "scube-sim-folder" and top["version"] == 1
    assert top["lidars"]["up_lidar"]["config"] == "lidars/up_lidar.yaml"


def test_round_trip_of_a_synthetic_sample_with_images_and_boxes(rng, tmp_path):
    samples = [synthetic_sample(rng), synthetic_sample(rng, "s1", 10.1)]
    write_folder_dataset(samples, tmp_path / "syn", name="synthetic")
    ds = FolderDataset(tmp_path / "syn")
    for got, want in zip(ds, samples):
        assert_same_sample(got, want)
    got = ds[0]
    assert got.metadata == {"source": "synthetic", "n": 3}
    assert np.all(np.isnan(got.boxes[1].velocity))
    # The raw sweep was stored compensated: its world points are unchanged.
    np.testing.assert_allclose(got.sweep("lidar_top").world_points(), samples[0].sweep("lidar_top").world_points(),
                               atol=1e-9)
    # PIL reads the PNGs back byte-exact; the sample file names them.
    d = tmp_path / "syn" / "samples" / "000000"
    doc = yaml.safe_load((d / "sample.yaml").read_text())
    assert doc["images"]["CAM_A"]["file"] == "CAM_A.png" and doc["boxes"][0]["velocity"] == [2.0, 0.5, 0.0]
    with Image.open(d / "CAM_B.png") as im:
        assert im.format == "PNG"
        np.testing.assert_array_equal(np.asarray(im), samples[0].frames["CAM_B"].image)
    assert not [p for p in (tmp_path / "syn" / "samples").iterdir() if p.name.startswith(".")]


def test_pcd_and_jpg_options_read_by_open3d_and_pil(rng, tmp_path):
    o3d = pytest.importorskip("open3d")
    s = synthetic_sample(rng)
    write_folder_dataset([s], tmp_path / "pcd", points_format="pcd", image_format="jpg")
    d = tmp_path / "pcd" / "samples" / "000000"
    want = s.sweep("lidar_top").compensated().points
    cloud = np.asarray(o3d.io.read_point_cloud(str(d / "lidar_top.pcd")).points)
    np.testing.assert_array_equal(cloud, want.astype(np.float32).astype(np.float64))
    got = FolderDataset(tmp_path / "pcd")[0]
    np.testing.assert_array_equal(got.sweep("lidar_top").points, want.astype(np.float32))  # float32 precision
    np.testing.assert_array_equal(got.sweep("lidar_top").ring, s.sweep("lidar_top").ring)
    assert np.abs(got.frames["CAM_A"].image.astype(int) - s.frames["CAM_A"].image).mean() < 4  # lossy JPEG
    with Image.open(d / "CAM_A.jpg") as im:
        assert im.format == "JPEG" and im.size == (40, 30)


def test_writer_refuses_to_overwrite_and_leaves_no_dataset_yaml_when_interrupted(rng, tmp_path):
    root = tmp_path / "ds"
    write_folder_dataset([synthetic_sample(rng)], root)
    with pytest.raises(FileExistsError, match="already holds a dataset"):
        write_folder_dataset([synthetic_sample(rng)], root)

    def failing():
        yield synthetic_sample(rng)
        raise RuntimeError("converter crashed")
    with pytest.raises(RuntimeError, match="converter crashed"):
        write_folder_dataset(failing(), root, overwrite=True)
    assert not (root / "dataset.yaml").exists()
    assert sorted(p.name for p in (root / "samples").iterdir()) == ["000000"]
    with pytest.raises(DatasetError, match=r"dataset\.yaml: no such file"):
        FolderDataset(root)
    write_folder_dataset([synthetic_sample(rng)] * 2, root, overwrite=True)
    assert len(FolderDataset(root)) == 2


def test_writer_rejects_a_sensor_that_changes_between_samples(rng, tmp_path):
    a, b = synthetic_sample(rng), synthetic_sample(rng, "s1")
    b.lidars["lidar_top"] = LidarSpec("lidar_top", b.lidars["lidar_top"].config, np.eye(4))
    with pytest.raises(ValueError, match="LiDAR 'lidar_top' has another model or mount"):
        write_folder_dataset([a, b], tmp_path / "x")
    with pytest.raises(ValueError, match="points_format 'las'"):
        write_folder_dataset([a], tmp_path / "y", points_format="las")


@pytest.fixture
def written(rng, tmp_path):
    root = tmp_path / "ds"
    write_folder_dataset([synthetic_sample(rng)], root)
    return root


def edit_yaml(path, edit):
    doc = yaml.safe_load(path.read_text())
    edit(doc)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


@pytest.mark.parametrize("edit, key, message", [
    (lambda d: d["boxes"][0].update(colour="red"), "boxes[0].colour", "unknown key"),
    (lambda d: d.update(ego_pose=d["ego_pose"][:3]), "ego_pose", r"expected a 4x4 matrix, got shape \(3, 4\)"),
    (lambda d: d["sweeps"]["lidar_top"].update(sensor_to_world=[[1, 0], [0, 1]]), "sweeps.lidar_top.sensor_to_world",
     "expected a 4x4 matrix"),
    (lambda d: d["boxes"][1].update(rotation=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]), "boxes[1].rotation", "orthonormal"),
    (lambda d: d["boxes"][1].update(yaw=0.3), "boxes[1]", "exactly one of 'rotation' and 'yaw'"),
    (lambda d: d["sweeps"]["lidar_top"].update(motion_compensated=False), "sweeps.lidar_top.motion_compensated",
     "Input should be True"),
    (lambda d: d.update(timestamp="10.0"), "timestamp", "valid number"),
])
def test_bad_sample_yaml_names_file_and_key(written, edit, key, message):
    path = written / "samples" / "000000" / "sample.yaml"
    edit_yaml(path, edit)
    ds = FolderDataset(written)
    with pytest.raises(DatasetError) as exc:
        ds[0]
    text = str(exc.value)
    assert text.startswith(f"{path}: {key}: "), text
    assert re.search(message, text), text


def test_missing_files_name_the_file_and_key(written):
    d = written / "samples" / "000000"
    (d / "CAM_B.png").unlink()
    with pytest.raises(DatasetError, match=rf"{d / 'sample.yaml'}: images\.CAM_B\.file: missing file .*CAM_B\.png"):
        FolderDataset(written)[0]
    (written / "lidars" / "lidar_top.yaml").unlink()
    with pytest.raises(DatasetError, match=r"dataset\.yaml: lidars\.lidar_top\.config: no such file .*lidar_top\.yaml"):
        FolderDataset(written)


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(version=3), r"version: 3 is newer than this reader"),
    (lambda d: d.update(format="other"), r"format: expected 'scube-sim-folder'"),
    (lambda d: d["lidars"]["lidar_top"].update(preset="VLP-16"),
     r"lidars\.lidar_top: .*exactly one of 'preset' and 'config'"),
    (lambda d: d["cameras"]["CAM_A"].update(fx=-1.0), r"cameras\.CAM_A\.fx: expected a finite number > 0, got -1\.0"),
    (lambda d: d["cameras"]["CAM_A"].update(lens="wide"), r"cameras\.CAM_A\.lens: unknown key"),
    (lambda d: d["lidars"].update({"bad/name": d["lidars"]["lidar_top"]}),
     r"lidars\.bad/name\.\[key\]: String should match"),
])
def test_bad_dataset_yaml_names_file_and_key(written, edit, message):
    edit_yaml(written / "dataset.yaml", edit)
    with pytest.raises(DatasetError, match=rf"{written / 'dataset.yaml'}: {message}"):
        FolderDataset(written)


def test_hand_written_dataset_with_a_preset_and_yaw_boxes(tmp_path):
    """What a user converting their own data writes: a preset LiDAR, a .bin cloud, yaw boxes."""
    root = tmp_path / "mine"
    d = root / "samples" / "000000"
    d.mkdir(parents=True)
    pts = np.array([[1.0, 2.0, 0.5, 0.25], [3.0, -1.0, 0.2, 0.75]], np.float32)
    pts.tofile(d / "velo.bin")  # KITTI layout: float32 x y z intensity
    eye = np.eye(4).tolist()
    (root / "dataset.yaml").write_text(yaml.safe_dump({
        "format": "scube-sim-folder", "version": 1,
        "lidars": {"velo": {"preset": "HDL-32E", "sensor_to_ego": eye}}}))
    (d / "sample.yaml").write_text(yaml.safe_dump({
        "name": "frame0", "timestamp": 1.5, "ego_pose": eye,
        "sweeps": {"velo": {"file": "velo.bin", "timestamp": 1.5, "sensor_to_world": eye}},
        "boxes": [{"center": [1, 2, 0.5], "size": [4, 2, 1.5], "yaw": float(np.pi / 2), "label": "car"}]}))
    s = FolderDataset(root)[0]
    np.testing.assert_array_equal(s.sweep("velo").points, pts[:, :3])
    np.testing.assert_array_equal(s.sweep("velo").intensity, pts[:, 3])
    assert s.sweep("velo").ring is None and s.frames is None
    assert s.lidars["velo"].config.channels == 32
    b = s.boxes[0]
    np.testing.assert_allclose(b.rotation @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    assert b.label == 1 and np.all(np.isnan(b.velocity))


def test_sample_folders_are_read_in_natural_order(rng, tmp_path):
    root = tmp_path / "ds"
    write_folder_dataset([synthetic_sample(rng, "a", 1.0), synthetic_sample(rng, "b", 2.0)], root)
    (root / "samples" / "000000").rename(root / "samples" / "frame_9")
    (root / "samples" / "000001").rename(root / "samples" / "frame_10")
    (root / "samples" / ".000002.tmp-1").mkdir()  # a writer's temporary: ignored
    assert [s.name for s in FolderDataset(root)] == ["a", "b"]
