"""(Re)write the shipped LiDAR presets in `sensors/lidar/` from the vendor files in ../shared/data.

    .venv/bin/python tools/make_presets.py [--data ../shared/data] [--out sensors/lidar]

Each preset names its source (repository, commit, path, and the file name in ../shared/data) and
says in `notes` what came from the file and what did not. The vendor files themselves are never
copied: only the numbers, with their source, go into our YAML.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from scube_sim.io.safe_pickle import load_pickle  # noqa: E402
from scube_sim.lidar.config import dump_config  # noqa: E402
from scube_sim.lidar.importers import (
    from_hesai_csv,
    from_ouster_json,
    from_velodyne_yaml,
    from_waymo_frame,
    velodyne_distance_resolution,
)
from scube_sim.transforms import euler_to_rotmat, rotmat_to_euler  # noqa: E402

VELODYNE = ("ros-drivers/velodyne @ 29abd0e1361cb7f5eda451d2b51c35eeca45e0d5, "
            "velodyne_pointcloud/params/{f} (../shared/data/velodyne-calibration/{f})")
HESAI = ("HesaiTechnology/HesaiLidar_SDK_2.0 @ ea7f86fad62fe53c947bd9f29f9216be5bae7b1d, "
         "correction/angle_correction/{m}_Angle Correction File.csv and "
         "correction/firetime_correction/{m}_Firetime Correction File.csv "
         "(../shared/data/hesai-calibration/{m}_Angle_Correction_File.csv, {m}_Firetime_Correction_File.csv)")
OUSTER = ("ouster-lidar/ouster-sdk @ 46b7bceee7995914e2f3f3facf4d78418335b2d7, {p} "
          "(../shared/data/ouster-sdk-lidar/{local})")
WAYMO = ("waymo-research/waymo-open-dataset @ 99a4cb3ff07e2fe06c2ce73da001f850f628e45a, "
         "src/waymo_open_dataset/utils/testdata/pvps_data_one_frame.tfrecord, laser_calibrations[TOP] "
         "(extracted to ../shared/data/waymo-open-dataset-frame/frame_metadata.json)")

# Common to every preset (see the issue): class reflectivity, strongest return, 85 degree grazing cut.
COMMON = {
    "intensity": {"source": "class"},
    "beam": {"return_mode": "strongest"},
    "drop": {"max_incidence_deg": 85.0},
}
# The response to measured reflectance (`intensity.response`, lidar/response.py). gain: the
# reading of a white (100 %) diffuse target as a share of the 0-255 full scale, from the vendor's
# manual; incidence_exponent: measured on the shared logs by tools/fit_intensity_response.py
# (across surfaces: HDL-32E 0.220 on nuScenes; HDL-64E 0.208 and 0.251 on KITTI raw frames 0 and
# 2; VLP-32C 0.157 and 0.180 on Argoverse 2's up and down sensors); sensors without a log here
# keep the Lambertian cosine (1).
CALIBRATED = "reports calibrated reflectivity, distance-independent (fall-off exponent 0)"
RESPONSES = {
    "vlp16": ({"gain": round(100 / 255, 6)},
              "Response to measured reflectance: gain 100/255 (VLP-16 manual, 'Calibrated Reflectivity': "
              f"diffuse 0-100 for 0-100 %; {CALIBRATED}); incidence: Lambertian cosine (not measured here)."),
    "hdl32e": ({"gain": round(100 / 255, 6), "incidence_exponent": 0.22},
               "Response to measured reflectance: gain 100/255 (Velodyne 'HDL32E Software Version 2.0 "
               f"Description' (2012): diffuse 0-100 for 0-100 %, {CALIBRATED}); intensity ~ cos(incidence)^0.22, "
               "measured on the nuScenes sweep (tools/fit_intensity_response.py: 0.220 across surfaces)."),
    "hdl64e": ({"gain": 1.0, "incidence_exponent": 0.23},
               "Response to measured reflectance: gain 1 (the HDL-64E reports uncalibrated intensity and no "
               "reflectivity scale is published: KITTI's 0-1 reflectance is taken at face value); intensity ~ "
               "cos(incidence)^0.23, measured on KITTI raw frames 0 and 2 (tools/fit_intensity_response.py: "
               "0.208 and 0.251 across surfaces); this unit's file has no per-laser intensity correction "
               "(focal_slope 0, limits 0-255)."),
    "vlp32c": ({"gain": round(100 / 255, 6), "incidence_exponent": 0.17},
               "Response to measured reflectance: gain 100/255 (the VLP-16 and HDL-32E manuals' calibrated "
               "reflectivity, diffuse 0-100 for 0-100 %; the VLP-32C manual was not available to confirm); "
               "intensity ~ cos(incidence)^0.17, measured on Argoverse 2 (tools/fit_intensity_response.py: "
               "0.157 and 0.180 across surfaces, up and down sensor)."),
    "vls128": ({"gain": round(110 / 255, 6)},
               "Response to measured reflectance: gain 110/255 (VLS-128 manual, 'Calibrated Reflectivity': "
               f"diffuse 0-110 for 0-100 %; {CALIBRATED}); incidence: Lambertian cosine (not measured here)."),
}
DEFAULT_RESPONSE_NOTE = ("Response to measured reflectance: the defaults (gain 1, Lambertian cosine): no "
                         "published reflectivity scale was at hand and no log here to measure it on.")


def with_response(pid: str, overrides: dict) -> dict:
    """`overrides` with the preset's intensity response and its note appended to `notes`."""
    resp, note = RESPONSES.get(pid, ({}, DEFAULT_RESPONSE_NOTE))
    out = dict(overrides)
    out["intensity"] = {**out.get("intensity", {}), "response": resp}
    out["notes"] = " ".join(x for x in (out.get("notes", ""), note) if x)
    return out


