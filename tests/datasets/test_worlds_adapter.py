"""`open_dataset("worlds", DIR)` on one tiny generated sample, against expectations computed here:
an OpenCV projection written below (voxel centres -> pixels, compared with the stored depth), the
world regenerated from its seed (boxes, ego poses), the rig file (timestamps), the LiDAR points
placed with their per-point poses landing in occupied voxels; and errors naming the file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from scube_sim.boxes import points_in_boxes
from scube_sim.camera.frames import Frames
from scube_sim.camera.rig import load_rig
from scube_sim.datasets import DatasetError, LidarSweep, Sample, open_dataset
from scube_sim.datasets.base import frames_with_context
from scube_sim.datasets.worlds import WorldsDataset, WorldsSample
from scube_sim.errors import InputError
from scube_sim.labels import label_id
from scube_sim.lidar.config import load_lidar_config
from scube_sim.worlds.dataset import DatasetConfig, generate_dataset
from scube_sim.worlds.generator import generate_world

# The smallest images the rig allows to be useful (FRONT is 77 x 51 px), coarse voxels, two instants.
CFG = DatasetConfig(image_scale=0.04, visibility_scale=0.04, fine_voxel_m=0.4, coarse_factor=2,
                    frame_offsets=[0, 5], lidar="vlp16")
INDEX = 1  # train sample 1 is a suburban world: the quickest to make (~5 s)
CHUNK_CORNER = np.array([-10.24, -51.2, -3.23])  # documented in worlds.groundtruth
CHUNK_SIZE = 102.4


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("worlds")
    generate_dataset(out, "train", 1, CFG, start=INDEX, progress=False)
    return out


@pytest.fixture(scope="module")
def sample(root) -> WorldsSample:
    return open_dataset("worlds", root)[0]


@pytest.fixture(scope="module")
def world(sample):
    return generate_world(sample.ground_truth.world)


def project_opencv(intr, p_cam: np.ndarray) -> np.ndarray:
    """(N, 3) camera points (z > 0) -> (N, 2) pixel coordinates, Brown-Conrady k1 k2 p1 p2 k3,
    pixel (i, j) spanning [i, i + 1) x [j, j + 1)."""
    x, y = p_cam[:, 0] / p_cam[:, 2], p_cam[:, 1] / p_cam[:, 2]
    k1, k2, p1, p2, k3 = intr.dist if intr.dist else (0.0,) * 5
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.c_[intr.fx * xd + intr.cx, intr.fy * yd + intr.cy]


def in_view(im, points_world: np.ndarray):
    """Indices of the points the camera images (in front, inside the picture, inside the lens
    model's one-to-one zone), their pixels (K, 2) int and camera depths z (K,)."""
    w2c = np.linalg.inv(im.cam_to_world)
    pc = points_world @ w2c[:3, :3].T + w2c[:3, 3]
    idx = np.nonzero(pc[:, 2] > 0.5)[0]
    idx = idx[np.hypot(pc[idx, 0], pc[idx, 1]) / pc[idx, 2] < 0.6]
    uv = np.floor(project_opencv(im.intrinsics, pc[idx])).astype(np.int64)
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < im.intrinsics.width) & (uv[:, 1] >= 0) & (uv[:, 1] < im.intrinsics.height)
    return idx[ok], uv[ok], pc[idx[ok], 2]


def fine_centres_world(sample) -> np.ndarray:
    gt = sample.ground_truth
    c = CHUNK_CORNER + (gt.fine.ijk + 0.5) * gt.fine.voxel_size
    return c @ gt.chunk_to_world[:3, :3].T + gt.chunk_to_world[:3, 3]


# --- what a sample holds ----------------------------------------------------------------------


