"""The fitted ray-drop model in the LiDAR model: selected by `drop.model` in a sensor YAML,
sampled with the sweep's seed, and dropping at the logistic rate its file states (analytic:
a wall at x = 10 m, rays at azimuth phi meet it at incidence phi)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from scube_sim.config import ConfigError
from scube_sim.lidar.config import load_config_file
from scube_sim.lidar.drop import DropModel
from scube_sim.lidar.model import Lidar
from scube_sim.raytrace.tracer import Tracer
from scube_sim.worlds import primitives as pr


def wall(x=10.0, half=200.0):
    return pr.quad([[x, -half, -half], [x, -half, half], [x, half, half], [x, half, -half]], label=14)


def sensor_yaml(tmp_path, model_file="drop.yaml", n=4000, az_deg=(0.0, 60.0)):
    """A sensor with `n` rays in each of two azimuths, its drop model at `model_file` (relative)."""
    az = np.repeat(az_deg, n)
    cfg = {"name": "two-directions", "pattern": {"type": "emitter", "azimuth_deg": az.tolist(),
                                                 "elevation_deg": [0.0] * az.size},
           "range": {"min_m": 0.3, "max_m": 200.0}, "drop": {"model": model_file}}
    path = tmp_path / "sensor.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_drop_model_from_a_sensor_yaml_drops_at_its_logistic_rate(tmp_path):
    # p(drop) = sigmoid(-1 + 2 cos): head-on (cos 1) sigmoid(1) = 0.731, at 60 degrees sigmoid(0) = 0.5.
    DropModel(-1.0, {"cos_incidence": 2.0}).save(tmp_path / "drop.yaml")
    cfg = load_config_file(sensor_yaml(tmp_path))
    assert cfg.drop.model == str((tmp_path / "drop.yaml").resolve())  # relative to the sensor YAML
    lidar = Lidar(cfg)
    p = lidar.scan(Tracer(wall()), np.eye(4), seed=5).points
    n = 4000
    for az, want in ((0.0, 1 / (1 + np.exp(-1.0))), (60.0, 0.5)):
        kept = np.sum(np.isclose(np.rad2deg(p["azimuth"]), az, atol=1e-3))
        sd = np.sqrt(n * want * (1 - want))
        assert abs((n - kept) - n * want) < 4 * sd
    # The sweep's seed: the same seed, the same sweep; another seed, another one.
    again = lidar.scan(Tracer(wall()), np.eye(4), seed=5).points
    other = lidar.scan(Tracer(wall()), np.eye(4), seed=6).points
    assert again.tobytes() == p.tobytes() and other.tobytes() != p.tobytes()


def test_unknown_labels_and_rings_weigh_nothing():
    m = DropModel(0.0, {"label.car": 5.0, "ring.3": -5.0})
    p = m.probability([1.0, 1.0, 1.0], [10.0, 10.0, 10.0], [0.3, 0.3, 0.3], [1, 14, 14], [0, 0, 3])
    np.testing.assert_allclose(p, [1 / (1 + np.exp(-5.0)), 0.5, 1 / (1 + np.exp(5.0))])


def test_bad_drop_model_files_name_the_file_and_key(tmp_path):
    with pytest.raises(ConfigError, match=r"drop\.model: .*nothere\.yaml: no such file"):
        Lidar(load_config_file(sensor_yaml(tmp_path, "nothere.yaml")))
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"format": "scube_sim.drop_model", "version": 1, "intercept": 0.0,
                                   "coefficients": {"colour": 1.0}}))
    with pytest.raises(ConfigError, match=r"bad\.yaml: coefficients: unknown term 'colour'"):
        DropModel.load(bad)
    bad.write_text(yaml.safe_dump({"format": "scube_sim.drop_model", "version": 1, "intercept": 0.0,
                                   "coefficients": {"label.spaceship": 1.0}}))
    with pytest.raises(ConfigError, match=r"'label\.spaceship' names no label"):
        DropModel.load(bad)
    bad.write_text(yaml.safe_dump({"format": "something else"}))
    with pytest.raises(ConfigError, match=r"bad\.yaml: key 'format'"):
        DropModel.load(bad)


def test_shipped_hdl32e_drop_model_loads_and_is_no_preset():
    from scube_sim.lidar.config import preset_paths
    from scube_sim.resources import sensors_dir

    path = sensors_dir() / "lidar" / "hdl32e.drop.yaml"
    m = DropModel.load(path)
    assert m.sensor == "HDL-32E" and "nuScenes" in m.source
    assert "hdl32edrop" not in preset_paths()
