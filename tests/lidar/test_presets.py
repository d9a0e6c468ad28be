"""Shipped presets (sensors/lidar/*.yaml): resolvable by name, faithful to their vendor files,
and the config loader's error messages."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
import yaml

from scube_sim.lidar.config import ConfigError, LidarConfig, SpinningPattern, load_lidar_config, preset_paths
from tests.conftest import require


# Independent readers of the vendor files: (elevations in degrees, azimuth offsets in our
# CCW convention or None when the file has none).
def velodyne(path: Path):
    lasers = sorted(yaml.safe_load(path.read_text())["lasers"], key=lambda l: l["laser_id"])
    return [math.degrees(l["vert_correction"]) for l in lasers], [math.degrees(l["rot_correction"]) for l in lasers]


def hesai(path: Path):
    with open(path, encoding="utf-8-sig", newline="") as fh:
        rows = sorted(csv.DictReader(fh), key=lambda r: int(r["Channel"]))
    return [float(r["Elevation"]) for r in rows], [-float(r["Azimuth"]) for r in rows]


def ouster(path: Path):
    meta = json.loads(path.read_text())
    beams = meta.get("beam_intrinsics", meta)
    return list(map(float, beams["beam_altitude_angles"])), [-float(a) for a in beams["beam_azimuth_angles"]]


def waymo(path: Path):
    top = next(l for l in json.loads(path.read_text())["laser_calibrations"] if l["name"] == "TOP")
    return [math.degrees(v) for v in top["beam_inclinations_rad"]], None


# id, a punctuated / case-varied name, file under ../shared/data, reader, channels
PRESETS = [
    ("vlp16", "VLP-16", "velodyne-calibration/VLP16db.yaml", velodyne, 16),
    ("hdl32e", "HDL_32E", "velodyne-calibration/32db.yaml", velodyne, 32),
    ("hdl64e", "Hdl-64e", "velodyne-calibration/64e_utexas.yaml", velodyne, 64),
    ("vlp32c", "vlp_32C", "velodyne-calibration/VeloView-VLP-32C.yaml", velodyne, 32),
    ("vls128", "VLS-128", "velodyne-calibration/VLS128.yaml", velodyne, 128),
    ("os1-64", "OS1_64", "ouster-sdk-lidar/metadata/2_1_2_os1-991913000010-64.json", ouster, 64),
    ("os1-128", "OS1_128", "ouster-sdk-lidar/OS-1-128_v2.3.0_1024x10.json", ouster, 128),
    ("pandar64", "Pandar-64", "hesai-calibration/Pandar64_Angle_Correction_File.csv", hesai, 64),
    ("pandar128", "PANDAR_128", "hesai-calibration/Pandar128E3X_Angle_Correction_File.csv", hesai, 128),
    ("waymo-top", "Waymo Top", "waymo-open-dataset-frame/frame_metadata.json", waymo, 64),
]
IDS = [p[0] for p in PRESETS]


def test_all_presets_shipped():
    assert sorted(preset_paths()) == sorted(i.replace("-", "") for i in IDS)


@pytest.mark.parametrize("pid, alias, rel, reader, n", PRESETS, ids=IDS)
def test_preset_loads_by_id_and_alias(pid, alias, rel, reader, n):
    cfg = load_lidar_config(pid)
    assert isinstance(cfg, LidarConfig) and isinstance(cfg.pattern, SpinningPattern)
    assert cfg.id == pid
    assert cfg.channels == n
    assert load_lidar_config(alias) == cfg
    assert load_lidar_config(preset_paths()[pid.replace("-", "")]) == cfg  # by path
    assert Path(rel).name in cfg.source
    assert cfg.notes
    assert cfg.intensity.source == "class" and cfg.beam.return_mode == "strongest"
    assert cfg.drop.max_incidence_deg == 85 and cfg.ego_body is None
    fire = cfg.pattern.channels.table("fire_time_us")
    # Every channel fires within its column's period (negative: before the encoder instant).
    assert abs(fire).max() < 1e6 / (cfg.pattern.columns * cfg.pattern.rotation_hz)


def test_display_name_resolves():
    assert load_lidar_config("Pandar128E3X").id == "pandar128"


@pytest.mark.parametrize("pid, alias, rel, reader, n", PRESETS, ids=IDS)
def test_preset_matches_vendor_file(shared_data, pid, alias, rel, reader, n):
    elevation, azimuth = reader(require(shared_data / rel))
    ch = load_lidar_config(pid).pattern.channels
    assert len(elevation) == ch.count == n
    for ours, theirs in zip(ch.elevation_deg, elevation, strict=True):
        assert abs(ours - theirs) <= 1e-9
    got = ch.table("azimuth_offset_deg")
    expected = azimuth if azimuth is not None else [0.0] * n
    for ours, theirs in zip(got, expected, strict=True):
        assert abs(ours - theirs) <= 1e-9


def test_preset_fire_times():
    # Spot checks of the published firing sequences (see tools/make_presets.py).
    assert load_lidar_config("vlp16").pattern.channels.fire_time_us[15] == pytest.approx(15 * 2.304)
    assert load_lidar_config("hdl32e").pattern.channels.fire_time_us[31] == pytest.approx(31 * 1.152)
    ft = load_lidar_config("hdl64e").pattern.channels.fire_time_us
    assert ft[:32] == ft[32:] and ft[5] == pytest.approx(7.26)
    assert load_lidar_config("vlp32c").pattern.channels.fire_time_us[:4] == [0.0, 0.0, 2.304, 2.304]


def test_pandar64_fire_times_are_the_vendor_file(shared_data):
    path = require(shared_data / "hesai-calibration" / "Pandar64_Firetime_Correction_File.csv")
    with open(path, encoding="utf-8-sig", newline="") as fh:
        vendor = {int(r[0]): float(r[1]) for r in list(csv.reader(fh))[1:] if r}
    assert load_lidar_config("pandar64").pattern.channels.fire_time_us == [vendor[c] for c in range(1, 65)]


# --- config loader errors ----------------------------------------------------------------------

MINIMAL = """\
name: test
pattern:
  type: spinning
  columns: 100
  rotation_hz: 10
  channels:
    elevation_deg: [-1.0, 1.0]