def test_open_dataset_gives_a_worlds_sample(root, sample):
    ds = open_dataset("worlds", root)
    assert isinstance(ds, WorldsDataset) and len(ds) == 1 and ds.split == "train"
    assert isinstance(sample, WorldsSample) and isinstance(sample, Sample)
    assert sample.name == f"train/{INDEX:06d}" and sample.metadata["index"] == INDEX
    rig = load_rig(CFG.rig)
    assert isinstance(sample.frames, Frames) and sample.frames.names == [c.name for c in rig.cameras]
    assert [f.offset for f in sample.timeline] == CFG.frame_offsets
    assert sample.timeline[0].frames is sample.frames and sample.timeline[0].boxes is sample.boxes
    for f in sample.timeline:
        t_ref = f.offset / CFG.frame_rate_hz
        assert f.time == pytest.approx(t_ref) and f.frames.timestamp == pytest.approx(t_ref)
        for im, cam in zip(f.frames.images, rig.cameras):
            assert im.timestamp == pytest.approx(t_ref + cam.time_offset_s)
            assert im.image.shape == (im.intrinsics.height, im.intrinsics.width, 3)
            assert im.intrinsics.width == max(1, round(cam.width * CFG.image_scale))
            assert im.depth.dtype == np.float32 and im.semantic.dtype == np.int16
            np.testing.assert_array_equal(im.sky, im.semantic == label_id("sky"))
            np.testing.assert_array_equal(im.sky, ~np.isfinite(im.depth))
    gt = sample.ground_truth
    assert gt.fine.voxel_size == CFG.fine_voxel_m
    assert gt.coarse.voxel_size == pytest.approx(CFG.fine_voxel_m * CFG.coarse_factor)
    for g in (gt.fine, gt.coarse):
        assert g.ijk.dtype == np.int32 and g.labels.dtype == np.int16 and g.visible.dtype == bool
        assert len(g) > 1000 and 0 < g.visible.mean() < 1
        assert np.all((g.ijk >= 0) & (g.ijk < round(CHUNK_SIZE / g.voxel_size)))
    # the LiDAR: the dataset's sensor, with its preset's mount; a raw sweep over one period
    lidar = load_lidar_config("vlp16")
    assert set(sample.lidars) == {"vlp16"}
    np.testing.assert_allclose(sample.lidars["vlp16"].sensor_to_ego, lidar.mount.matrix())
    (sw,) = sample.sweeps
    assert isinstance(sw, LidarSweep) and sw.sensor == "vlp16" and not sw.motion_compensated
    assert len(sw) == len(gt.lidar_points) > 1000
    assert sw.timestamp == 0.0 and 0.0 <= sw.time_offset.min() and sw.time_offset.max() < 1 / lidar.pattern.rotation_hz
    np.testing.assert_allclose(sw.sensor_to_world, sample.ego_pose @ lidar.mount.matrix(), atol=1e-12)


def test_eval_frames_off_loads_only_the_input_instant(root, sample):
    s = WorldsDataset(root, eval_frames=False)[0]
    assert [f.offset for f in s.timeline] == [0]
    for a, b in zip(s.frames.images, sample.frames.images):
        np.testing.assert_array_equal(a.image, b.image)


def test_poses_and_boxes_match_the_regenerated_world(sample, world):
    rig = load_rig(CFG.rig)
    np.testing.assert_allclose(sample.ground_truth.chunk_to_world, world.ego_pose_at(0.0), atol=1e-12)
    np.testing.assert_allclose(sample.ground_truth.sun_dir, world.sun_dir, atol=1e-15)
    for f in sample.timeline:
        np.testing.assert_allclose(f.frames.ego_pose, world.ego_pose_at(f.time), atol=1e-12)
        for im, cam in zip(f.frames.images, rig.cameras):
            np.testing.assert_allclose(im.cam_to_world, world.ego_pose_at(im.timestamp) @ cam.cam_to_ego(), atol=1e-9)
        expect = world.boxes_at(f.time)
        assert len(f.boxes) == len(expect) > 0
        for got, b in zip(f.boxes, expect):
            assert (got.instance, got.label) == (b.instance, b.label)
            np.testing.assert_array_equal(got.center, b.center)
            np.testing.assert_array_equal(got.size, b.size)
            np.testing.assert_allclose(got.rotation, b.rotation, atol=1e-12)
    # the moving ones move: their boxes at T+5 differ from those at T
    moving = {a.instance for a in world.actors}
    later = {b.instance: b.center for b in sample.timeline[1].boxes}
    assert moving and any(not np.allclose(b.center, later[b.instance]) for b in sample.boxes if b.instance in moving)


