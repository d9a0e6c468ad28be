"""`scube_sim.model.data` on a tiny generated worlds dataset (one waymo-5 and one nuscenes-6 sample),
against expectations computed here: an OpenCV projection of the ground-truth voxel centres compared
with the returned depth (after resizes too, so the adjusted K is checked), the world-frame poses
and boxes of the dataset adapter, linear ramps through the resize functions, and the seeding rule."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from pydantic import ValidationError
from torch.utils.data import DataLoader

from scube_sim.boxes import points_in_boxes
from scube_sim.camera.resize import nearest_index, resize_bilinear, resize_nearest, scale_intrinsics
from scube_sim.camera.rig import load_rig
from scube_sim.datasets import open_dataset
from scube_sim.errors import InputError
from scube_sim.labels import label_id
from scube_sim.model.data.augment import CameraSelection
from scube_sim.model.data.worlds import DataConfig, WorldsTorchDataset, collate
from scube_sim.worlds.dataset import DatasetConfig, generate_dataset

# One style, two rigs: sample i has rig RIGS[i % 2] (the samples cycle through the rigs once per
# round of styles). Suburban worlds at 4 % of the rigs' resolution are the quickest to make.
RIGS = ["waymo-5", "nuscenes-6"]
CFG = DatasetConfig(rigs=RIGS, styles=["suburban"], image_scale=0.04, visibility_scale=0.04, fine_voxel_m=0.4,
                    coarse_factor=2, frame_offsets=[0, 5], lidar="vlp16")
CHUNK_CORNER = np.array([-10.24, -51.2, -3.23])  # documented in worlds.groundtruth


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("worlds")
    generate_dataset(out, "train", 2, CFG, progress=False)
    # A test split to refuse: a copy of the train samples is enough for that.
    shutil.copytree(out / "train", out / "test")
    return out


@pytest.fixture(scope="module")
def plain(root) -> list[dict]:
    ds = WorldsTorchDataset(root, config=DataConfig(eval_frames=True))
    return [ds[0], ds[1]]


@pytest.fixture(scope="module")
def samples(root):
    ds = open_dataset("worlds", root, eval_frames=False)
    return [ds[0], ds[1]]


def project_opencv(k: np.ndarray, dist: np.ndarray, p_cam: np.ndarray) -> np.ndarray:
    """(N, 3) camera points (z > 0) -> (N, 2) image coordinates: Brown-Conrady [k1 k2 p1 p2 k3]."""
    x, y = p_cam[:, 0] / p_cam[:, 2], p_cam[:, 1] / p_cam[:, 2]
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.c_[k[0, 0] * xd + k[0, 2], k[1, 1] * yd + k[1, 2]]


def depth_errors(item: dict, k_override=None) -> np.ndarray:
    """|depth at the pixel a visible fine voxel centre projects to - its camera z|, pooled over the
    item's cameras (centres in front, within the lens model's tame zone, inside the image)."""
    v = item["fine_voxel_size"]
    centres = CHUNK_CORNER + (item["fine_ijk"][item["fine_visible"]].numpy() + 0.5) * v
    errs = []
    for n in range(len(item["camera_names"])):
        c2k = item["cam_to_chunk"][n].numpy().astype(np.float64)
        pc = (centres - c2k[:3, 3]) @ c2k[:3, :3]  # chunk -> camera (rigid inverse)
        pc = pc[(pc[:, 2] > 0.5) & (np.hypot(pc[:, 0], pc[:, 1]) < 0.6 * pc[:, 2])]
        k = item["intrinsics"][n].numpy().astype(np.float64) if k_override is None else k_override[n]
        uv = np.floor(project_opencv(k, item["distortion"][n].numpy().astype(np.float64), pc)).astype(np.int64)
        h, w = item["image_size"][n].tolist()
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        errs.append(np.abs(item["depth"][n].numpy()[uv[ok, 1], uv[ok, 0]] - pc[ok, 2]))
    return np.concatenate(errs)


# --- what an item holds -----------------------------------------------------------------------------


def test_items_hold_each_rigs_cameras_with_documented_shapes(plain, samples):
    for item, s, rig_name in zip(plain, samples, RIGS):
        rig = load_rig(rig_name)
        n = len(rig.cameras)
        assert item["camera_names"] == [c.name for c in rig.cameras] and item["sample"] == s.name
        torch.testing.assert_close(item["camera_index"], torch.arange(n))
        h = max(im.intrinsics.height for im in s.frames.images)
        w = max(im.intrinsics.width for im in s.frames.images)
        shapes = {"images": (n, 3, h, w), "intrinsics": (n, 3, 3), "distortion": (n, 5), "image_size": (n, 2),
                  "valid": (n, h, w), "cam_to_chunk": (n, 4, 4), "times": (n,), "depth": (n, h, w),
                  "semantic": (n, h, w), "sky": (n, h, w), "instance": (n, h, w), "chunk_to_world": (4, 4)}
        dtypes = {"images": torch.float32, "intrinsics": torch.float32, "distortion": torch.float32,
                  "image_size": torch.int64, "valid": torch.bool, "cam_to_chunk": torch.float32,
                  "times": torch.float32, "depth": torch.float32, "semantic": torch.int64, "sky": torch.bool,
                  "instance": torch.int64, "chunk_to_world": torch.float64}
        for key, shape in shapes.items():
            assert tuple(item[key].shape) == shape and item[key].dtype == dtypes[key], key
        for level, g in (("fine", s.ground_truth.fine), ("coarse", s.ground_truth.coarse)):
            assert item[f"{level}_ijk"].dtype == torch.int64 and item[f"{level}_labels"].dtype == torch.int64
            np.testing.assert_array_equal(item[f"{level}_ijk"].numpy(), g.ijk)
            np.testing.assert_array_equal(item[f"{level}_labels"].numpy(), g.labels)
            np.testing.assert_array_equal(item[f"{level}_visible"].numpy(), g.visible)
            assert item[f"{level}_voxel_size"] == g.voxel_size
        for i, im in enumerate(s.frames.images):
            ih, iw = im.image.shape[:2]
            assert item["image_size"][i].tolist() == [ih, iw]
            assert item["valid"][i, :ih, :iw].all() and item["valid"][i].sum() == ih * iw
            # as stored (no resize): the image bytes / 255, the maps unchanged, padding as documented
            np.testing.assert_array_equal((item["images"][i, :, :ih, :iw] * 255).round().byte().permute(1, 2, 0),
                                          im.image)
            np.testing.assert_array_equal(item["depth"][i, :ih, :iw].numpy(), im.depth)
            np.testing.assert_array_equal(item["instance"][i, :ih, :iw].numpy(), im.instance)
            pad = ~item["valid"][i]
            assert (item["semantic"][i][pad] == -1).all() and (item["instance"][i][pad] == -1).all()
            assert (item["depth"][i][pad] == 0).all() and not item["sky"][i][pad].any()
            np.testing.assert_allclose(item["intrinsics"][i].numpy(), im.intrinsics.K, rtol=1e-6)
            assert item["times"][i].item() == pytest.approx(im.timestamp - s.timestamp, abs=1e-6)
    # waymo-5's side cameras are shorter than its front ones: their rows below are padding
    assert not plain[0]["valid"][3].all() and plain[0]["valid"][0].all()
    assert plain[0]["distortion"].abs().sum() > 0 and (plain[1]["distortion"] == 0).all()  # opencv vs pinhole


def test_poses_are_camera_to_chunk(plain, samples):
    """chunk_to_world @ cam_to_chunk gives back the adapter's world-frame camera poses; the chunk is
    the ego frame at T, so the cameras sit near their rig mounts in it."""
    for item, s, rig_name in zip(plain, samples, RIGS):
        c2w = item["chunk_to_world"].numpy()
        np.testing.assert_allclose(c2w, s.ego_pose, atol=1e-12)
        mounts = {c.name: c.cam_to_ego() for c in load_rig(rig_name).cameras}
        for i, im in enumerate(s.frames.images):
            c2k = item["cam_to_chunk"][i].numpy().astype(np.float64)
            np.testing.assert_allclose(c2w @ c2k, im.cam_to_world, atol=1e-4)
            # the ego moves less than a metre in the tens of milliseconds between T and the image
            assert np.linalg.norm(c2k[:3, 3] - mounts[im.name][:3, 3]) < 1.0
            np.testing.assert_allclose(c2k[:3, :3], mounts[im.name][:3, :3], atol=0.05)


def test_sky_pixels_have_infinite_depth(plain):
    for item in plain:
        valid = item["valid"]
        assert item["sky"].any() and (~item["sky"] & valid).any()
        assert torch.isinf(item["depth"][item["sky"]]).all()
        assert torch.isfinite(item["depth"][~item["sky"] & valid]).all()
        assert (item["semantic"][item["sky"]] == label_id("sky")).all()
        assert (item["instance"][item["sky"]] == 0).all()


def test_actor_pixels_lie_in_their_boxes(plain, samples):
    """nuscenes-6 (pinhole) pixels with a box's instance id, back-projected with K, depth and
    cam_to_chunk and moved to the world, lie in that box and no other (the boxes are at T, the
    images up to 45 ms earlier: a margin for the actors' motion). Ids without a box are the
    static objects' (buildings, trees, poles); 0 the ground and the sky."""
    item, s = plain[1], samples[1]
    ids = [b.instance for b in s.boxes]
    c2w = item["chunk_to_world"].numpy()
    checked = 0
    for n in range(len(item["camera_names"])):
        inst = item["instance"][n].numpy()
        for iid in set(np.unique(inst).tolist()) & set(ids):
            v, u = np.nonzero(inst == iid)
            z = item["depth"][n].numpy()[v, u].astype(np.float64)
            k = item["intrinsics"][n].numpy().astype(np.float64)
            p_cam = np.c_[(u + 0.5 - k[0, 2]) / k[0, 0] * z, (v + 0.5 - k[1, 2]) / k[1, 1] * z, z]
            pose = c2w @ item["cam_to_chunk"][n].numpy().astype(np.float64)
            p = p_cam @ pose[:3, :3].T + pose[:3, 3]
            which = points_in_boxes(p, s.boxes, margin=0.3)
            assert np.mean(which == ids.index(iid)) > 0.95, (item["camera_names"][n], iid)
            checked += len(u)
        ground = np.isin(item["semantic"][n].numpy(), [label_id("road"), label_id("sidewalk"), label_id("sky")])
        assert (inst[ground] == 0).all()
    assert checked > 500


# --- ground truth against an independent projection, before and after resizing -------------------------


@pytest.mark.parametrize("cfg", [DataConfig(), DataConfig(image_size=(64, 96)), DataConfig(image_scale=2.0)],
                         ids=["stored", "size-64x96", "scale-2"])
def test_voxel_centres_project_onto_their_depth(root, cfg):
    """Visible fine voxel centres, moved into each camera by cam_to_chunk and projected with the
    item's K and distortion, land on pixels whose depth is their camera z (within the voxel: the
    surface may lie half a diagonal from the centre); the stored K on resized maps does not."""
    ds = WorldsTorchDataset(root, config=cfg)
    for i in range(len(ds)):
        item = ds[i]
        v = item["fine_voxel_size"]
        err = depth_errors(item)
        assert len(err) > 2000
        assert np.median(err) < v / 2 and np.mean(err < v) > 0.6, (i, np.median(err), np.mean(err < v))
        if cfg.image_size is not None:
            stored = [np.array(im.intrinsics.K) for im in ds.worlds[i].frames.images]
            bad = depth_errors(item, k_override=stored)
            assert np.median(bad) > v, np.median(bad)


def test_resize_follows_the_pixel_centre_convention():
    """A map holding each pixel centre's ray coordinate x = (u + 0.5 - cx) / fx (linear in u),
    resized bilinearly, holds the ray coordinate the scaled K gives its new pixel centres (away
    from the borders, where bilinear clamps); likewise in y. Exact when enlarging or shrinking by
    an integer factor; the antialiasing filter, truncated to whole source pixels, is off-centre by
    a fraction of a source pixel when shrinking by another factor."""
    k = np.array([[50.0, 0.0, 31.3], [0.0, 47.0, 19.8], [0.0, 0.0, 1.0]])
    h, w = 40, 64
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = torch.tensor(np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1]]), dtype=torch.float64)
    for new, tol_px in (((64, 96), 1e-9), ((40, 64), 1e-9), ((20, 32), 1e-9), ((10, 16), 1e-9), ((25, 37), 0.1)):
        out = resize_bilinear(rays, new).numpy()
        k2 = scale_intrinsics(k, (h, w), new)
        u2, v2 = np.meshgrid(np.arange(new[1]) + 0.5, np.arange(new[0]) + 0.5)
        inner = (slice(2, -2), slice(2, -2))  # the filters reach 2 pixels from the border
        err_u = np.abs(out[0] - (u2 - k2[0, 2]) / k2[0, 0])[inner].max() * k[0, 0]  # in source pixels
        err_v = np.abs(out[1] - (v2 - k2[1, 2]) / k2[1, 1])[inner].max() * k[1, 1]
        assert err_u < tol_px and err_v < tol_px, (new, err_u, err_v)
    # a half-pixel slip (K scaled about pixel centres at integers) is 10 times what the filter does
    slip = k.copy()
    slip[0, 2] = (k[0, 2] - 0.5) * 37 / 64 + 0.5
    assert abs(scale_intrinsics(k, (h, w), (25, 37))[0, 2] - slip[0, 2]) > 0.2
    np.testing.assert_array_equal(scale_intrinsics(k, (h, w), (2 * h, 2 * w)),
                                  [[100.0, 0, 62.6], [0, 94.0, 39.6], [0, 0, 1]])


