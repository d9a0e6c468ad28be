"""Fitting and scoring the ray-drop model: the logistic fit against data drawn from known weights,
the scores by hand, the ego body of a full grid, and a whole study on an exact scene whose
"real" sensor drops every return beyond 25 m."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.datasets.base import LidarSweep
from scube_sim.errors import InputError
from scube_sim.lidar.config import load_lidar_config
from scube_sim.lidar.drop import DropModel
from scube_sim.lidar.model import Lidar
from scube_sim.mesh import TriangleMesh
from scube_sim.raytrace.tracer import Tracer
from scube_sim.realdata.fidelity import real_rays
from scube_sim.realdata.raydrop import auc, drop_scores, drop_study, fit_logistic, log_loss
from scube_sim.transforms import make_pose
from scube_sim.worlds import primitives as pr

H = 1.8


def test_logistic_fit_recovers_known_weights():
    rng = np.random.default_rng(0)
    n = 40000
    x = np.c_[rng.normal(0, 1, n), rng.uniform(0, 3, n)]
    z = -1.0 + 0.8 * x[:, 0] - 0.5 * x[:, 1]
    y = rng.random(n) < 1 / (1 + np.exp(-z))
    w = fit_logistic(x, y, l2=1e-3)
    # Standard errors at this n are about 0.015-0.03.
    np.testing.assert_allclose(w, [-1.0, 0.8, -0.5], atol=0.08)


def test_scores_by_hand():
    assert auc(np.array([0.1, 0.4, 0.35, 0.8]), np.array([0, 0, 1, 1], bool)) == pytest.approx(0.75)
    assert auc(np.array([1.0, 1.0, 0.0]), np.array([1, 0, 0], bool)) == pytest.approx(0.75)  # a tie counts half
    assert log_loss(np.full(4, 0.5), np.array([0, 1, 0, 1], bool)) == pytest.approx(np.log(2))
    s = drop_scores(np.array([True, True, False, False, False]), np.array([True, False, False, True, False]))
    assert (s["real drop, sim drop"], s["real drop, sim return"], s["real return, sim drop"],
            s["real return, sim return"]) == (2, 1, 1, 1)
    assert s["drop precision"] == pytest.approx(2 / 3) and s["drop recall"] == pytest.approx(2 / 3)
    assert s["hit agreement"] == pytest.approx(3 / 5)


def full_grid_sweep(max_return_m=25.0, columns=360):
    """An HDL-32E full grid over ground and a wall 20 m ahead, stored as nuScenes stores it:
    every ring of every column, a no-return at the origin; this "real" sensor returns nothing
    beyond `max_return_m` (the far ground), and its lowest rays see the car's roof 0.5 m away
    towards the back."""
    scene = TriangleMesh.concatenate([
        pr.quad([[-80, -80, -H], [80, -80, -H], [80, 80, -H], [-80, 80, -H]]),
        pr.quad([[20, -80, -H], [20, 80, -H], [20, 80, 8], [20, -80, 8]])])
    cfg = load_lidar_config("HDL-32E")
    cfg = cfg.model_copy(update={
        "pattern": cfg.pattern.model_copy(update={"columns": columns}),
        "noise": cfg.noise.model_copy(update={"range_sigma_m": 0.0, "quantization_m": 0.0}),
        "drop": cfg.drop.model_copy(update={"max_incidence_deg": 90.0}), "ego_body": None})
    lidar = Lidar(cfg)
    out = lidar.scan(Tracer(scene), make_pose()).points
    pat = lidar.pattern
    rng = np.full(len(pat), np.inf)
    rng[out["column"] * 32 + out["ring"]] = out["range"]  # pulse index = column * 32 + channel
    pts = pat.directions * np.where(rng <= max_return_m, rng, 0.0)[:, None]
    roof = (np.rad2deg(pat.elevation) < -25.0) & (np.abs(np.rad2deg(pat.azimuth)) > 120.0)
    pts[roof] = 0.5 * pat.directions[roof]  # the car's own roof, off the sensor's plane
    sweep = LidarSweep("top", pts, make_pose(), 0.0, ring=pat.ring.astype(np.int16))
    return scene, cfg, sweep, roof


def test_full_grid_rays_into_the_ego_body_are_flagged():
    _, _, sweep, roof = full_grid_sweep()
    rays = real_rays(sweep)
    assert rays.no_returns_known and len(rays) == len(sweep)
    np.testing.assert_array_equal(rays.ego_body, roof)


def test_drop_study_learns_a_range_limit_and_beats_the_hand_set_rules(tmp_path):
    scene, cfg, sweep, _ = full_grid_sweep()
    study = drop_study(scene, cfg, sweep, tmp_path / "drop.yaml", l2=1.0, seed=1)
    model = DropModel.load(tmp_path / "drop.yaml")
    assert model.coefficients["log_range"] > 0  # farther, more drops
    assert model.scores["fitted model"]["hit agreement"] == pytest.approx(study.scores["fitted model"]["hit agreement"],
                                                                          abs=1e-4)  # written to the file
    fitted, hand = study.scores["fitted model"], study.scores["hand-set rules (preset)"]
    # The truth is a step at 25 m; a logistic in log range gets nearly all of it.
    assert fitted["drop recall"] > 0.95 and fitted["drop precision"] > 0.95
    assert fitted["hit agreement"] > hand["hit agreement"] + 0.1
    assert study.probabilistic["fitted model"]["auc"] > 0.99
    # Scored on the odd 30-degree sectors, the rays into the ego body left out.
    rays = real_rays(sweep)
    az = np.rad2deg(np.arctan2(rays.directions[:, 1], rays.directions[:, 0])) + 180.0
    odd = (az // 30).astype(int) % 2 == 1
    assert fitted["rays"] == int((odd & ~rays.ego_body).sum()) < int(odd.sum())


def test_drop_study_needs_the_no_returns():
    scene, cfg, sweep, _ = full_grid_sweep()
    returns_only = sweep.subset(np.linalg.norm(sweep.points, axis=1) > 1.0)
    with pytest.raises(InputError, match="records its no-returns"):
        drop_study(scene, cfg, returns_only, "unused.yaml")


def test_transfer_study_fits_one_sensor_and_scores_another(tmp_path):
    """Fitted on one sensor's grid, scored on another's (another column count, so other rays) of
    the same scene, both dropping every return beyond 25 m."""
    from scube_sim.realdata.raydrop import transfer_study

    scene, cfg, sweep_a, _ = full_grid_sweep(columns=360)
    _, _, sweep_b, roof_b = full_grid_sweep(columns=300)
    rays_a, rays_b = real_rays(sweep_a), real_rays(sweep_b)
    study = transfer_study((scene, cfg, rays_a, sweep_a), (scene, cfg, rays_b, sweep_b), tmp_path / "d.yaml",
                           l2=1.0, seed=1)
    fitted, hand = study.scores["model fitted on top"], study.scores["hand-set rules (preset)"]
    assert fitted["rays"] == int((~roof_b).sum())  # the ego body left out
    assert fitted["drop recall"] > 0.95 and fitted["drop precision"] > 0.95
    assert fitted["hit agreement"] > hand["hit agreement"] + 0.1
    assert DropModel.load(tmp_path / "d.yaml").coefficients["log_range"] > 0
