"""`scube-sim eval sensor-to-sensor`'s measures against hand-made answers (range images, point
sets, poses, voxel look-ups), and the whole evaluation on a tiny worlds sample through the CLI:
the ground-truth VoxSplat's sweep meets its voxel size's error bound on the mesh's rays."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from scube_sim.cli import app
from scube_sim.converter.eval.sensor_to_sensor import (
    ahead_poses,
    clear_rows,
    evaluate_sample,
    evaluate_split,
    geometric_lidar,
    pose_clear,
    seen_labels,
    seen_points,
    sweep_metrics,
)
from scube_sim.converter.pipeline import Converter
from scube_sim.converter.profile import load_profile
from scube_sim.errors import InputError
from scube_sim.labels import label_id
from scube_sim.voxsplat import voxel_keys
from scube_sim.worlds.groundtruth import CHUNK_CORNER


def test_sweep_metrics_on_hand_made_range_images_and_parallel_planes():
    ref = np.full((4, 10), 10.0, np.float32)
    cand = ref.copy()
    cand[0] += 0.5          # ten rays 0.5 m long
    cand[1, :5] = np.nan    # five rays without a return
    rays = np.ones_like(ref, bool)
    rays[3] = False         # not compared
    g = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0), [0.0]), -1).reshape(-1, 3)
    m = sweep_metrics(ref, cand, rays, g, g + [0, 0, 0.3])
    assert m["rays"] == 30
    assert m["hit_agreement"] == pytest.approx(25 / 30)
    # 25 rays return on both: 10 at 0.5 m, 15 at 0
    assert m["median_m"] == pytest.approx(0.0) and m["p90_m"] == pytest.approx(0.5)
    assert m["chamfer_m"] == pytest.approx(0.3)  # planes 0.3 m apart, the same grid
    none = sweep_metrics(ref, np.full_like(ref, np.nan), rays, g, g[:0])
    assert none["hit_agreement"] == 0 and np.isnan(none["median_m"]) and np.isnan(none["chamfer_m"])


def test_pose_clear_finds_an_object_voxel_in_the_ego_box_grown_by_the_margin():
    size = 0.4
    # one building voxel whose centre lies 1.5 m to the side of the ego 60 m on, 0.8 m up
    centre = np.array([61.0, -1.5, 0.8])
    ijk = np.floor((centre - CHUNK_CORNER) / size).astype(np.int16)[None]
    vox = {"coarse_ijk": ijk, "coarse_labels": np.array([label_id("building")], np.uint8), "coarse_voxel_size": size}
    # the box reaches 1.1 m to each side: clear without a margin, not with the 1 m one; 20 m on, clear
    assert pose_clear(vox, 60.0, margin=0.0) and not pose_clear(vox, 60.0) and pose_clear(vox, 20.0)
    road = {**vox, "coarse_labels": np.array([label_id("road")], np.uint8)}
    assert pose_clear(road, 60.0)  # the ground never blocks



def test_clear_rows_summarise_the_rows_of_the_poses_a_car_can_stand_at():
    row = {"scene": "converted", "split": "all", "rays": 10, "median_m": 1.0, "p90_m": 2.0, "hit_agreement": 1.0,
           "chamfer_m": 0.5}
    samples = [{"rows": [{**row, "ahead_m": 0.0}, {**row, "ahead_m": 60.0, "median_m": 9.0}],
                "pose_clear": {"0": True, "60": False}},
               {"rows": [{**row, "ahead_m": 0.0, "median_m": 3.0}, {**row, "ahead_m": 60.0, "median_m": 5.0}],
                "pose_clear": {"0": True, "60": True}}]
    got = {r["ahead_m"]: r for r in clear_rows(samples)}
    assert got[0.0]["rays"] == 20 and got[0.0]["median_m"] == pytest.approx(2.0)
    assert got[60.0]["rays"] == 10 and got[60.0]["median_m"] == pytest.approx(5.0)


def test_ahead_poses_move_the_sensor_along_the_ego_heading_in_the_world():
    lidar = geometric_lidar("vlp16")
    yaw90 = np.array([[0.0, -1, 0, 100], [1, 0, 0, 200], [0, 0, 1, 5], [0, 0, 0, 1]])
    p0, p20 = ahead_poses(lidar, yaw90, (0.0, 20.0))
    np.testing.assert_allclose(p20.world[:3, 3] - p0.world[:3, 3], [0, 20, 0], atol=1e-12)
    np.testing.assert_allclose(p20.chunk[:3, 3] - p0.chunk[:3, 3], [20, 0, 0], atol=1e-12)
    np.testing.assert_allclose(p0.chunk, lidar.mount)
    # the geometric sensor: no noise, no drops, one return
    assert lidar.config.noise.range_sigma_m == 0 and lidar.config.drop.random_rate == 0
    assert lidar.config.beam.return_mode == "strongest"


def test_seen_points_look_up_the_fine_voxel_of_each_point():
    ijk = np.array([[0, 0, 0], [5, 6, 7], [5, 6, 8]])
    voxels = {"fine_ijk": ijk, "fine_visible": np.array([True, True, False]), "fine_voxel_size": np.float64(0.2)}
    pts = CHUNK_CORNER + np.array([[0.1, 0.1, 0.1], [1.05, 1.25, 1.45], [1.05, 1.25, 1.65], [3.0, 3.0, 3.0]])
    np.testing.assert_array_equal(seen_points(pts, voxels), [True, True, False, False])
    assert voxel_keys(ijk).dtype == np.int64


def test_seen_labels_split_seen_voxels_into_ground_and_objects():
    ijk = np.array([[0, 0, 0], [5, 6, 7], [5, 6, 8]])
    voxels = {"fine_ijk": ijk, "fine_visible": np.array([True, True, False]), "fine_voxel_size": np.float64(0.2),
              "fine_labels": np.array([label_id("road"), label_id("car"), label_id("building")], np.uint8)}
    pts = CHUNK_CORNER + np.array([[1.05, 1.25, 1.45], [0.1, 0.1, 0.1], [1.05, 1.25, 1.65], [3.0, 3.0, 3.0]])
    np.testing.assert_array_equal(seen_labels(pts, voxels), [label_id("car"), label_id("road"), -1, -1])


def test_cli_eval_sensor_to_sensor_on_a_tiny_worlds_split(tiny_converter, tmp_path):
    out = tmp_path / "s2s.json"
    r = CliRunner().invoke(app, ["eval", "sensor-to-sensor", "--data", str(tiny_converter["data"]), "--profile",
                                 str(tiny_converter["profile"]), "--sensor", "vlp16", "--gt-voxel", "0.8", "--limit", "1",
                                 "--no-progress", "-o", str(out)])
    assert r.exit_code == 0, r.output
    res = json.loads(out.read_text())
    assert res["samples_n"] == 1 and res["split"] == "test"
    rows = {(x["scene"], x["ahead_m"], x["split"]): x for x in res["rows"]}
    assert {k[1] for k in rows} == {0.0, 20.0, 60.0}
    assert set(res["clear_poses"]) == {"0", "20", "60"} and all(0 <= n <= 1 for n in res["clear_poses"].values())
    assert res["samples"][0]["pose_clear"] == {a: bool(n) for a, n in res["clear_poses"].items()}
    for ahead in (0.0, 20.0, 60.0):
        for scene in ("ground-truth VoxSplat", "converted"):
            a, s, u, so, sg = (rows[(scene, ahead, k)] for k in ("all", "seen", "unseen", "seen-obj", "seen-gnd"))
            assert a["rays"] == s["rays"] + u["rays"] > 1000
            assert s["rays"] == so["rays"] + sg["rays"]
        gt = rows[("ground-truth VoxSplat", ahead, "all")]
        # the ground truth's surfels lie on the mesh: range error well inside a voxel, every ray returns
        assert gt["median_m"] < 0.8 / 4 and gt["hit_agreement"] > 0.99 and gt["chamfer_m"] < 0.8 / 2
    st = res["stages"]
    assert st["seconds"] > 0 and st["peak_mb"] > 0 and np.isfinite(st["input_psnr_db"])
    # the ground truth's surfels sit on the mesh (their centres within a few centimetres); the
    # converted observed surfaces' distances are reported
    assert st["gt_surface_median_m"] < 0.05 and st["surface_median_m"] >= 0 and st["surface_p90_m"] >= st["surface_median_m"]
    assert "median |dr|" in r.output and "converted" in r.output
    # the paper-route profile sees no context by default; the tiny data holds only its own instant
    assert res["samples"][0]["context"] == 0 and res["samples"][0]["offsets"] == [0]


def test_evaluate_sample_hands_back_the_range_images_its_rows_were_scored_on(tiny_converter):
    conv = Converter(load_profile(tiny_converter["profile"]))
    lidar = geometric_lidar("vlp16")
    cache, sweeps = {}, {}
    sample = sorted(d for d in (tiny_converter["data"] / "test").iterdir() if (d / "meta.json").is_file())[0]
    res = evaluate_sample(conv, sample, lidar, gt_voxel=0.8, ahead=(0.0, 20.0), with_psnr=False, gt_cache=cache,
                          sweeps=sweeps)
    assert set(sweeps) == {("converted", 0.0), ("converted", 20.0)}
    (cached,) = cache.values()
    rows = {(r["scene"], r["ahead_m"], r["split"]): r for r in res["rows"]}
    for ref, pose in zip(cached["refs"], cached["poses"]):
        img = sweeps[("converted", pose.ahead)]
        assert img.shape == ref["img"].shape and np.isfinite(img).any()
        for split in ("all", "seen"):
            mask = ref["masks"][split]
            both = mask & np.isfinite(img)
            row = rows[("converted", pose.ahead, split)]
            assert row["hit_agreement"] == pytest.approx(both.sum() / mask.sum())
            assert row["median_m"] == pytest.approx(np.median(np.abs(img - ref["img"])[both]))


def test_eval_sensor_to_sensor_gives_the_converter_the_context_instants(tiny_converter, tmp_path):
    """--context K: the converter is given the sample's instants within K of it (fewer where the
    log holds fewer), and the result records which."""
    from scube_sim.worlds.dataset import generate_dataset

    from ..tiny_converter import TINY

    generate_dataset(tmp_path / "w", "test", 1, TINY.model_copy(update={"frame_offsets": [-2, -1, 0, 1]}), progress=False)
    out = tmp_path / "s2s.json"
    r = CliRunner().invoke(app, ["eval", "sensor-to-sensor", "--data", str(tmp_path / "w"), "--profile",
                                 str(tiny_converter["profile"]), "--sensor", "vlp16", "--gt-voxel", "0.8",
                                 "--context", "1", "--no-progress", "-o", str(out)])
    assert r.exit_code == 0, r.output
    sample = json.loads(out.read_text())["samples"][0]
    assert (sample["context"], sample["offsets"]) == (1, [0, -1, 1])


def test_eval_sensor_to_sensor_names_a_missing_split(tiny_converter, tmp_path):
    with pytest.raises(InputError, match="nosuch"):
        evaluate_split(tiny_converter["data"], split="nosuch", profile=tiny_converter["profile"])
    # a stage no shipped profile names a checkpoint for still needs one (geometry and appearance
    # default to the paper-route profile's: tests/test_tracebacks.py)
    r = CliRunner().invoke(app, ["eval", "stage", "geometry-vae", "--data", str(tiny_converter["data"])])
    assert r.exit_code != 0 and "--checkpoint" in r.output