def test_pixel_instance_ids_lie_in_their_boxes(sample, world):
    """Each pixel that sees a boxed object (an actor, a parked car) carries that box's instance id:
    its depth, back-projected, lands inside the regenerated world's box of that id at the
    camera's own timestamp; the sky carries 0."""
    checked = 0
    for f in sample.timeline:
        for im in f.frames.images:
            assert im.instance is not None and im.instance.shape == im.depth.shape
            assert np.all(im.instance[im.sky] == 0)
            boxes = {b.instance: b for b in world.boxes_at(im.timestamp)}
            rays = im.intrinsics.pixel_rays().reshape(-1, 3)
            inst = im.instance.reshape(-1)
            for iid in set(np.unique(inst).tolist()) & set(boxes):
                px = np.flatnonzero(inst == iid)
                p_cam = rays[px] * (im.depth.reshape(-1)[px] / rays[px, 2])[:, None]
                p = p_cam @ im.cam_to_world[:3, :3].T + im.cam_to_world[:3, 3]
                # float16 depth: a few centimetres at these ranges
                inside = points_in_boxes(p, [boxes[iid]], margin=0.15) == 0
                assert inside.mean() > 0.99, (im.name, iid, inside.mean())
                checked += px.size
    assert checked > 0


# --- ground truth against an independent projection ---------------------------------------------


def test_depth_at_projected_voxel_centres_matches_their_distance(sample):
    """Every visible fine voxel's centre, projected with the stored camera pose and intrinsics,
    lands on a pixel whose depth is the centre's camera depth (within the voxel: its surface may
    sit up to half a diagonal from the centre), for most voxels of every camera."""
    centres = fine_centres_world(sample)
    vis = np.nonzero(sample.ground_truth.fine.visible)[0]
    v = sample.ground_truth.fine.voxel_size
    for f in sample.timeline[:1]:
        for im in f.frames.images:
            idx, uv, z = in_view(im, centres[vis])
            assert len(idx) > 300, im.name
            err = np.abs(im.depth[uv[:, 1], uv[:, 0]] - z)
            assert np.median(err) < v / 2, im.name
            assert np.mean(err < v) > 0.6, im.name


def test_visible_voxels_are_seen_by_a_camera(sample):
    """A voxel marked visible projects into at least one input camera at T with nothing much
    nearer at that pixel; most voxels not marked visible are hidden from every camera."""
    centres = fine_centres_world(sample)
    gt = sample.ground_truth
    seen = np.zeros(len(gt.fine), bool)
    for im in sample.frames.images:
        idx, uv, z = in_view(im, centres)
        seen[idx[im.depth[uv[:, 1], uv[:, 0]] >= z - 2 * gt.fine.voxel_size]] = True
    assert seen[gt.fine.visible].mean() > 0.9
    assert seen[~gt.fine.visible].mean() < 0.3


