"""The converter end to end on tiny models: frames in, a VoxSplat out with provenance, the same
bytes for the same seed, the world frame kept to 1e-4 m at 10^6 m from the origin, confidence
counted over K samples, and clear errors for input it cannot use."""

from __future__ import annotations

import copy
import hashlib
import re
import subprocess
import sys

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from scube_sim.camera.frames import CameraImage, Frames
from scube_sim.camera.model import Intrinsics
from scube_sim.cli import app
from scube_sim.converter.frames import network_inputs, open_frames
from scube_sim.converter.pipeline import Converter
from scube_sim.converter.profile import FineProfile, load_profile
from scube_sim.datasets import open_dataset
from scube_sim.errors import InputError
from scube_sim.voxsplat import VoxSplat


def _frames(tiny_converter) -> Frames:
    return open_frames(tiny_converter["sample"])


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_importing_the_package_does_not_import_torch():
    code = "import sys, scube_sim; assert callable(scube_sim.convert); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_cli_converts_a_worlds_sample_with_provenance_and_the_same_bytes_twice(tiny_converter, tmp_path):
    outs = []
    for name in ("a.npz", "b.npz"):
        r = CliRunner().invoke(app, ["convert", str(tiny_converter["sample"]), "--profile", str(tiny_converter["profile"]),
                                     "--seed", "3", "-o", str(tmp_path / name)])
        assert r.exit_code == 0, r.output
        outs.append(tmp_path / name)
    assert outs[0].read_bytes() == outs[1].read_bytes()
    vs = VoxSplat.load(outs[0])
    m = vs.metadata
    assert m["source"] == "scube_sim.convert" and m["profile"] == "tiny" and m["seed"] == 3
    assert m["geometry_checkpoint"]["sha256"] == _sha(tiny_converter["geo"])
    assert m["appearance_checkpoint"]["sha256"] == _sha(tiny_converter["app"])
    assert m["sample_steps"] == 2 and m["confidence_samples"] == 1
    gt = open_dataset("worlds", tiny_converter["data"], split="test")[0].ground_truth
    np.testing.assert_array_equal(np.array(m["chunk_to_world"]), gt.chunk_to_world)
    assert vs.voxel_size == pytest.approx(3.2) and vs.gaussians_per_voxel == 2
    assert vs.num_voxels > 0
    # every voxel inside the 102.4 x 102.4 x 25.6 m box the geometry stage predicts
    assert (vs.ijk >= 0).all() and (vs.ijk[:, :2] < 32).all() and (vs.ijk[:, 2] < 8).all()
    assert vs.channel("observed").dtype == bool and len(vs.channel("observed")) == vs.num_voxels
    assert (vs.channel("confidence") == 1.0).all()  # one sample: confidence 1
    assert vs.channel("sky_panorama").shape == (8, 16, 3)
    assert vs.channel("reflectance").shape == (vs.num_voxels, 2)
    # `lidar --mode auto` traces a converted scene in the mode it names (soft)
    assert m["trace_mode"] == "soft"
    r = CliRunner().invoke(app, ["lidar", str(outs[0]), "--sensor", "vlp16", "--pose", "0,0,1.8,0,0,0",
                                 "-o", str(tmp_path / "s.pcd")])
    assert r.exit_code == 0 and "mode soft" in r.output, r.output


