"""The depth yardstick (`converter.eval.depth`, `scube-sim eval depth`): metrics on synthetic
predictions against known ground truth, the LiDAR ground truth and its ground rule, and the CLI
on a tiny worlds split."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from scube_sim.camera import CameraImage, Frames, Intrinsics
from scube_sim.camera.depth import lidar_depth
from scube_sim.cli import app
from scube_sim.converter.eval.depth import (
    DepthScore,
    depth_method,
    evaluate_depth,
    format_table,
    ground_returns,
    ground_truth,
    json_ready,
)
from scube_sim.datasets import LidarSweep, Sample
from scube_sim.labels import label_id
from tests.conftest import look_at, one_line_error


def _row(res_rows, band="0-80 m", part="all"):
    return next(r for r in res_rows if r["range"] == band and r["part"] == part)


def test_constant_scale_error_and_holes(rng):
    gt = rng.uniform(1.0, 79.0, (60, 80)).astype(np.float32)
    ground = np.zeros(gt.shape, bool)
    ground[40:] = True
    s = DepthScore()
    s.add(1.1 * gt, gt, ground)
    for r in s.rows():
        if r["gt_pixels"]:
            assert r["coverage"] == 1.0
            assert r["abs_rel"] == pytest.approx(0.1, rel=1e-5)
            assert r["delta_1.25"] == 1.0
    allrow = _row(s.rows())
    assert allrow["gt_pixels"] == gt.size
    assert allrow["median_abs_err_m"] == pytest.approx(0.1 * np.median(gt.astype(np.float64)), rel=3e-3)
    assert allrow["median_rel"] == pytest.approx(0.1, rel=1e-6)  # float32 gt times 1.1
    assert _row(s.rows(), part="ground")["gt_pixels"] == ground.sum()
    # holes: a third of the pixels without a prediction are misses, not dropped from the base
    pred = 1.1 * gt
    holes = np.zeros(gt.shape, bool)
    holes[:, ::3] = True
    pred[holes] = np.nan
    s = DepthScore()
    s.add(pred, gt, ground)
    allrow = _row(s.rows())
    assert allrow["gt_pixels"] == gt.size and allrow["predicted"] == (~holes).sum()
    assert allrow["coverage"] == pytest.approx((~holes).mean())
    assert allrow["abs_rel"] == pytest.approx(0.1, rel=1e-5)
    # a 30 % over-estimate: abs rel 0.3, delta < 1.25 none; pixels beyond 80 m are counted, not scored
    gt2 = gt.copy()
    gt2[0, :10] = np.inf
    gt2[1, :10] = 120.0
    s = DepthScore()
    s.add(1.3 * gt2, gt2, ground)
    assert _row(s.rows())["delta_1.25"] == 0.0 and _row(s.rows())["abs_rel"] == pytest.approx(0.3, rel=1e-5)
    assert _row(s.rows())["gt_pixels"] == gt.size - 20 and s.gt_beyond == 10


def test_median_relative_error_is_exact_per_band_and_part(rng):
    """Ground pixels off by r = 0.001 k (k = 1..100), the others by r = 0.1 + 0.002 k, half of
    each under, half over the truth, shuffled over two images: the medians are the analytic
    middles (even counts: the mean of the two middle values), not a histogram bin's."""
    n = 100
    r = np.concatenate([0.001 * np.arange(1, n + 1), 0.1 + 0.002 * np.arange(1, n + 1)])
    ground = np.arange(2 * n) < n
    sign = np.where(np.arange(2 * n) % 2 == 0, 1.0, -1.0)
    gt = np.where(ground, rng.uniform(10.0, 20.0, 2 * n), rng.uniform(20.0, 40.0, 2 * n))
    pred = gt * (1.0 + sign * r)
    order = rng.permutation(2 * n)
    gt, pred, ground = gt[order], pred[order], ground[order]
    s = DepthScore()
    for half in (slice(0, n), slice(n, 2 * n)):  # two images of 10 x 10
        s.add(pred[half].reshape(10, 10), gt[half].reshape(10, 10), ground[half].reshape(10, 10))
    rows = s.rows()
    want_ground = (0.050 + 0.051) / 2  # ranks 50 and 51 of 0.001 k
    want_other = 0.1 + 0.002 * (50 + 51) / 2
    want_all = (0.100 + 0.102) / 2  # rank 100: the largest ground error, rank 101: the smallest other
    assert _row(rows, part="ground")["median_rel"] == pytest.approx(want_ground, rel=1e-12)
    assert _row(rows, part="not ground")["median_rel"] == pytest.approx(want_other, rel=1e-12)
    assert _row(rows)["median_rel"] == pytest.approx(want_all, rel=1e-12)
    # the bands: ground truth 10-20 m is the ground here, 20-40 m the rest; 0-10 m has no pixel
    assert _row(rows, "10-20 m")["median_rel"] == pytest.approx(want_ground, rel=1e-12)
    assert _row(rows, "20-40 m", "all")["median_rel"] == pytest.approx(want_other, rel=1e-12)
    assert np.isnan(_row(rows, "0-10 m")["median_rel"]) and np.isnan(_row(rows, "20-40 m", "ground")["median_rel"])
    # the mean relative error and the other columns as before
    assert _row(rows)["abs_rel"] == pytest.approx(r.mean(), rel=1e-9)
    # pixels without a prediction or beyond 80 m do not enter it
    s.add(np.array([[np.nan, 500.0]]), np.array([[15.0, 100.0]]), np.zeros((1, 2), bool))
    assert _row(s.rows())["median_rel"] == pytest.approx(want_all, rel=1e-12)
    assert _row(s.rows())["gt_pixels"] == 2 * n + 1 and _row(s.rows())["predicted"] == 2 * n
    res = {"method": "m", "dataset": "d", "samples": 1, "images": 2, "ground_truth": {"lidar": 2},
           "ground_rule": ["LiDAR ground plane"], "coverage_all_pixels": 1.0, "coverage_gt_pixels": 1.0,
           "gt_pixels": 2 * n, "gt_beyond_max": 0, "seconds_per_image": 1.0, "seconds_per_image_max": 1.0,
           "peak_mb": 1.0, "rows": s.rows()}
    lines = format_table(res)
    assert lines[2].endswith("| median abs err (m) | median rel err |")
    assert any(line.startswith("| 0-80 m | all |") and line.endswith(f"| {want_all:.4f} |") for line in lines)
    assert any(line.startswith("| 0-10 m | all |") and line.endswith("| – |") for line in lines)