def test_lidar_points_with_their_own_poses_land_in_occupied_voxels(sample):
    """The raw sweep's points, each moved to the world by the sensor pose at its fire time, lie
    on the surface the fine voxels hold (the sweep sees the scene at T)."""
    gt = sample.ground_truth
    sw = sample.sweep()
    to_chunk = np.linalg.inv(gt.chunk_to_world)
    v, n = gt.fine.voxel_size, round(CHUNK_SIZE / gt.fine.voxel_size)
    occupied = set(map(tuple, gt.fine.ijk.tolist()))

    def fraction_in_voxels(world_pts):
        p = world_pts @ to_chunk[:3, :3].T + to_chunk[:3, 3]
        ijk = np.floor((p - CHUNK_CORNER) / v).astype(np.int64)
        ijk = ijk[np.all((ijk >= 0) & (ijk < n), axis=1)]
        return np.mean([tuple(k) in occupied for k in ijk.tolist()])

    assert fraction_in_voxels(sw.world_points()) > 0.97
    # the ego moves ~0.5 m during the sweep: ignoring the per-point poses puts many points off the surface
    assert fraction_in_voxels(sw.points @ sw.sensor_to_world[:3, :3].T + sw.sensor_to_world[:3, 3]) < 0.95
    labels = gt.lidar_points["label"]
    assert np.isin(label_id("road"), labels) and np.all(labels != label_id("sky"))


# --- bad input ------------------------------------------------------------------------------


@pytest.fixture
def copy(root, tmp_path) -> Path:
    """A private copy of the dataset to break."""
    out = tmp_path / "ds"
    shutil.copytree(root, out)
    return out


def sample_dir(root: Path) -> Path:
    return root / "train" / f"{INDEX:06d}"


def test_missing_dataset_json(copy):
    (copy / "dataset.json").unlink()
    with pytest.raises(DatasetError, match=r"dataset\.json"):
        open_dataset("worlds", copy)


def test_foreign_dataset_json(copy):
    head = json.loads((copy / "dataset.json").read_text())
    head["format"] = "something-else"
    (copy / "dataset.json").write_text(json.dumps(head))
    with pytest.raises(DatasetError, match=r"dataset\.json.*something-else"):
        open_dataset("worlds", copy)
    (copy / "dataset.json").write_text("{not json")
    with pytest.raises(DatasetError, match=r"dataset\.json: not valid JSON"):
        open_dataset("worlds", copy)


def test_missing_split_and_unknown_split(root):
    with pytest.raises(DatasetError, match=r"val: no 'val' split.*splits here: train"):
        open_dataset("worlds", root, split="val")
    with pytest.raises(DatasetError, match="split: expected one of train, val, test"):
        open_dataset("worlds", root, split="training")


def test_missing_or_broken_meta_json(copy):
    meta = sample_dir(copy) / "meta.json"
    text = meta.read_text()
    meta.unlink()
    ds = open_dataset("worlds", copy)
    with pytest.raises(DatasetError, match=r"000001/meta\.json: missing sample metadata"):
        ds[0]
    meta.write_text(text[: len(text) // 2])
    with pytest.raises(DatasetError, match=r"meta\.json: not valid JSON"):
        ds[0]
    data = json.loads(text)
    data["version"] = 99
    meta.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match=r"meta\.json: format 'scube_sim.worlds' version 99"):
        ds[0]
    del data["frames"]
    data["version"] = 1
    meta.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match=r"meta\.json: missing key 'frames'"):
        ds[0]


@pytest.mark.parametrize("name, match", [
    ("frames.npz", r"frames\.npz: missing per-camera depth"),
    ("voxels.npz", r"voxels\.npz: missing ground-truth voxels"),
    ("lidar.npz", r"lidar\.npz: missing LiDAR sweep"),
    ("rgb_05_FRONT.png", r"rgb_05_FRONT\.png: missing image of camera 'FRONT' at frame offset 5"),
])
def test_missing_sample_file(copy, name, match):
    (sample_dir(copy) / name).unlink()
    with pytest.raises(DatasetError, match=match):
        open_dataset("worlds", copy)[0]