def test_cli_convert_shows_each_stage_and_takes_threads(tiny_converter, tmp_path, monkeypatch):
    """Off a terminal (CliRunner's stderr), one line per stage as it starts; --no-progress none;
    --threads sizes the pools (the same bytes) and a negative count is refused in one line."""
    import torch

    monkeypatch.setenv("SCUBE_SIM_THREADS", "2")  # the command sets it; keep the test process's own
    before = torch.get_num_threads()
    base = ["convert", str(tiny_converter["sample"]), "--profile", str(tiny_converter["profile"])]
    try:
        r = CliRunner().invoke(app, [*base, "-o", str(tmp_path / "a.npz"), "--threads", "1"])
        assert r.exit_code == 0, r.output
        stages = [m.group(1) for ln in r.stderr.splitlines() if (m := re.match(r"\s*\d+\.\d s  (.*)", ln))]
        assert stages[0].startswith("loading profile") and stages[1].startswith("opening")
        assert stages[2].startswith("geometry:") and stages[3].startswith("appearance:")
        assert stages[-1].startswith("writing") and len(stages) == 5
        quiet = CliRunner().invoke(app, [*base, "-o", str(tmp_path / "b.npz"), "--no-progress", "--threads", "2"])
        assert quiet.exit_code == 0 and " s  " not in quiet.stderr, quiet.output
        assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
        bad = CliRunner().invoke(app, [*base, "-o", str(tmp_path / "c.npz"), "--threads", "-1"])
        assert bad.exit_code == 2 and "--threads: expected an integer from 0 to 1024, got -1" in bad.output
        assert not (tmp_path / "c.npz").exists()
    finally:
        torch.set_num_threads(before)


def test_the_same_file_whatever_torch_s_thread_count(tiny_converter, tmp_path):
    """A batch worker runs on one thread, `convert` on all the cores: the networks' sums split by
    thread count (without the converter's pin, 1 and 2 threads differ by ~1e-6 here), the files
    must not."""
    import torch

    threads = torch.get_num_threads()
    conv = Converter(tiny_converter["profile"])
    files = []
    try:
        for n in (2, 1):
            torch.set_num_threads(n)
            files.append(conv.convert(_frames(tiny_converter), seed=1).scene.save(tmp_path / f"t{n}.npz").read_bytes())
            assert torch.get_num_threads() == n  # the caller's setting is restored
    finally:
        torch.set_num_threads(threads)
    assert files[0] == files[1]


def test_confidence_is_counted_over_k_samples_and_the_first_is_the_plain_conversion(tiny_converter):
    conv = Converter(tiny_converter["profile"])
    frames = _frames(tiny_converter)
    one = conv.convert(frames, seed=1).scene
    many = conv.convert(frames, seed=1, confidence=True).scene
    assert many.metadata["confidence_samples"] == 3
    np.testing.assert_array_equal(one.ijk, many.ijk)
    c = many.channel("confidence")
    assert set(np.round(c * 3).astype(int).tolist()) <= {1, 2, 3}
    # the share each voxel gets is the count of samples (seeds 1, 2, 3) that hold it
    sets = [{tuple(v) for v in conv.convert(frames, seed=s).scene.ijk.tolist()} for s in (1, 2, 3)]
    expect = np.array([sum(tuple(v) in s for s in sets) / 3 for v in many.ijk.tolist()], np.float32)
    np.testing.assert_allclose(c, expect, atol=1e-6)


def test_a_lidar_only_conversion_skips_the_sky_and_keeps_the_gaussians(tiny_converter):
    conv = Converter(tiny_converter["profile"])
    frames = _frames(tiny_converter)
    full = conv.convert(frames, seed=0).scene
    lidar = conv.convert(frames, seed=0, sky=False).scene
    assert "sky_panorama" not in lidar.channels and "sky_panorama" in full.channels
    np.testing.assert_array_equal(lidar.params, full.params)
    near = conv.convert(frames, seed=0, sky=False, max_range=30.0).scene
    centres = full.voxel_centers() + full.origin
    inside = np.linalg.norm(centres[:, :2], axis=1) <= 30.0
    assert 0 < near.num_voxels == int(inside.sum()) < full.num_voxels
    np.testing.assert_array_equal(near.ijk, full.ijk[inside])
    with pytest.raises(InputError, match="max_range"):
        conv.convert(frames, max_range=-1.0).scene


