"""Vendor-file importers: sign conventions against each vendor's own point formula, layouts, errors.

Our beam model (config.py): channel c of a column whose head angle is H (degrees, CCW from +x)
points along az = H + azimuth_offset_deg[c], el = elevation_deg[c], i.e.
d = (cos el cos az, cos el sin az, sin el), from the origin
h (-sin az, cos az, 0) + v (-sin el cos az, -sin el sin az, cos el). A clockwise head at encoder
angle R (degrees, clockwise from forward) has H = -R.
"""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import yaml

from scube_sim.lidar.config import ConfigError
from scube_sim.lidar.importers import from_hesai_csv, from_ouster_json, from_velodyne_yaml, from_waymo_frame
from tests.conftest import require


def our_point(cfg, c: int, head_deg: float, r: float) -> np.ndarray:
    ch = cfg.pattern.channels
    az = math.radians(head_deg + ch.table("azimuth_offset_deg")[c])
    el = math.radians(ch.elevation_deg[c])
    h, v = ch.table("origin_horizontal_m")[c], ch.table("origin_vertical_m")[c]
    d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    o = h * np.array([-math.sin(az), math.cos(az), 0.0]) + v * np.array(
        [-math.sin(el) * math.cos(az), -math.sin(el) * math.sin(az), math.cos(el)])
    return o + r * d


# --- Velodyne ----------------------------------------------------------------------------------


def ros_velodyne_point(laser: dict, rotation_deg: float, distance: float) -> np.ndarray:
    """ros-drivers/velodyne rawdata.cc, with the distance corrections left out (we do not model them)."""
    cos_rot = math.cos(math.radians(rotation_deg) - laser["rot_correction"])  # cos(a - b) in the driver
    sin_rot = math.sin(math.radians(rotation_deg) - laser["rot_correction"])
    el = laser["vert_correction"]
    v = laser.get("vert_offset_correction", 0.0)
    h = laser.get("horiz_offset_correction", 0.0)
    xy = distance * math.cos(el) - v * math.sin(el)
    x = xy * sin_rot - h * cos_rot
    y = xy * cos_rot + h * sin_rot
    z = distance * math.sin(el) + v * math.cos(el)
    return np.array([y, -x, z])  # "standard ROS coordinate system": x_ros = y, y_ros = -x


