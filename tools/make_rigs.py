"""(Re)write the shipped camera rigs in `sensors/rigs/` from real calibrations in ../shared/data.

    .venv/bin/python tools/make_rigs.py [--data ../shared/data] [--out sensors/rigs]

waymo-5: the five cameras of a Waymo Open Dataset frame (intrinsics with OpenCV distortion,
camera-to-vehicle extrinsics, each camera's pose time relative to the frame). nuscenes-6: the six
cameras of a nuScenes keyframe (K, cam2ego, image time relative to the LiDAR keyframe). Only the
numbers go into our YAML, with their source.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from scube_sim.atomic import atomic_path  # noqa: E402
from scube_sim.camera.model import Intrinsics  # noqa: E402
from scube_sim.camera.rig import BODY_FROM_OPTICAL, RigConfig  # noqa: E402
from scube_sim.io.safe_pickle import load_pickle  # noqa: E402
from scube_sim.transforms import invert_pose, rotmat_to_euler  # noqa: E402


def _mount(body_to_ego: np.ndarray) -> dict:
    return {"xyz": [round(float(v), 6) for v in body_to_ego[:3, 3]],
            "rpy_deg": [round(float(np.degrees(a)), 6) for a in rotmat_to_euler(body_to_ego[:3, :3])]}


def waymo(data: Path) -> dict:
    meta = json.loads((data / "waymo-open-dataset-frame" / "frame_metadata.json").read_text())
    t0 = meta["timestamp_micros"] * 1e-6
    times = {im["name"]: im["pose_timestamp_s"] - t0 for im in meta["images"]}
    cams = []
    for c in meta["camera_calibrations"]:
        fu, fv, cu, cv, k1, k2, p1, p2, k3 = c["intrinsic_fu_fv_cu_cv_k1_k2_p1_p2_k3"]
        # Waymo's camera frame is already x forward, y left, z up: our camera body frame.
        ext = np.asarray(c["extrinsic_camera_to_vehicle_4x4"], np.float64)
        cams.append({"name": c["name"], "width": c["width"], "height": c["height"], "fx": fu, "fy": fv, "cx": cu, "cy": cv,
                     "distortion": {"model": "opencv", "coeffs": [k1, k2, p1, p2, k3]}, "mount": _mount(ext),
                     "time_offset_s": round(times.get(c["name"], 0.0), 6)})
    order = ["FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT"]
    cams.sort(key=lambda c: order.index(c["name"]))
    return {"name": "waymo-5",
            "source": ("waymo-research/waymo-open-dataset @ 99a4cb3ff07e2fe06c2ce73da001f850f628e45a, "
                       "src/waymo_open_dataset/utils/testdata/pvps_data_one_frame.tfrecord, camera_calibrations "
                       "and images[].pose_timestamp_s (extracted to ../shared/data/waymo-open-dataset-frame/"
                       "frame_metadata.json), segment 1024360143612057520_3580_000_3600_000"),
            "notes": ("Intrinsics (f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3) and camera-to-vehicle extrinsics of one "
                      "real vehicle; time_offset_s is each image's pose time minus the frame time. Rolling "
                      "shutter (left to right, ~2.5 ms exposure, ~47 ms readout) is not modelled."),
            "cameras": cams}


def nuscenes(data: Path) -> dict:
    info = load_pickle(data / "nuscenes-mmdet3d-demo" / "n015-2018-07-24-11-22-45+0800.pkl")
    d = info["data_list"][0]
    t0 = d["timestamp"]
    cams = []
    for name in ["CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK_RIGHT", "CAM_BACK"]:
        c = d["images"][name]
        intr = Intrinsics.from_k(c["cam2img"], 1600, 900)  # the half-pixel convention: see from_k
        cam2ego = np.asarray(c["cam2ego"], np.float64)
        body = cam2ego @ invert_pose(BODY_FROM_OPTICAL)
        cams.append({"name": name, "width": 1600, "height": 900, "fx": intr.fx, "fy": intr.fy,
                     "cx": intr.cx, "cy": intr.cy, "distortion": {"model": "pinhole"},
                     "mount": _mount(body), "time_offset_s": round(float(c["timestamp"] - t0), 6)})
    return {"name": "nuscenes-6",
            "source": ("open-mmlab/mmdetection3d @ fe25f7a51d36e3702f961e198894580d83c4387b, "
                       "demo/data/nuscenes/n015-2018-07-24-11-22-45+0800.pkl (../shared/data/nuscenes-mmdet3d-demo/), "
                       "nuScenes v1.0-mini log n015-2018-07-24-11-22-45+0800"),
            "notes": ("K (cam2img, principal point moved by the half pixel between OpenCV's and our pixel-centre convention) and cam2ego of the six cameras of one real keyframe; nuScenes images are "
                      "undistorted, so no distortion. time_offset_s is each image's timestamp minus the LiDAR keyframe's."),
            "cameras": cams}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=REPO / "sensors" / "rigs")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for rig in (waymo(args.data), nuscenes(args.data)):
        RigConfig.model_validate(rig)
        with atomic_path(args.out / f"{rig['name']}.yaml") as tmp:
            Path(tmp).write_text(yaml.safe_dump(rig, sort_keys=False, width=110))
        print(f"wrote {args.out / (rig['name'] + '.yaml')}")


if __name__ == "__main__":
    main()