def test_broken_arrays_name_the_file_and_key(copy):
    d = sample_dir(copy)
    (d / "lidar.npz").write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match=r"lidar\.npz: not a readable \.npz"):
        open_dataset("worlds", copy)[0]
    with np.load(d / "frames.npz") as z:
        maps = {k: z[k] for k in z.files if k != "depth_00_SIDE_LEFT"}
    np.savez(d / "frames.npz", **maps)
    with pytest.raises(DatasetError, match=r"frames\.npz: missing array 'depth_00_SIDE_LEFT'"):
        open_dataset("worlds", copy)[0]


def test_index_out_of_range_names_the_split(root):
    ds = open_dataset("worlds", root)
    with pytest.raises(IndexError, match=r"worlds .*train: sample 1 out of range \(have 1\)"):
        ds[1]
    assert len(list(ds)) == 1


def test_unfinished_sample_folders_are_skipped(copy):
    shutil.copytree(sample_dir(copy), copy / "train" / ".tmp-000002")
    (copy / "train" / "notes").mkdir()
    assert len(open_dataset("worlds", copy)) == 1


# --- instants before T (layout version 3) and the converter's context ------------------------------

CTX_CFG = CFG.model_copy(update={"frame_offsets": [-4, -1, 0, 2, 5, 10]})