def test_a_fit_to_the_input_views_is_a_profile_knob_with_provenance(tiny_converter, tmp_path):
    """fit_steps: the Gaussians after the network, fitted to the input views; the voxels stay,
    the Gaussians move; recorded in the metadata; deterministic; LiDAR-only keeps no sky."""
    conv = Converter(tiny_converter["profile"])
    frames = _frames(tiny_converter)
    plain = conv.convert(frames, seed=0).scene
    steps = []
    fitted = conv.convert(frames, seed=0, fit_steps=3, progress=lambda step, total: steps.append((step, total))).scene
    assert steps == [(1, 3), (2, 3), (3, 3)]
    assert plain.metadata["fit_steps"] == 0 and fitted.metadata["fit_steps"] == 3
    np.testing.assert_array_equal(fitted.ijk, plain.ijk)
    assert np.isfinite(fitted.params).all() and not np.array_equal(fitted.params, plain.params)
    again = conv.convert(frames, seed=0, fit_steps=3).scene
    np.testing.assert_array_equal(again.params, fitted.params)
    np.testing.assert_array_equal(again.channel("sky_panorama"), fitted.channel("sky_panorama"))
    lidar = conv.convert(frames, seed=0, fit_steps=3, sky=False).scene
    assert "sky_panorama" not in lidar.channels
    np.testing.assert_array_equal(lidar.params, fitted.params)
    with pytest.raises(InputError, match="fit_steps"):
        conv.convert(frames, fit_steps=-2).scene
    r = CliRunner().invoke(app, ["convert", str(tiny_converter["sample"]), "--profile", str(tiny_converter["profile"]),
                                 "--fit-steps", "-1", "-o", str(tmp_path / "x.npz")])
    assert r.exit_code == 2 and "--fit-steps" in r.output and not (tmp_path / "x.npz").exists()


def _moved(frames: Frames, offset) -> Frames:
    out = copy.deepcopy(frames)
    out.ego_pose[:3, 3] += offset
    for im in out.images:
        im.cam_to_world[:3, 3] += offset
    return out


def test_frames_a_million_metres_out_convert_to_the_same_scene(tiny_converter):
    conv = Converter(tiny_converter["profile"])
    frames = _frames(tiny_converter)
    near = conv.convert(frames, seed=2).scene
    far = conv.convert(_moved(frames, np.array([1.0e6, -1.0e6, 30.0])), seed=2).scene
    np.testing.assert_array_equal(near.ijk, far.ijk)
    np.testing.assert_allclose(far.means(), near.means(), rtol=0, atol=1e-4)
    shift = np.array(far.metadata["chunk_to_world"])[:3, 3] - np.array(near.metadata["chunk_to_world"])[:3, 3]
    np.testing.assert_allclose(shift, [1.0e6, -1.0e6, 30.0], rtol=0, atol=1e-6)


def _camera(name, width, height, fx, pose, image=None):
    intr = Intrinsics(width, height, fx, fx, width / 2, height / 2)
    img = np.full((height, width, 3), 128, np.uint8) if image is None else image
    return CameraImage(name, img, intr, pose, 0.0)


def test_any_image_size_meets_the_network_at_its_focal_length(tiny_converter):
    """A 64 x 48 and a 4000 x 3000 camera with the same field of view resize to the same size
    (the profile's focal length), so memory is bounded by the field of view."""
    conv = Converter(tiny_converter["profile"])
    base = _frames(tiny_converter).images[0]
    fov = 2 * np.arctan(base.intrinsics.width / 2 / base.intrinsics.K[0, 0])
    cams = [_camera(f"c{w}", w, h, w / 2 / np.tan(fov / 2), base.cam_to_world) for w, h in ((64, 48), (4000, 3000))]
    frames = Frames(cams, _frames(tiny_converter).ego_pose, 0.0, {"sample": "sizes"})
    item = network_inputs(frames, conv.profile.geometry)
    small, large = item["image_size"].tolist()
    assert abs(small[1] - large[1]) <= 1 and abs(small[0] - large[0]) <= 1
    # the profile's focal length is the dataset camera's: the same field of view, the same width
    assert abs(large[1] - base.intrinsics.width) <= 1
    np.testing.assert_allclose(item["intrinsics"][:, 0, 0].numpy(), conv.profile.geometry.focal_px, rtol=0.05)
    vs = conv.convert(frames, seed=0).scene
    assert np.isfinite(vs.params).all()


