"""Intensity on surfaces of measured reflectance: each sensor's own response, against analytic
targets (a flat wall of Gaussians at x = 10 m, normal +x, so a ray at azimuth phi and elevation 0
meets it at incidence phi). The expected gains and exponents are the numbers the presets' notes
cite (Velodyne manuals; tools/fit_intensity_response.py), written here independently."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from scube_sim.config import ConfigError
from scube_sim.errors import InputError
from scube_sim.labels import LABEL_REFLECTIVITY, label_id
from scube_sim.lidar.config import config_from_dict, load_lidar_config
from scube_sim.lidar.importers import from_velodyne_yaml
from scube_sim.lidar.model import Lidar
from scube_sim.lidar.pattern import replay_pattern
from scube_sim.lidar.response import Response
from scube_sim.raytrace.tracer import Tracer
from scube_sim.voxsplat import Gaussians, VoxSplat
from tests.conftest import require

WALL = label_id("building")
AZ = np.deg2rad(np.linspace(-60, 60, 25))


def wall_of_gaussians(x=10.0, half=20.0, spacing=0.1) -> VoxSplat:
    ys, zs = np.meshgrid(np.arange(-half, half + 1e-9, spacing), np.arange(-4, 4 + 1e-9, spacing))
    n = ys.size
    means = np.c_[np.full(n, x), ys.ravel(), zs.ravel()]
    scales = np.tile([1e-3, spacing / 2, spacing / 2], (n, 1))  # identity rotation: x is the normal
    g = Gaussians(means, scales, np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.99), np.zeros((n, 3), np.float32))
    return VoxSplat.from_gaussians(g, 0.2, labels=np.full(n, WALL), origin=np.zeros(3))


def sweep_wall(scene: VoxSplat, preset: str):
    """Intensity per ray of AZ (elevation 0) from the origin, for a quiet `preset`."""
    cfg = load_lidar_config(preset)
    cfg = cfg.model_copy(update={"noise": cfg.noise.model_copy(update={"range_sigma_m": 0.0, "quantization_m": 0.0}),
                                 "drop": cfg.drop.model_copy(update={"max_incidence_deg": 90.0}), "ego_body": None})
    dirs = np.c_[np.cos(AZ), np.sin(AZ), np.zeros_like(AZ)]
    p = Lidar(cfg, replay_pattern(dirs)).scan(Tracer(scene, mode="max_response"), np.eye(4)).points
    assert np.array_equal(p["column"], np.arange(AZ.size))  # every ray returns
    return p


def test_one_scene_gives_each_sensor_its_own_intensity_scale():
    scene = wall_of_gaussians()
    scene.set_channel("reflectance", np.where(scene.valid, 0.5, np.nan))
    cos = np.cos(AZ)
    hdl32 = sweep_wall(scene, "hdl32e")["intensity"]
    vls = sweep_wall(scene, "vls128")["intensity"]
    # HDL-32E: diffuse 0-100 of 255 for 0-100 %, cos^0.22; VLS-128: 0-110 of 255, Lambertian.
    np.testing.assert_allclose(hdl32, 100 / 255 * 0.5 * cos ** 0.22, rtol=1e-5)
    np.testing.assert_allclose(vls, 110 / 255 * 0.5 * cos, rtol=1e-5)
    assert vls[AZ.size // 2] > hdl32[AZ.size // 2] and vls[0] < hdl32[0]  # head-on vs 60 degrees


def test_without_the_channel_intensity_is_the_class_formula_and_nan_falls_back_per_gaussian():
    scene = wall_of_gaussians()
    cos = np.cos(AZ)
    np.testing.assert_allclose(sweep_wall(scene, "hdl32e")["intensity"], LABEL_REFLECTIVITY[WALL] * cos, rtol=1e-5)
    # Measured on the left half (y > 0) only: the right half keeps the class formula.
    left = scene.means()[..., 1] > 0
    scene.set_channel("reflectance", np.where(scene.valid & left, 0.8, np.nan))
    p = sweep_wall(scene, "hdl32e")
    want = np.where(p["y"] > 0.05, 100 / 255 * 0.8 * cos ** 0.22, LABEL_REFLECTIVITY[WALL] * cos)
    off_seam = np.abs(p["y"]) > 0.05
    np.testing.assert_allclose(p["intensity"][off_seam], want[off_seam], rtol=1e-5)


def _cfg(**response):
    return config_from_dict({"name": "t", "pattern": {"type": "spinning", "columns": 8, "rotation_hz": 10,
                                                      "channels": {"elevation_deg": [0.0, 1.0]}},
                             "intensity": {"falloff_exponent": 2.0, "reference_range_m": 5.0,
                                           "response": response}})


def test_response_forward_and_inverse_agree_and_follow_the_formula():
    r = Response(_cfg(gain=0.4, incidence_exponent=0.5, channel_gain=[1.0, 2.0]).intensity)
    rho = np.array([0.1, 0.3, 0.6, 0.2])
    cos = np.array([1.0, 0.25, 0.5, 0.81])
    rng = np.array([2.0, 10.0, 20.0, 5.0])
    ch = np.array([0, 1, 0, -1])  # -1: unknown laser, gain 1
    want = 0.4 * np.array([1, 2, 1, 1]) * rho * np.sqrt(cos) * np.minimum(1, (5.0 / rng) ** 2)
    np.testing.assert_allclose(r.forward(rho, cos, rng, ch), want)
    np.testing.assert_allclose(r.inverse(want, cos, rng, ch), rho)
    assert r.forward([10.0], [1.0], [1.0], [1])[0] == 1.0  # full scale
    # Grazing: the inverse stops dividing below cos 0.05.
    assert r.inverse([0.01], [0.001], [1.0], [0])[0] == pytest.approx(0.01 / (0.4 * np.sqrt(0.05)))


def test_velodyne_per_laser_correction_by_hand():
    r = Response(_cfg(gain=1.0, velodyne={"focal_distance": [0.0, 1310.0], "focal_slope": [1.0, 0.5],
                                          "min_intensity": [0.0, 20.0], "max_intensity": [255.0, 200.0],
                                          "distance_resolution_m": 0.002}).intensity)
    # At 10 m the fall-off is (5 / 10)^2 = 1/4: rho 0.1 and 0.5 give 6.375 and 31.875 bytes before
    # the correction. Laser 0 at 10 m (5000 units): offset 256, term = 256 - 256 (1 - 5000/65535)^2
    # = 37.573 bytes. Laser 1: offset 256 x 0.9^2 = 207.36, term = 0.5 |207.36 - 218.427| = 5.534.
    rho = [0.1, 0.5]
    out = r.forward(rho, [1.0, 1.0], [10.0, 10.0], [0, 1]) * 255
    np.testing.assert_allclose(out, [6.375 + 37.573, 31.875 + 5.534], atol=2e-3)
    np.testing.assert_allclose(r.inverse(out / 255, [1.0, 1.0], [10.0, 10.0], [0, 1]), rho, atol=1e-5)
    # The clamp: laser 1 never reads above 200 or below 20.
    assert r.forward([100.0], [1.0], [1.0], [1])[0] * 255 == pytest.approx(200.0)
    assert r.forward([0.0], [1.0], [10.0], [1])[0] * 255 == pytest.approx(20.0)


def test_per_laser_tables_must_match_the_channels():
    with pytest.raises(ConfigError, match=r"intensity.response.channel_gain has 3 entries but the pattern has 2"):
        _cfg(channel_gain=[1.0, 1.0, 1.0])
    with pytest.raises(ConfigError, match=r"intensity.response.gain"):
        _cfg(gain=-1.0)


def test_velodyne_calibration_intensity_tables_are_imported(shared_data):
    path = require(shared_data / "velodyne-calibration" / "64e_s3-xiesc.yaml")
    lasers = sorted(yaml.safe_load(path.read_text())["lasers"], key=lambda x: x["laser_id"])
    cfg = from_velodyne_yaml(path, columns=100, rotation_hz=10.0)
    v = cfg.intensity.response.velodyne
    assert v is not None and len(v.focal_slope) == 64
    assert v.focal_distance == [float(x["focal_distance"]) for x in lasers]
    assert v.focal_slope == [float(x["focal_slope"]) for x in lasers]
    # The driver's defaults (0 and 255 where a laser has no limit) and its floor().
    assert v.min_intensity == [float(np.floor(x.get("min_intensity", 0))) for x in lasers]
    assert v.max_intensity == [float(np.floor(x.get("max_intensity", 255))) for x in lasers]
    # Nominal files have no correction: nothing is set.
    assert from_velodyne_yaml(require(shared_data / "velodyne-calibration" / "32db.yaml"), columns=100,
                              rotation_hz=10.0).intensity.response.velodyne is None


def test_reflectance_channel_values_are_checked():
    vs = wall_of_gaussians(half=1.0)
    with pytest.raises(InputError, match=r"channel 'reflectance': values must lie in \[0, 100\]"):
        vs.set_channel("reflectance", np.full(vs.valid.shape, -0.1))
    vs.set_channel("reflectance", np.where(vs.valid, 2.5, np.nan))  # retroreflective, and not known


def test_rings_numbered_by_elevation_map_to_the_vendor_channels():
    """nuScenes numbers HDL-32E rings by elevation; the preset's tables are in laser-id order."""
    from scube_sim.lidar.pattern import channels_by_elevation

    cfg = load_lidar_config("hdl32e")
    el = np.deg2rad(np.asarray(cfg.pattern.channels.elevation_deg))
    order = np.argsort(el)  # laser id of the k-th lowest beam
    rank = np.repeat(np.arange(32), 5)
    az = np.tile(np.linspace(-3, 3, 5), 32)
    e = el[order][rank] + 1e-4  # measured a little off the table
    dirs = np.c_[np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)]
    np.testing.assert_array_equal(channels_by_elevation(dirs, rank, cfg), order[rank])
    assert np.all(channels_by_elevation(dirs, np.full(rank.size, -1), cfg) == -1)  # unknown rings