def _street_sample(with_depth_map: bool = False):
    """A camera 1.5 m above flat ground (z = 0) looking along +x, a wall at x = 25 m, and a LiDAR
    1.8 m up beside the camera whose returns cover both."""
    intr = Intrinsics(96, 64, 60.0, 60.0, 48.0, 32.0)
    pose = look_at([0.0, 0.0, 1.5], [10.0, 0.0, 1.5])
    xs, ys = np.meshgrid(np.arange(3.0, 24.0, 0.1), np.arange(-12.0, 12.0, 0.1))
    ground = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    ys, zs = np.meshgrid(np.arange(-12.0, 12.0, 0.1), np.arange(0.05, 6.0, 0.1))
    wall = np.column_stack([np.full(ys.size, 25.0), ys.ravel(), zs.ravel()])
    pts_world = np.concatenate([ground, wall])
    sensor = np.eye(4)
    sensor[:3, 3] = [0.0, 0.3, 1.8]
    sweep = LidarSweep("top", pts_world - sensor[:3, 3], sensor, 0.0)
    im = CameraImage("front", np.zeros((64, 96, 3), np.uint8), intr, pose, 0.0)
    if with_depth_map:  # a rendered map: the LiDAR's own depth, labels road below the horizon
        im.depth = np.where(np.isfinite(d := lidar_depth(pts_world, im)), d, np.inf).astype(np.float32)
        im.semantic = np.full((64, 96), label_id("building"), np.int16)
        im.semantic[33:] = label_id("road")
    frames = Frames([im], np.eye(4), 0.0)
    return Sample("street", 0.0, np.eye(4), frames, [sweep]), pts_world, len(ground)


class _Scaled:
    """A method that knows the truth: `factor` times a fixed map."""

    name = "scaled"

    def __init__(self, maps, factor=1.1):
        self.maps, self.factor = maps, factor

    def __call__(self, frames, index):
        return self.factor * self.maps[index]


class _OneSample(list):
    name = "street"
    root = "memory"


def test_lidar_ground_truth_and_its_ground_plane():
    sample, pts, n_ground = _street_sample()
    flags = ground_returns(pts, np.array([0.0, 0.0, 1.0]))
    assert flags[:n_ground].all() and flags[n_ground:].mean() < 0.05  # the wall's bottom 0.2 m band only
    (gt, ground, source), = ground_truth(sample)
    assert source == "lidar"
    np.testing.assert_array_equal(np.isfinite(gt), np.isfinite(lidar_depth(pts, sample.frames.images[0])))
    assert ground.any() and (np.isfinite(gt) & ~ground).any()
    res = evaluate_depth(_OneSample([sample]), [0], _Scaled([gt]))
    allrow = _row(res["rows"])
    assert allrow["coverage"] == 1.0 and allrow["abs_rel"] == pytest.approx(0.1, rel=1e-5)
    assert allrow["gt_pixels"] == np.isfinite(gt).sum()
    assert res["coverage_all_pixels"] == pytest.approx(np.isfinite(gt).mean())
    assert res["ground_truth"] == {"lidar": 1} and res["ground_rule"] == ["LiDAR ground plane"]
    assert _row(res["rows"], part="ground")["gt_pixels"] == ground.sum()
    wall_band = _row(res["rows"], "20-40 m", "not ground")
    assert wall_band["gt_pixels"] > 0 and wall_band["delta_1.25"] == 1.0
    json.dumps(json_ready(res), allow_nan=False)
    assert any("| 0-80 m | all |" in line for line in format_table(res))