def test_a_camera_that_sees_only_sky_and_frames_without_sky_masks_give_defined_output(tiny_converter):
    conv = Converter(tiny_converter["profile"])
    frames = _frames(tiny_converter)
    bare = copy.deepcopy(frames)
    for im in bare.images:  # a real adapter's frames: no depth, semantics or sky masks
        im.depth = im.semantic = im.sky = im.instance = None
    vs = conv.convert(bare, seed=0).scene
    assert vs.channel("sky_panorama").shape == (8, 16, 3) and np.isfinite(vs.channel("sky_panorama")).all()
    up = np.eye(4)  # 2 m over the ego, optical axis (camera z) straight up, camera x to the ego's right
    up[:3, :3] = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # columns x, y, z
    up[:3, 3] = [0.0, 0.0, 2.0]
    pose = frames.ego_pose @ up
    sky_only = Frames([_camera("UP", 32, 24, 16.0, pose)], frames.ego_pose, 0.0, {"sample": "up"})
    vs = conv.convert(sky_only, seed=0).scene
    assert np.isfinite(vs.params).all() and vs.channel("sky_panorama").shape == (8, 16, 3)


def test_bad_input_gives_clear_errors(tiny_converter, tmp_path):
    conv = Converter(tiny_converter["profile"])
    frames = _frames(tiny_converter)
    with pytest.raises(InputError, match="no images"):
        conv.convert(Frames([], frames.ego_pose, 0.0)).scene
    with pytest.raises(InputError, match="expected a scube_sim.camera.Frames"):
        conv.convert({"images": []}).scene
    dup = copy.deepcopy(frames)
    dup.images[1].name = dup.images[0].name
    with pytest.raises(InputError, match="camera names must be unique"):
        conv.convert(dup).scene
    with pytest.raises(InputError, match="seed"):
        conv.convert(frames, seed=-1).scene
    with pytest.raises(InputError, match="shipped"):
        load_profile("no-such-profile")
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"geometry": {"checkpoint": "x", "focal_px": -1}}))
    with pytest.raises(InputError, match="bad.yaml"):
        load_profile(bad)
    with pytest.raises(InputError, match="not a worlds sample folder"):
        open_frames(tmp_path)
    r = CliRunner().invoke(app, ["convert", str(tmp_path), "--profile", str(tiny_converter["profile"]),
                                 "-o", str(tmp_path / "x.npz")])
    assert r.exit_code == 2 and "not a worlds sample folder" in r.output
    assert not (tmp_path / "x.npz").exists()
    r = CliRunner().invoke(app, ["convert", str(tiny_converter["sample"]), "--profile", str(tiny_converter["profile"]),
                                 "-o", str(tmp_path / "x.ply")])
    assert r.exit_code == 2 and ".npz" in r.output


def test_real_frames_convert_and_a_lidar_only_log_is_refused(tiny_converter, shared_data):
    """The nuScenes demo keyframe's six 1600 x 900 cameras meet the network at the profile's focal
    length and convert; an Argoverse 2 sample (LiDAR only here) gets a clear error."""
    from tests.conftest import require

    root = require(shared_data / "nuscenes-mmdet3d-demo" / "n015-2018-07-24-11-22-45+0800.pkl").parent
    frames = open_frames(root, "nuscenes", 0)
    assert len(frames) == 6 and frames.metadata["dataset"] == "nuscenes"
    conv = Converter(tiny_converter["profile"])
    item = network_inputs(frames, conv.profile.geometry)
    np.testing.assert_allclose(item["intrinsics"][:, 0, 0].numpy(), conv.profile.geometry.focal_px, rtol=0.01)
    vs = conv.convert(frames, seed=0, sky=False).scene
    assert np.isfinite(vs.params).all() and vs.metadata["cameras"] == frames.names
    assert vs.channel("observed").shape == (vs.num_voxels,)
    av2 = require(shared_data / "argoverse2-sensor-log-7fab2350")
    with pytest.raises(InputError, match="no camera images"):
        open_frames(av2, "argoverse2", 0)