def test_nearest_resize_takes_the_pixel_holding_each_new_centre():
    # 4 -> 6 pixels: new centres at 0.33, 1, 1.67, 2.33, 3, 3.67 old pixels
    assert nearest_index(4, 6).tolist() == [0, 1, 1, 2, 3, 3]
    # 6 -> 4: new centres at 0.75, 2.25, 3.75, 5.25
    assert nearest_index(6, 4).tolist() == [0, 2, 3, 5]
    a = np.arange(24, dtype=np.int32).reshape(4, 6)
    out = resize_nearest(a, (6, 4))
    assert out.dtype == np.int32
    np.testing.assert_array_equal(out, a[[0, 1, 1, 2, 3, 3]][:, [0, 2, 3, 5]])


# --- training mode --------------------------------------------------------------------------------


def test_test_split_is_never_trained_on(root):
    with pytest.raises(InputError, match="split 'test'.*never trained on"):
        WorldsTorchDataset(root, split="test", train=True)
    item = WorldsTorchDataset(root, split="test", train=False)[0]  # evaluation may read it
    assert item["sample"] == "test/000000"


def test_augmentation_is_a_function_of_seed_epoch_and_index(root, plain):
    cfg = DataConfig(cameras=CameraSelection(mode="drop", drop_p=0.5))
    a = WorldsTorchDataset(root, config=cfg, train=True)
    b = WorldsTorchDataset(root, config=cfg, train=True)
    a.set_epoch(3)
    b.set_epoch(3)
    first = [a[0], a[1]]
    second = [b[1], b[0]][::-1]  # the other order
    loader = DataLoader(b, batch_size=1, num_workers=2, collate_fn=collate)
    third = [{k: v[0] for k, v in batch.items() if isinstance(v, list)} for batch in loader]
    for x, y, z in zip(first, second, third):
        assert x["camera_names"] == y["camera_names"] == z["camera_names"]
        assert torch.equal(x["images"], y["images"]) and torch.equal(x["images"], z["images"])
    a.set_epoch(4)
    assert not all(torch.equal(x["images"], a[i]["images"]) and x["camera_names"] == a[i]["camera_names"]
                   for i, x in enumerate(first))
    other_seed = WorldsTorchDataset(root, config=cfg.model_copy(update={"seed": 1}), train=True)
    other_seed.set_epoch(3)
    assert not torch.equal(other_seed[0]["images"], first[0]["images"]) \
        or other_seed[0]["camera_names"] != first[0]["camera_names"]
    # augmentation changes the images only: each kept camera's maps, K and pose are the plain item's
    for x, p in zip(first, plain):
        idx = x["camera_index"]
        assert not torch.equal(x["images"], p["images"][idx])
        for key in ("depth", "semantic", "sky", "instance", "valid", "intrinsics", "distortion", "cam_to_chunk",
                    "times", "image_size"):
            assert torch.equal(x[key], p[key][idx]), key
        assert x["camera_names"] == [p["camera_names"][i] for i in idx.tolist()]