def test_depth_maps_win_over_lidar_and_labels_give_ground():
    sample, _, _ = _street_sample(with_depth_map=True)
    (gt, ground, source), = ground_truth(sample)
    assert source == "depth map"
    im = sample.frames.images[0]
    np.testing.assert_array_equal(ground, im.semantic == label_id("road"))
    even = np.arange(96)[None, :] % 2 == 0
    holes = _Scaled([np.where(even, gt, np.nan)], 1.0)
    res = evaluate_depth(_OneSample([sample]), [0], holes)
    allrow = _row(res["rows"])
    assert allrow["abs_rel"] == 0.0 and allrow["delta_1.25"] == 1.0
    has_gt = np.isfinite(gt)
    assert allrow["gt_pixels"] == has_gt.sum() and allrow["predicted"] == (has_gt & even).sum()
    assert allrow["coverage"] == pytest.approx((has_gt & even).sum() / has_gt.sum())
    assert res["ground_rule"] == ["semantic labels"]


def test_cli_eval_depth_on_a_tiny_worlds_split(tiny_converter, tmp_path):
    data = tiny_converter["data"]
    out = tmp_path / "depth.json"
    r = CliRunner().invoke(app, ["eval", "depth", "--data", str(data), "--dataset", "worlds", "--split", "test",
                                 "--limit", "1", "--checkpoint", str(tiny_converter["geo"]), "-o", str(out),
                                 "--no-progress"])
    assert r.exit_code == 0, r.output
    assert "| 0-80 m | all |" in r.output and "depth map" in r.output
    res = json.loads(out.read_text())
    assert res["method"] == "mono" and res["samples"] == 1 and res["images"] >= 1
    assert res["coverage_all_pixels"] == 1.0  # the monocular head gives every pixel a depth
    allrow = _row(res["rows"])
    assert allrow["gt_pixels"] > 0 and allrow["coverage"] == 1.0 and 0 <= allrow["abs_rel"]
    assert res["seconds_per_image"] > 0
    # the split folder itself, as `convert --dataset worlds` takes it
    r = CliRunner().invoke(app, ["eval", "depth", "--data", str(data / "test"), "--dataset", "worlds",
                                 "--checkpoint", str(tiny_converter["geo"]), "--no-progress"])
    assert r.exit_code == 0, r.output
    # errors: one line
    one_line_error(CliRunner().invoke(app, ["eval", "depth", "--data", str(data)]), "--dataset")
    one_line_error(CliRunner().invoke(app, ["eval", "depth", "--data", str(data), "--dataset", "worlds",
                                            "--method", "magic", "--no-progress"]), "magic", "mono", "stereo")
    one_line_error(CliRunner().invoke(app, ["eval", "depth", "--data", str(tmp_path / "none"), "--dataset",
                                            "nuscenes", "--no-progress"]), "none")


def test_fused_takes_stereo_where_confident_and_the_head_elsewhere(monkeypatch):
    """The fused map is a per-pixel choice: stereo's depth where its confidence reaches the
    threshold (and it has one), the monocular head's everywhere else."""
    import scube_sim.converter.eval.depth as depth_mod
    from scube_sim.reconstruct.stereo import StereoResult

    h, w = 4, 5
    stereo = np.full((h, w), 7.0, np.float32)
    stereo[0, 0] = np.nan  # no depth, though "confident": the head fills it
    conf = np.zeros((h, w), np.float32)
    conf[:2] = 0.9  # the top two rows are confident
    conf[1, 4] = 0.49  # just under the threshold (0.5)
    monkeypatch.setattr(depth_mod, "stereo_depth",
                        lambda frames, index, cfg: StereoResult(stereo, conf, conf, conf, []))
    monkeypatch.setattr(depth_mod.MonoDepth, "__init__", lambda self, ck, focal=None: None)
    monkeypatch.setattr(depth_mod.MonoDepth, "__call__", lambda self, frames, index: np.full((h, w), 30.0, np.float32))
    fused = depth_method("fused", checkpoint="any")
    out = fused(None, 0)
    want = np.full((h, w), 30.0, np.float32)
    want[:2] = 7.0
    want[0, 0] = want[1, 4] = 30.0
    np.testing.assert_array_equal(out, want)
    assert fused.name == "fused" and "fused" in depth_mod.METHODS