def test_one_camera_and_twenty_cameras_convert(tiny_converter):
    conv = Converter(tiny_converter["profile"])
    frames = _frames(tiny_converter)
    one = Frames(frames.images[:1], frames.ego_pose, 0.0, {"sample": "one"})
    assert np.isfinite(conv.convert(one, seed=0).scene.params).all()
    many = []
    for i in range(20):  # the rig's cameras again and again, each a new name
        im = copy.deepcopy(frames.images[i % len(frames.images)])
        im.name = f"cam{i:02d}"
        many.append(im)
    vs = conv.convert(Frames(many, frames.ego_pose, 0.0, {"sample": "twenty"}), seed=0).scene
    assert np.isfinite(vs.params).all() and len(vs.metadata["cameras"]) == 20


def test_an_ego_frame_above_the_road_is_moved_down_by_its_height(tiny_converter):
    """Frames whose ego frame sits ego_height_m above the road (KITTI's Velodyne) convert as the
    same frames with the ego pose lowered by that height: the chunk starts at road level."""
    conv = Converter(tiny_converter["profile"])
    frames = _frames(tiny_converter)
    raised = copy.deepcopy(frames)
    lift = np.eye(4)
    lift[2, 3] = 1.5
    raised.ego_pose = raised.ego_pose @ lift
    raised.metadata["ego_height_m"] = 1.5
    a, b = conv.convert(frames, seed=0).scene, conv.convert(raised, seed=0).scene
    np.testing.assert_array_equal(a.ijk, b.ijk)
    np.testing.assert_allclose(a.params, b.params, rtol=0, atol=1e-5)
    np.testing.assert_allclose(np.array(a.metadata["chunk_to_world"]), np.array(b.metadata["chunk_to_world"]),
                               rtol=0, atol=1e-9)
    raised.metadata["ego_height_m"] = "tall"
    with pytest.raises(InputError, match="ego_height_m"):
        conv.convert(raised).scene


def test_a_profile_keeps_the_m_most_opaque_gaussians_per_voxel(tiny_converter):
    prof = load_profile(tiny_converter["profile"])
    one = prof.model_copy(update={"appearance": prof.appearance.model_copy(update={"gaussians_per_voxel": 1})})
    frames = _frames(tiny_converter)
    full = Converter(prof).convert(frames, seed=0, sky=False).scene
    cut = Converter(one).convert(frames, seed=0, sky=False).scene
    assert full.gaussians_per_voxel == 2 and cut.gaussians_per_voxel == 1
    np.testing.assert_array_equal(cut.ijk, full.ijk)
    np.testing.assert_allclose(cut.opacities()[:, 0], np.where(full.valid, full.opacities(), -1).max(1), rtol=1e-6)


def test_a_convert_batch_loads_the_model_once_per_worker_and_writes_what_convert_writes(tiny_converter, tmp_path):
    """Three worlds samples on one worker process: the converter loads for the first task only,
    and each scene.npz equals `scube-sim convert` of that sample, byte for byte."""
    from scube_sim.parallel.runner import run_batch
    from scube_sim.runs.batch_jobs import make_job

    samples = [tiny_converter["data"] / split / "000000" for split in ("train", "val", "test")]
    out = tmp_path / "batch"
    rep = run_batch(make_job("convert", {"profile": str(tiny_converter["profile"]), "seed": 3}), [str(s) for s in samples],
                    out, workers=1, progress=False)
    assert (rep.status, rep.completed) == ("complete", 3)
    loaded = [rep.records[f"{s.parent.name}/000000"]["stats"]["model_loaded"] for s in samples]
    assert loaded == [True, False, False]  # one worker runs them in order: one load
    for s in samples:
        direct = tmp_path / f"{s.parent.name}.npz"
        r = CliRunner().invoke(app, ["convert", str(s), "--profile", str(tiny_converter["profile"]), "--seed", "3",
                                     "-o", str(direct)])
        assert r.exit_code == 0, r.output
        assert _sha(out / s.parent.name / "000000" / "scene.npz") == _sha(direct)