@pytest.mark.parametrize("mode", ["front", "drop"])
def test_rig_randomisation_keeps_cameras_paired(root, plain, mode):
    cfg = DataConfig(cameras=CameraSelection(mode=mode, drop_p=0.6, keep_front=True))
    ds = WorldsTorchDataset(root, config=cfg, train=True)
    counts = set()
    for epoch in range(3 if mode == "drop" else 1):  # "front" draws nothing
        ds.set_epoch(epoch)
        for i, p in enumerate(plain):
            x = ds[i]
            names = x["camera_names"]
            assert len(names) >= 1 and len(names) == x["images"].shape[0] == x["cam_to_chunk"].shape[0]
            assert names[0] in ("FRONT", "CAM_FRONT")  # kept, and first in rig order
            if mode == "front":
                assert len(names) == 1
            for j, n in enumerate(names):
                src = p["camera_names"].index(n)
                assert x["camera_index"][j] == src
                assert torch.equal(x["intrinsics"][j], p["intrinsics"][src])
                assert torch.equal(x["cam_to_chunk"][j], p["cam_to_chunk"][src])
                assert torch.equal(x["depth"][j], p["depth"][src])
            counts.add(len(names))
    if mode == "drop":
        assert len(counts) > 1  # the subsets vary


def test_eval_frames_are_later_instants_unaugmented(root, plain, samples):
    cfg = DataConfig(eval_frames=True, cameras=CameraSelection(mode="front"))
    x = WorldsTorchDataset(root, config=cfg, train=True)[0]
    (ev,) = x["eval_frames"]
    (ev_plain,) = plain[0]["eval_frames"]
    assert ev["offset"] == 5 and ev["time"] == pytest.approx(0.5)
    assert ev["camera_names"] == [c.name for c in load_rig(RIGS[0]).cameras]  # every camera
    for key in ("images", "depth", "intrinsics", "cam_to_chunk"):
        assert torch.equal(ev[key], ev_plain[key]), key
    later = open_dataset("worlds", root)[0].timeline[1]
    for i, im in enumerate(later.frames.images):
        np.testing.assert_allclose(x["chunk_to_world"].numpy() @ ev["cam_to_chunk"][i].numpy().astype(np.float64),
                                   im.cam_to_world, atol=1e-4)
        assert ev["times"][i].item() == pytest.approx(im.timestamp - samples[0].timestamp, abs=1e-6)
    # the ego drove on: the cameras at T+5 are metres ahead in the chunk frame
    assert ev["cam_to_chunk"][0, 0, 3] - x["cam_to_chunk"][0, 0, 3] > 1.0
    assert "eval_frames" not in WorldsTorchDataset(root)[0]