@pytest.fixture(scope="module")
def ctx_root(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("worlds_ctx")
    generate_dataset(out, "train", 1, CTX_CFG, start=INDEX, progress=False)
    return out


def test_offsets_before_t_round_trip(ctx_root):
    assert json.loads((ctx_root / "dataset.json").read_text())["version"] == 4
    d = sample_dir(ctx_root)
    rig = load_rig(CTX_CFG.rig)
    tags = {"m04", "m01", "00", "02", "05", "10"}
    assert {p.name for p in d.glob("rgb_*.png")} == {f"rgb_{t}_{c.name}.png" for t in tags for c in rig.cameras}
    s = open_dataset("worlds", ctx_root)[0]
    assert s.log == s.name == f"train/{INDEX:06d}" and s.frames.log == s.log and s.frames.offset == 0
    assert [f.offset for f in s.timeline] == CTX_CFG.frame_offsets
    assert s.reference is s.timeline[2] and s.reference.frames is s.frames and s.timestamp == 0.0
    assert [f.offset for f in s.later()] == [2, 5, 10]
    world = generate_world(s.ground_truth.world)
    np.testing.assert_allclose(s.ground_truth.chunk_to_world, s.ego_pose, atol=1e-12)
    pos = []
    for f in s.timeline:
        t = f.offset / CTX_CFG.frame_rate_hz
        assert f.time == pytest.approx(t) and f.frames.offset == f.offset and f.frames.log == s.log
        np.testing.assert_allclose(f.frames.ego_pose, world.ego_pose_at(t), atol=1e-9)
        for im, cam in zip(f.frames.images, rig.cameras):
            assert im.timestamp == pytest.approx(t + cam.time_offset_s)
            np.testing.assert_allclose(im.cam_to_world, world.ego_pose_at(t + cam.time_offset_s) @ cam.cam_to_ego(),
                                       atol=1e-9)
        pos.append(f.frames.ego_pose[:3, 3])
    # the path before T continues the one after it: the same speed, no jump at T
    speed = np.linalg.norm(np.diff(np.array(pos), axis=0), axis=1) / np.diff([f.time for f in s.timeline])
    np.testing.assert_allclose(speed, speed[-1], rtol=1e-3)
    assert speed[-1] > 1.0
    # the images before T are renders of their own instant, not copies of T's
    assert not np.array_equal(s.timeline[0].frames["FRONT"].image, s.frames["FRONT"].image)


def test_frames_with_context_gives_the_stored_instants_but_t_and_the_evaluation_ones(ctx_root):
    ds = open_dataset("worlds", ctx_root)
    world = generate_world(ds[0].ground_truth.world)
    assert frames_with_context(ds, 0, 0).context == []
    for k, want in ((1, [-1]), (2, [-1, 2]), (4, [-4, -1, 2]), (10, [-4, -1, 2]), (50, [-4, -1, 2])):
        assert ds.context_offsets(0, k) == want
        f = frames_with_context(ds, 0, k)
        assert f.offset == 0 and f.log == f"train/{INDEX:06d}" and f.timestamp == 0.0
        assert [c.offset for c in f.context] == want
        for c in f.context:
            t = c.offset / CTX_CFG.frame_rate_hz
            assert c.log == f.log and c.context == [] and c.timestamp == pytest.approx(t)
            np.testing.assert_allclose(c.ego_pose, world.ego_pose_at(t), atol=1e-9)
            got = {b.instance: b.center for b in c.boxes}
            for b in world.boxes_at(t):
                np.testing.assert_allclose(got[b.instance], b.center, atol=1e-9)
            assert all(im.depth is not None and im.semantic is not None for im in c.images)
    # without the later instants loaded, the context is the same
    lean = WorldsDataset(ctx_root, eval_frames=False)
    assert [f.offset for f in lean[0].timeline] == [0]
    assert [c.offset for c in frames_with_context(lean, 0, 4).context] == [-4, -1, 2]
    with pytest.raises(DatasetError, match="context"):
        ds.context_frames(0, -1)


def test_older_datasets_still_read_but_take_no_new_sample(root, copy):
    """The tiny dataset above has offsets 0 and 5 only, written as version 4 (texture version 2).
    Its files are laid out as versions 2 and 3 lay theirs (those differ in their images' looks
    only), so the same folder headed as version 2 or 3 reads the same; it has no context (5 is an
    evaluation instant). A generator run into an older folder is refused: its new samples would
    look different from the old ones."""
    assert json.loads((root / "dataset.json").read_text())["version"] == 4
    assert json.loads((sample_dir(root) / "meta.json").read_text())["version"] == 4
    ds = open_dataset("worlds", root)
    s = ds[0]
    assert s.log == s.name and s.reference is s.timeline[0] and [f.offset for f in s.later()] == [5]
    assert frames_with_context(ds, 0, 10).context == [] and ds.context_offsets(0, 10) == []
    # the headers a reader accepts: versions 2, 3 and 4; 1 and a version 2 that claims offsets before T are refused
    head_path = copy / "dataset.json"
    head = json.loads(head_path.read_text())
    meta_path = sample_dir(copy) / "meta.json"
    meta = json.loads(meta_path.read_text())
    for old in (2, 3):
        head_path.write_text(json.dumps({**head, "version": old}))
        meta_path.write_text(json.dumps({**meta, "version": old}))
        assert len(open_dataset("worlds", copy)) == 1
        with pytest.raises(InputError, match=rf"dataset\.json: dataset version {old} was made with older textures"):
            generate_dataset(copy, "train", 1, None, start=INDEX + 1, progress=False)
    meta_path.write_text(json.dumps(meta))
    head_path.write_text(json.dumps({**head, "version": 1}))
    with pytest.raises(DatasetError, match=r"dataset\.json: dataset version 1"):
        open_dataset("worlds", copy)
    bad = {**head, "version": 2, "config": {**head["config"], "frame_offsets": [-2, 0, 5]}}
    head_path.write_text(json.dumps(bad))
    with pytest.raises(DatasetError, match=r"dataset\.json: dataset version 2 cannot hold frame offsets before T"):
        open_dataset("worlds", copy)


def test_torch_items_take_t_from_offset_0(ctx_root):
    pytest.importorskip("torch")
    from scube_sim.model.data.worlds import DataConfig, WorldsTorchDataset

    item = WorldsTorchDataset(ctx_root, split="train", config=DataConfig(eval_frames=True))[0]
    assert float(item["times"].min()) >= 0.0  # the cameras at T fire after it (waymo-5)
    assert [e["offset"] for e in item["eval_frames"]] == [2, 5, 10]
    assert [e["time"] for e in item["eval_frames"]] == pytest.approx([0.2, 0.5, 1.0])