# --- the fine level ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_fine(tiny_converter, tmp_path_factory):
    from .tiny_converter import build_fine

    return build_fine(tiny_converter, tmp_path_factory.mktemp("fine"))


def _with_fine(tiny_converter, fine_ck, **fine):
    prof = load_profile(tiny_converter["profile"])
    return prof.model_copy(update={"fine": FineProfile(checkpoint=str(fine_ck), focal_px=prof.geometry.focal_px,
                                                       **fine)})


def test_the_fine_level_subdivides_the_coarse_prediction(tiny_converter, tiny_fine):
    frames = _frames(tiny_converter)
    coarse = Converter(load_profile(tiny_converter["profile"])).convert(frames, seed=0, sky=False).scene
    conv = Converter(_with_fine(tiny_converter, tiny_fine))
    fine = conv.convert(frames, seed=0, sky=False).scene
    assert (coarse.voxel_size, fine.voxel_size) == (3.2, 1.6) and len(fine.ijk) > 0
    # every fine voxel is a child of a coarse one (both indexed from the same chunk corner), and
    # carries its parent's confidence
    parent = {tuple(v): c for v, c in zip(coarse.ijk.tolist(), coarse.channel("confidence"))}
    kids = [tuple(v) for v in (fine.ijk // 2).tolist()]
    assert all(k in parent for k in kids)
    np.testing.assert_array_equal(fine.channel("confidence"), np.array([parent[k] for k in kids], np.float32))
    assert fine.channel("observed").dtype == bool and fine.channel("observed").any()
    meta = fine.metadata
    assert meta["fine_checkpoint"]["sha256"] == hashlib.sha256(tiny_fine.read_bytes()).hexdigest()
    assert coarse.metadata["fine_checkpoint"] is None
    # the same frames and seed: the same scene
    again = conv.convert(frames, seed=0, sky=False).scene
    np.testing.assert_array_equal(again.ijk, fine.ijk)
    np.testing.assert_array_equal(again.params, fine.params)


def test_the_fine_level_groups_into_the_output_voxel_size(tiny_converter, tiny_fine):
    frames = _frames(tiny_converter)
    fine = Converter(_with_fine(tiny_converter, tiny_fine)).convert(frames, seed=0, sky=False).scene
    grouped = Converter(_with_fine(tiny_converter, tiny_fine, output_voxel_size=3.2)).convert(frames, seed=0,
                                                                                               sky=False).scene
    assert grouped.voxel_size == 3.2
    # an output voxel wherever one of its 8 children is, labelled by the children's most common label
    # (ties: the lowest id)
    keys, inverse = np.unique(fine.ijk // 2, axis=0, return_inverse=True)
    np.testing.assert_array_equal(grouped.ijk, keys)
    votes = np.zeros((len(keys), 256), np.int64)
    np.add.at(votes, (inverse.ravel(), fine.labels.astype(np.int64)), 1)
    np.testing.assert_array_equal(grouped.labels, votes.argmax(1))


def test_bad_fine_settings_name_the_key(tiny_converter, tiny_fine):
    with pytest.raises(InputError, match="fine.output_voxel_size"):
        Converter(_with_fine(tiny_converter, tiny_fine, output_voxel_size=2.4))
    with pytest.raises(InputError, match="fine-level"):
        Converter(_with_fine(tiny_converter, tiny_converter["geo"]))