def test_collate_batches_voxels_with_a_batch_column(plain):
    b = collate(plain)
    assert b["sample"] == [p["sample"] for p in plain] and b["camera_counts"].tolist() == [5, 6]
    assert [t.shape[0] for t in b["images"]] == [5, 6] and b["chunk_to_world"].shape == (2, 4, 4)
    for level in ("fine", "coarse"):
        coords = b[f"{level}_coords"]
        n = [len(p[f"{level}_ijk"]) for p in plain]
        assert coords.shape == (sum(n), 4) and coords.dtype == torch.int64
        assert b[f"{level}_counts"].tolist() == n
        assert torch.equal(coords[:, 0], torch.repeat_interleave(torch.arange(2), torch.tensor(n)))
        for i, p in enumerate(plain):
            sel = coords[:, 0] == i
            assert torch.equal(coords[sel, 1:], p[f"{level}_ijk"])
            assert torch.equal(b[f"{level}_labels"][sel], p[f"{level}_labels"])
            assert torch.equal(b[f"{level}_visible"][sel], p[f"{level}_visible"])
        assert b[f"{level}_voxel_size"].tolist() == [p[f"{level}_voxel_size"] for p in plain]
    assert len(b["eval_frames"]) == 2 and b["eval_frames"][1][0]["offset"] == 5
    with pytest.raises(InputError, match="collate"):
        collate([])


def test_data_config_is_strict():
    DataConfig.model_validate({"image_size": [64, 96], "augment": {"jpeg": {"p": 0.1, "quality": [30, 90]}},
                               "cameras": {"mode": "drop"}})
    with pytest.raises(ValidationError, match="at most one"):
        DataConfig(image_size=(64, 96), image_scale=0.5)
    with pytest.raises(ValidationError, match="Extra inputs"):
        DataConfig.model_validate({"image_sise": [64, 96]})
    with pytest.raises(ValidationError):
        DataConfig.model_validate({"cameras": {"mode": "rear"}})