@pytest.mark.parametrize("fname", ["64e_s2.1-sztaki.yaml", "VeloView-VLP-32C.yaml", "VLS128.yaml"])
def test_velodyne_matches_ros_driver_formula(shared_data, fname):
    path = require(shared_data / "velodyne-calibration" / fname)
    lasers = sorted(yaml.safe_load(path.read_text())["lasers"], key=lambda l: l["laser_id"])
    cfg = from_velodyne_yaml(path, columns=1800, rotation_hz=10)
    n = len(lasers)
    # The sztaki unit has nonzero vertical and horizontal origin offsets and azimuth offsets.
    if fname.startswith("64e"):
        assert np.any(cfg.pattern.channels.table("origin_horizontal_m") != 0)
        assert np.any(cfg.pattern.channels.table("origin_vertical_m") != 0)
    for c in sorted({0, 1, 5, n // 2, n // 2 + 3, n - 1}):
        for rotation in (0.0, 37.5, 123.25, 270.0, 359.99):
            for r in (2.0, 25.0):
                expected = ros_velodyne_point(lasers[c], rotation, r)
                got = our_point(cfg, c, -rotation, r)
                np.testing.assert_allclose(got, expected, atol=1e-9, err_msg=f"laser {c} at {rotation}")


def test_velodyne_ros_frame_forward_is_encoder_zero():
    # A laser with no corrections at encoder 0 points along ROS +x; at 90 degrees along -y (clockwise).
    laser = {"rot_correction": 0.0, "vert_correction": 0.0}
    np.testing.assert_allclose(ros_velodyne_point(laser, 0.0, 1.0), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(ros_velodyne_point(laser, 90.0, 1.0), [0, -1, 0], atol=1e-12)


def test_velodyne_missing_laser_key_and_count(tmp_path):
    good = {"lasers": [{"laser_id": i, "rot_correction": 0.0, "vert_correction": 0.01 * i} for i in range(4)],
            "num_lasers": 4}
    p = tmp_path / "cal.yaml"
    p.write_text(yaml.safe_dump(good))
    cfg = from_velodyne_yaml(p, columns=100, rotation_hz=10, fire_time_us=[0, 1, 2, 3])
    assert cfg.channels == 4 and cfg.pattern.channels.fire_time_us == [0, 1, 2, 3]
    assert cfg.source == "cal.yaml"

    bad = dict(good, num_lasers=5)
    p.write_text(yaml.safe_dump(bad))
    with pytest.raises(ConfigError, match=r"cal\.yaml: num_lasers is 5 but 'lasers' has 4 rows"):
        from_velodyne_yaml(p, columns=100, rotation_hz=10)

    bad = {"lasers": [dict(l) for l in good["lasers"]]}
    del bad["lasers"][2]["vert_correction"]
    p.write_text(yaml.safe_dump(bad))
    with pytest.raises(ConfigError, match=r"cal\.yaml: lasers\[2\]: missing key 'vert_correction'"):
        from_velodyne_yaml(p, columns=100, rotation_hz=10)

    p.write_text(yaml.safe_dump({"num_lasers": 4}))
    with pytest.raises(ConfigError, match=r"cal\.yaml: missing key 'lasers'"):
        from_velodyne_yaml(p, columns=100, rotation_hz=10)

    with pytest.raises(ConfigError, match=r"nope\.yaml: no such file"):
        from_velodyne_yaml(tmp_path / "nope.yaml", columns=100, rotation_hz=10)


def test_velodyne_bad_overrides_name_the_file(tmp_path):
    p = tmp_path / "cal.yaml"
    p.write_text(yaml.safe_dump({"lasers": [{"laser_id": 0, "rot_correction": 0.0, "vert_correction": 0.0}]}))
    with pytest.raises(ConfigError, match=r"cal\.yaml \(imported\): range: .*max_m \(1\.0\) must exceed"):
        from_velodyne_yaml(p, columns=100, rotation_hz=10, range={"min_m": 5.0, "max_m": 1.0})


# --- Hesai -------------------------------------------------------------------------------------


def hesai_sdk_point(elev_deg: float, block_az_deg: float, az_corr_deg: float, r: float) -> np.ndarray:
    """HesaiLidar_SDK_2.0 ComputeXYZI: x = xy sin(az), y = xy cos(az) (x right, y = azimuth 0);
    then turned into our frame (x = their y, y = -their x)."""
    az = math.radians(block_az_deg + az_corr_deg)
    el = math.radians(elev_deg)
    x, y, z = r * math.cos(el) * math.sin(az), r * math.cos(el) * math.cos(az), r * math.sin(el)
    return np.array([y, -x, z])


def test_hesai_matches_sdk_formula(shared_data):
    d = shared_data / "hesai-calibration"
    path = require(d / "Pandar64_Angle_Correction_File.csv")
    with open(path, encoding="utf-8-sig", newline="") as fh:
        rows = list(csv.DictReader(fh))
    cfg = from_hesai_csv(path, columns=1800, rotation_hz=10)
    for c in (0, 7, 8, 9, 33, 63):
        for block in (0.0, 45.2, 181.0, 300.3):
            expected = hesai_sdk_point(float(rows[c]["Elevation"]), block, float(rows[c]["Azimuth"]), 30.0)
            np.testing.assert_allclose(our_point(cfg, c, -block, 30.0), expected, atol=1e-9)


def test_hesai_bom_micro_sign_and_channel_order(tmp_path):
    ang = tmp_path / "X_Angle.csv"
    ang.write_bytes("\ufeffChannel,Elevation,Azimuth\r\n1,2.5,-1.0\r\n2,-3.25,0.5\r\n3,0.0,1.5\r\n".encode("utf-8"))
    fire = tmp_path / "X_Firetime.csv"
    # Rows out of channel order, as in the vendor's Pandar64 file; μs in the header.
    fire.write_bytes("\ufeffChannel,fire time(μs)\r\n3,-1.5\r\n1,-4.25\r\n2,-2.0\r\n".encode("utf-8"))
    cfg = from_hesai_csv(ang, fire, columns=1800, rotation_hz=10, channels=3)
    ch = cfg.pattern.channels
    assert ch.elevation_deg == [2.5, -3.25, 0.0]
    assert ch.azimuth_offset_deg == [1.0, -0.5, -1.5]
    assert ch.fire_time_us == [-4.25, -2.0, -1.5]
    assert cfg.pattern.direction == "cw"

    fire.write_text("Channel,fire time(ns)\n1,1000\n2,2500\n3,0\n", encoding="utf-8")
    assert from_hesai_csv(ang, fire, columns=10, rotation_hz=10).pattern.channels.fire_time_us == [1.0, 2.5, 0.0]


def test_hesai_errors_name_the_file(tmp_path):
    ang = tmp_path / "A.csv"
    ang.write_text("Channel,Elevation\n1,2.5\n2,1.0\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"A\.csv: missing column 'Azimuth'"):
        from_hesai_csv(ang, columns=10, rotation_hz=10)

    ang.write_text("Channel,Elevation,Azimuth\n1,2.5,0\n2,1.0,0\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"A\.csv: expected 64 channel rows, found 2"):
        from_hesai_csv(ang, columns=10, rotation_hz=10, channels=64)

    ang.write_text("Channel,Elevation,Azimuth\n1,2.5,0\n3,1.0,0\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"A\.csv: channels must be numbered 1\.\.2"):
        from_hesai_csv(ang, columns=10, rotation_hz=10)

    ang.write_text("Channel,Elevation,Azimuth\n1,2.5,0\n2,high,0\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"A\.csv: row 3 Elevation: expected a number"):
        from_hesai_csv(ang, columns=10, rotation_hz=10)

    ang.write_text("Channel,Elevation,Azimuth\n1,2.5,0\n2,1.0,0\n", encoding="utf-8")
    fire = tmp_path / "F.csv"
    fire.write_text("Channel,fire time(us)\n1,1.0\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"F\.csv: expected 2 channel rows, found 1"):
        from_hesai_csv(ang, fire, columns=10, rotation_hz=10)
    fire.write_text("Channel,delay\n1,1.0\n2,2.0\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"F\.csv: missing column 'fire time'"):
        from_hesai_csv(ang, fire, columns=10, rotation_hz=10)
    with pytest.raises(ConfigError, match=r"G\.csv: no such file"):
        from_hesai_csv(ang, tmp_path / "G.csv", columns=10, rotation_hz=10)


def test_hesai_mode_table_picks_standard_mode(shared_data):
    d = shared_data / "hesai-calibration"
    ang = require(d / "Pandar128E3X_Angle_Correction_File.csv")
    fire = require(d / "Pandar128E3X_Firetime_Correction_File.csv")
    with open(fire, encoding="utf-8-sig", newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[1][0] == "operation mode" and rows[2][0] == "angle state"
    col = next(i for i in range(1, len(rows[1])) if rows[1][i] == "2" and rows[2][i] == "0")
    assert col == 9  # mode 0 (high resolution) has 4 angle states x 2 distance columns before it
    expected = {int(r[0]): float(r[col]) / 1000.0 for r in rows[3:] if r and r[0].isdigit()}
    cfg = from_hesai_csv(ang, fire, columns=1800, rotation_hz=10, channels=128)
    assert cfg.pattern.channels.fire_time_us == [expected[c] for c in range(1, 129)]
    # Standard mode: every channel fires within one 0.2 degree column (55.6 us at 10 Hz).
    ft = np.array(cfg.pattern.channels.fire_time_us)
    assert ft.min() > 0 and ft.max() < 1e6 / (1800 * 10)
    # High-resolution mode 0 has channels that do not fire in a given angle state (0 in the file),
    # and the OT128 table marks them '-': picking such a column is an error only for '-'.
    ot = require(d / "OT128_Firetime_Correction_File.csv")
    with pytest.raises(ConfigError, match=r"OT128_Firetime_Correction_File\.csv: row 3: channel 1 does not fire"):
        from_hesai_csv(d / "OT128_Angle_Correction_File.csv", ot, columns=1800, rotation_hz=10,
                       operation_mode=0, angle_state=0, mode_table_unit="us")


# --- Ouster ------------------------------------------------------------------------------------


def ouster_sdk_point(meta: dict, mid: int, beam: int, r_mm: float) -> np.ndarray:
    """Ouster sensor docs (ouster-sdk-lidar README), with lidar_origin_to_beam_origin n = 0,
    then lidar_to_sensor_transform's rotation."""
    n_cols = int(meta["lidar_mode"].split("x")[0])
    theta = 2 * math.pi * (1 - mid / n_cols)
    alpha = theta - math.radians(meta["beam_azimuth_angles"][beam])
    phi = math.radians(meta["beam_altitude_angles"][beam])
    p = r_mm * np.array([math.cos(alpha) * math.cos(phi), math.sin(alpha) * math.cos(phi), math.sin(phi)])
    rot = np.asarray(meta["lidar_to_sensor_transform"], dtype=float).reshape(4, 4)[:3, :3]
    return rot @ p / 1000.0


def test_ouster_matches_sdk_formula(shared_data):
    path = require(shared_data / "ouster-sdk-lidar" / "OS-1-128_v2.3.0_1024x10.json")
    meta = json.loads(path.read_text())
    cfg = from_ouster_json(path)
    p = cfg.pattern
    assert (p.columns, p.rotation_hz, p.direction, p.start_azimuth_deg) == (1024, 10.0, "cw", 180.0)
    assert p.channels.fire_time_us is None  # all channels of a column fire together
    for mid in (0, 1, 255, 512, 1000):
        head = p.start_azimuth_deg - mid * 360.0 / p.columns  # clockwise head
        for beam in (0, 1, 2, 3, 64, 127):
            np.testing.assert_allclose(our_point(cfg, beam, head, 12.5), ouster_sdk_point(meta, mid, beam, 12500.0),
                                       atol=1e-9)


def test_ouster_legacy_and_nested_layouts_agree(shared_data, tmp_path):
    legacy_path = require(shared_data / "ouster-sdk-lidar" / "OS-1-128_v2.3.0_1024x10.json")
    legacy = json.loads(legacy_path.read_text())
    nested = {
        "beam_intrinsics": {k: legacy[k] for k in
                            ("beam_altitude_angles", "beam_azimuth_angles", "lidar_origin_to_beam_origin_mm")},
        "config_params": {"lidar_mode": legacy["lidar_mode"]},
        "lidar_data_format": legacy["data_format"],
        "lidar_intrinsics": {"lidar_to_sensor_transform": legacy["lidar_to_sensor_transform"]},
    }
    nested_path = tmp_path / legacy_path.name
    nested_path.write_text(json.dumps(nested))
    a, b = from_ouster_json(legacy_path), from_ouster_json(nested_path)
    assert a.pattern == b.pattern

    # The real nested OS1-64 file.
    os64 = from_ouster_json(require(shared_data / "ouster-sdk-lidar" / "metadata" / "2_1_2_os1-991913000010-64.json"))
    assert os64.channels == 64 and os64.pattern.columns == 1024 and os64.pattern.start_azimuth_deg == 180.0
    # columns / rate arguments override lidar_mode (the 2048-column benchmark setting).
    assert from_ouster_json(legacy_path, columns=2048).pattern.columns == 2048


def test_ouster_errors_name_the_file(tmp_path):
    p = tmp_path / "meta.json"
    base = {"beam_altitude_angles": [1.0, 0.0], "beam_azimuth_angles": [0.5, -0.5], "lidar_mode": "1024x10",
            "data_format": {"pixels_per_column": 2}}
    p.write_text(json.dumps(base))
    assert from_ouster_json(p).pattern.channels.azimuth_offset_deg == [-0.5, 0.5]

    p.write_text(json.dumps(dict(base, data_format={"pixels_per_column": 3})))
    with pytest.raises(ConfigError, match=r"meta\.json: pixels_per_column is 3 but there are 2 beam angles"):
        from_ouster_json(p)
    p.write_text(json.dumps({k: v for k, v in base.items() if k != "beam_azimuth_angles"}))
    with pytest.raises(ConfigError, match=r"meta\.json: missing key beam_intrinsics\.beam_azimuth_angles or "
                                          r"beam_azimuth_angles"):
        from_ouster_json(p)
    p.write_text(json.dumps(dict(base, lidar_mode="fast")))
    with pytest.raises(ConfigError, match=r"meta\.json: lidar_mode 'fast'"):
        from_ouster_json(p)
    p.write_text("{not json")
    with pytest.raises(ConfigError, match=r"meta\.json: not valid JSON \(line 1"):
        from_ouster_json(p)


# --- Waymo -------------------------------------------------------------------------------------


def test_waymo_top(shared_data):
    path = require(shared_data / "waymo-open-dataset-frame" / "frame_metadata.json")
    cfg = from_waymo_frame(path)
    top = next(l for l in json.loads(path.read_text())["laser_calibrations"] if l["name"] == "TOP")
    el = cfg.pattern.channels.elevation_deg
    assert cfg.channels == 64
    np.testing.assert_allclose(el, np.degrees(top["beam_inclinations_rad"]), rtol=0, atol=1e-9)
    assert el == sorted(el)  # the file lists the bottom beam first
    assert (cfg.pattern.columns, cfg.pattern.rotation_hz) == (2650, 10.0)
    ext = np.asarray(top["extrinsic_laser_to_vehicle_4x4"])
    np.testing.assert_allclose(cfg.mount.matrix(), ext, atol=1e-9)
    # Column 0 as in Waymo's range images (range_image_utils.compute_range_image_polar): sensor-frame
    # azimuth pi (1 - 1/W) - az_correction, az_correction = atan2(R[1, 0], R[0, 0]); it looks backwards.
    expected = 180.0 - 180.0 / 2650 - math.degrees(math.atan2(ext[1, 0], ext[0, 0]))
    assert cfg.pattern.start_azimuth_deg == pytest.approx(expected, abs=1e-9)
    head0 = math.radians(cfg.pattern.start_azimuth_deg)
    v = ext[:3, :3] @ np.array([math.cos(head0), math.sin(head0), 0.0])
    assert abs(math.degrees(math.atan2(v[1], v[0]))) > 179.8

    with pytest.raises(ConfigError, match=r"frame_metadata\.json: laser FRONT: beam_inclinations_rad is missing"):
        from_waymo_frame(path, "FRONT")
    with pytest.raises(ConfigError, match=r"frame_metadata\.json: no laser named 'ROOF'; lasers: FRONT"):
        from_waymo_frame(path, "ROOF")