"""


def test_minimal_file_loads(tmp_path):
    p = tmp_path / "mini.yaml"
    p.write_text(MINIMAL)
    assert load_lidar_config(p).channels == 2


def test_bad_indentation_names_file_and_line(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text(MINIMAL.replace("  columns: 100", "   columns: 100"))
    with pytest.raises(ConfigError) as exc:
        load_lidar_config(p)
    msg = str(exc.value)
    assert str(p) in msg and "not valid YAML" in msg and "line 4" in msg


def test_unknown_key_names_the_key_path(tmp_path):
    p = tmp_path / "typo.yaml"
    p.write_text(MINIMAL.replace("elevation_deg: [-1.0, 1.0]", "elevation_deg: [-1.0, 1.0]\n    elevaton_deg: [0]"))
    with pytest.raises(ConfigError, match=r"typo\.yaml: pattern\.channels\.elevaton_deg: unknown key"):
        load_lidar_config(p)


def test_wrong_type_names_key_and_type(tmp_path):
    p = tmp_path / "type.yaml"
    p.write_text(MINIMAL.replace("columns: 100", "columns: many"))
    with pytest.raises(ConfigError, match=r"type\.yaml: pattern\.columns: .*valid integer"):
        load_lidar_config(p)
    p.write_text(MINIMAL + "noise:\n  range_sigma_m: [1]\n")
    with pytest.raises(ConfigError, match=r"type\.yaml: noise\.range_sigma_m: .*valid number"):
        load_lidar_config(p)


def test_unknown_sensor_lists_presets():
    with pytest.raises(ConfigError) as exc:
        load_lidar_config("vlp-17")
    msg = str(exc.value)
    assert "'vlp-17'" in msg
    for pid in IDS:
        assert pid in msg


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match=r"absent\.yaml: no such file"):
        load_lidar_config(tmp_path / "absent.yaml")