ROOF = {"xyz": [0.0, 0.0, 1.8], "rpy_deg": [0.0, 0.0, 0.0]}
ROOF_NOTE = "Mount: a placeholder roof mount (1.8 m above the ego origin, level, facing forward)."
COMMON_NOTE = ("Intensity from class reflectivity, strongest return, returns beyond 85 degrees "
               "incidence dropped: simulator choices, not sensor data.")


def _us(values) -> list[float]:
    """Round away float noise (2.304 * 3 = 6.912000000000001) at the picosecond level."""
    return [round(float(v), 6) for v in values]


def vlp16_fire_times() -> list[float]:
    # VLP-16 manual (63-9243), "Firing Sequence Timing": one laser every 2.304 us in laser-id
    # order, 16 firings + recharge = 55.296 us. The ROS driver uses the same constants.
    return _us(2.304 * i for i in range(16))


def hdl32e_fire_times() -> list[float]:
    # HDL-32E manual / packet-timing application note (63-9277): 32 single firings of
    # 1.152 us + 9.216 us recharge = 46.08 us, in laser-id order.
    return _us(1.152 * i for i in range(32))


def hdl64e_s2_fire_times() -> list[float]:
    # HDL-64E S2 manual, "Laser firing time table" (as implemented in valgur/velodyne_decoder
    # src/packet_decoder.cpp): the upper (lasers 0-31) and lower (32-63) blocks fire together;
    # within a block, groups of 4 lasers every 6.0 us at offsets 0, 1.26, 2.46, 3.66 us
    # (48 us cycle = 2083 columns per turn at 10 Hz).
    pattern = (0.0, 1.26, 2.46, 3.66)
    return _us(6.0 * ((i % 32) // 4) + pattern[(i % 32) % 4] for i in range(64))


def vlp32c_fire_times() -> list[float]:
    # VLP-32C: lasers fire in pairs, 2.304 us apart within a 55.296 us sequence; the ROS driver's
    # buildTimings() (and velodyne_decoder) put laser i at 2.304 * floor(i / 2).
    return _us(2.304 * (i // 2) for i in range(32))


def vls128_fire_times() -> list[float]:
    # VLS-128: 16 firing groups of 8 lasers (group = laser_id // 8), 2.665 us apart, with one
    # maintenance slot after group 8: ROS driver constants VLS128_CHANNEL_TDURATION = 2.665,
    # VLS128_SEQ_TDURATION = 53.3, azimuth cache (i + i / 8).
    return _us(2.665 * (g + g // 8) for g in (i // 8 for i in range(128)))


def nuscenes_hdl32e_mount(data: Path) -> tuple[dict, str]:
    """nuScenes LIDAR_TOP -> ego from the mmdetection3d demo info pickle, in our sensor frame."""
    pkl = data / "nuscenes-mmdet3d-demo" / "n015-2018-07-24-11-22-45+0800.pkl"
    if not pkl.is_file():
        return ROOF, ROOF_NOTE
    info = load_pickle(pkl)  # restricted: builtins and numpy only
    lidar2ego = np.asarray(info["data_list"][0]["lidar_points"]["lidar2ego"], dtype=np.float64)
    # nuScenes' LIDAR_TOP frame is the Velodyne driver frame (x right, y forward); ours is the ROS
    # frame (x forward, y left): ours -> theirs is a +90 degree yaw.
    rot = lidar2ego[:3, :3] @ euler_to_rotmat(0.0, 0.0, math.pi / 2)
    mount = {"xyz": [round(float(v), 6) for v in lidar2ego[:3, 3]],
             "rpy_deg": [round(math.degrees(a), 6) for a in rotmat_to_euler(rot)]}
    note = ("Mount: nuScenes LIDAR_TOP lidar2ego of log n015-2018-07-24-11-22-45+0800 "
            "(open-mmlab/mmdetection3d @ fe25f7a51d36e3702f961e198894580d83c4387b, "
            "demo/data/nuscenes/n015-2018-07-24-11-22-45+0800.pkl), turned from nuScenes' "
            "x-right/y-forward LiDAR frame to our x-forward frame.")
    return mount, note


def build(data: Path) -> dict[str, object]:
    vel = data / "velodyne-calibration"
    hes = data / "hesai-calibration"
    ous = data / "ouster-sdk-lidar"
    presets = {}

    velodyne_common = ("Per laser from the calibration: elevation (vert_correction), azimuth offset "
                       "(+rot_correction), beam-origin offsets (vert/horiz_offset_correction), and the "
                       "per-laser intensity correction where the file has one (focal_distance/slope, "
                       "min/max_intensity -> intensity.response.velodyne). Not modelled: dist_correction "
                       "and two-point corrections.")

    def velodyne(pid, name, f, columns, hz, fire, fire_note, rng, sigma, quant, quant_note, mount, mount_note):
        cfg = from_velodyne_yaml(
            vel / f, columns=columns, rotation_hz=hz, name=name, fire_time_us=fire, id=pid,
            source=VELODYNE.format(f=f), **with_response(pid, dict(
                notes=" ".join([velodyne_common, fire_note, quant_note, mount_note, COMMON_NOTE]),
                range={"min_m": rng[0], "max_m": rng[1]},
                noise={"range_sigma_m": sigma, "quantization_m": quant},
                mount=mount, **COMMON)))
        presets[pid] = cfg

    res = velodyne_distance_resolution(vel / "VLP16db.yaml")
    velodyne("vlp16", "VLP-16", "VLP16db.yaml", 1800, 10.0, vlp16_fire_times(),
             "1800 columns at 10 Hz (0.2 degrees). Fire times: VLP-16 manual firing sequence, laser i "
             "at 2.304*i us (55.296 us cycle).", (0.5, 100.0), 0.015, res,
             "Range 0.5-100 m, accuracy +/-3 cm typical (datasheet) -> noise sigma 1.5 cm; "
             f"quantization = the file's "
             f"distance_resolution {res} m.", ROOF, ROOF_NOTE)

    res = velodyne_distance_resolution(vel / "32db.yaml")
    mount, mount_note = nuscenes_hdl32e_mount(data)
    velodyne("hdl32e", "HDL-32E", "32db.yaml", 1084, 20.0, hdl32e_fire_times(),
             "1084 columns at 20 Hz: the nuScenes LIDAR_TOP configuration (one column per 46.08 us "
             "firing cycle). Fire times: HDL-32E manual, laser i at 1.152*i us (46.08 us cycle). "
             "Note the ROS driver's buildTimings() uses 1.152*floor(i/2), which does not add up to "
             "the manual's 32 x 1.152 + 9.216 = 46.08 us cycle.", (1.0, 100.0), 0.01, res,
             f"Range 1-100 m, accuracy <2 cm (datasheet) -> noise sigma 1 cm; quantization = the file's "
             f"distance_resolution {res} m.", mount, mount_note)

    res = velodyne_distance_resolution(vel / "64e_utexas.yaml")
    velodyne("hdl64e", "HDL-64E", "64e_utexas.yaml", 2083, 10.0, hdl64e_s2_fire_times(),
             "One real unit (UT Austin; the ROS driver's default calibration). Its origin offsets are "
             "all zero in the file (no horiz_offset_correction key, vert_offset_correction 0), so none "
             "are set. 2083 columns at 10 Hz (0.173 degrees: one column per 48 us cycle). Fire times: "
             "HDL-64E S2 'laser firing time table' (the unit has S2-style two-point calibration fields; "
             "taken from valgur/velodyne_decoder src/packet_decoder.cpp, which cites the S2 manual): upper "
             "and lower blocks fire together, laser j of a block at 6.0*floor(j/4) + "
             "(0, 1.26, 2.46, 3.66)[j%4] us.", (0.9, 120.0), 0.01, res,
             f"Range 0.9-120 m, accuracy <2 cm (datasheet) -> noise sigma 1 cm; quantization = the file's "
             f"distance_resolution {res} m.", ROOF, ROOF_NOTE)

    res = velodyne_distance_resolution(vel / "VeloView-VLP-32C.yaml")
    velodyne("vlp32c", "VLP-32C", "VeloView-VLP-32C.yaml", 1800, 10.0, vlp32c_fire_times(),
             "Nominal angles (VeloView). 1800 columns at 10 Hz (0.2 degrees). Fire times: lasers fire "
             "in pairs, laser i at 2.304*floor(i/2) us (55.296 us cycle), as the ROS driver's "
             "buildTimings() and velodyne_decoder compute them; tier4/nebula instead spreads the 16 "
             "pairs as 2.304*(k + floor(k/2)) - the manual was not available to settle it.",
             (0.5, 200.0), 0.015, res,
             f"Range 0.5-200 m, accuracy +/-3 cm (datasheet) -> noise sigma 1.5 cm; quantization = the file's "
             f"distance_resolution {res} m (the ROS driver and nebula also use 4 mm).", ROOF, ROOF_NOTE)

    velodyne("vls128", "VLS-128", "VLS128.yaml", 1800, 10.0, vls128_fire_times(),
             "Nominal angles. 1800 columns at 10 Hz (0.2 degrees; the 53.3 us firing cycle would give "
             "1876). Fire times: 16 groups of 8 lasers (group = laser_id // 8), group g at "
             "2.665*(g + floor(g/8)) us, from the ROS driver's VLS-128 constants (2.665 us channel, "
             "53.3 us sequence, one maintenance slot after group 8); velodyne_decoder (after VeloView) "
             "uses two slots and 2.89 us for firmware >= 5.2.3.0.", (1.0, 245.0), 0.015, 0.004,
             "Range 1-245 m, accuracy +/-3 cm (datasheet) -> noise sigma 1.5 cm. "
             "Quantization 0.004 m: the ROS driver decodes "
             "VLS-128 ranges with VLS128_DISTANCE_RESOLUTION = 4 mm and ignores the file's "
             "distance_resolution 0.007.", ROOF, ROOF_NOTE)

    ouster_note = ("Per beam from the metadata: elevation (beam_altitude_angles), azimuth offset "
                   "(-beam_azimuth_angles). columns and rate from lidar_mode 1024x10 (the file's mode; "
                   "2048x10 is also common: override pattern.columns). All channels of a column fire at "
                   "once (fire_time 0; Ouster encodes the stagger in the azimuth table). "
                   "start_azimuth_deg 180: measurement id 0 points along the lidar frame's +x, which "
                   "lidar_to_sensor_transform turns to the sensor's -x. Ignored: "
                   "lidar_origin_to_beam_origin_mm ({n} mm radial beam-origin offset; our schema has "
                   "no radial origin offset) and the 36.18 mm z offset from the lidar frame to Ouster's "
                   "sensor frame (our sensor origin is the lidar-frame origin). Range 0.5-120 m; noise "
                   "sigma 1 cm (a typical value, not from the metadata); quantization 1 mm (ranges "
                   "are reported in mm).")
    for pid, name, rel, local in [
        ("os1-64", "OS1-64", "tests/metadata/2_1_2_os1-991913000010-64.json",
         "metadata/2_1_2_os1-991913000010-64.json"),
        ("os1-128", "OS1-128", "tests/pcaps/OS-1-128_v2.3.0_1024x10.json", "OS-1-128_v2.3.0_1024x10.json"),
    ]:
        meta = json.loads((ous / local).read_text())
        n_mm = meta.get("lidar_origin_to_beam_origin_mm",
                        meta.get("beam_intrinsics", {}).get("lidar_origin_to_beam_origin_mm"))
        presets[pid] = from_ouster_json(
            ous / local, name=name, id=pid, source=OUSTER.format(p=rel, local=local), **with_response(pid, dict(
                notes=" ".join([ouster_note.format(n=n_mm), ROOF_NOTE, COMMON_NOTE]),
                range={"min_m": 0.5, "max_m": 120.0},
                noise={"range_sigma_m": 0.01, "quantization_m": 0.001},
                mount=ROOF, **COMMON)))

    hesai_note = ("Per channel from the angle file: elevation, azimuth offset = -Azimuth (Hesai's "
                  "azimuth is clockwise-positive, HesaiLidar_SDK_2.0 x = xy sin(az), y = xy cos(az)). "
                  "1800 columns at 10 Hz (0.2 degrees). Range 0.3-200 m; accuracy +/-2 cm typical "
                  "(datasheet) -> noise sigma 1 cm; quantization 4 mm (the packets' distance unit).")
    presets["pandar64"] = from_hesai_csv(
        hes / "Pandar64_Angle_Correction_File.csv", hes / "Pandar64_Firetime_Correction_File.csv",
        columns=1800, rotation_hz=10.0, name="Pandar64", channels=64, id="pandar64",
        source=HESAI.format(m="Pandar64"), **with_response("pandar64", dict(
            notes=" ".join([hesai_note, "Fire times: the vendor's fire-time file as is (-54.67 .. -3.62 us: "
                            "relative to the block's encoder instant, which the SDK shifts each channel's "
                            "azimuth from by t * rpm * 6e-6 degrees).", ROOF_NOTE, COMMON_NOTE]),
            range={"min_m": 0.3, "max_m": 200.0}, noise={"range_sigma_m": 0.01, "quantization_m": 0.004},
            mount=ROOF, **COMMON)))
    presets["pandar128"] = from_hesai_csv(
        hes / "Pandar128E3X_Angle_Correction_File.csv", hes / "Pandar128E3X_Firetime_Correction_File.csv",
        columns=1800, rotation_hz=10.0, name="Pandar128E3X", channels=128, id="pandar128",
        operation_mode=2, angle_state=0, source=HESAI.format(m="Pandar128E3X"), **with_response("pandar128", dict(
            notes=" ".join([hesai_note, "Fire times: the vendor's mode-dependent table, operation mode 2 "
                            "(standard: every channel fires in every 0.2 degree column; mode 0 is high "
                            "resolution, where channels alternate between angle states), angle state 0, "
                            "distance >= A1 (2.85 m) column; nanoseconds in the file, microseconds here.",
                            ROOF_NOTE, COMMON_NOTE]),
            range={"min_m": 0.3, "max_m": 200.0}, noise={"range_sigma_m": 0.01, "quantization_m": 0.004},
            mount=ROOF, **COMMON)))

    presets["waymo-top"] = from_waymo_frame(
        data / "waymo-open-dataset-frame" / "frame_metadata.json", "TOP", columns=2650, rotation_hz=10.0,
        name="Waymo TOP", id="waymo-top", source=WAYMO, **with_response("waymo-top", dict(
            notes=("64 beam inclinations from the frame's TOP laser calibration, in the file's ascending "
                   "order (channel 0 = bottom beam; Waymo range-image row r = channel 63 - r). 2650 "
                   "columns at 10 Hz, 75 m maximum range (Waymo Open Dataset paper). Not published: per-beam "
                   "azimuth offsets, fire timing (fire_time 0), range noise (1 cm placeholder), minimum "
                   "range (0.5 m placeholder). Mount: the frame's extrinsic_laser_to_vehicle_4x4 (segment "
                   "1024360143612057520_3580_000_3600_000). start_azimuth_deg puts column 0 at vehicle "
                   "azimuth 180 - 180/2650 degrees and the columns clockwise, as in Waymo's range images "
                   "(range_image_utils.compute_range_image_polar). " + COMMON_NOTE),
            range={"min_m": 0.5, "max_m": 75.0}, noise={"range_sigma_m": 0.01}, **COMMON)))
    return presets


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    default_data = Path(os.environ.get("SCUBE_SIM_SHARED_DATA", REPO.parent / "shared" / "data"))
    ap.add_argument("--data", type=Path, default=default_data, help="the shared data folder")
    ap.add_argument("--out", type=Path, default=REPO / "sensors" / "lidar", help="where to write *.yaml")
    args = ap.parse_args(argv)
    for pid, cfg in build(args.data).items():
        path = args.out / f"{pid}.yaml"
        dump_config(cfg, path)
        print(f"{path}: {cfg.name}, {cfg.channels} channels")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
