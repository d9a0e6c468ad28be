"""Fit a ray-drop model on a real sweep's full firing grid and score it.

    .venv/bin/python tools/fit_drop_model.py [--data ../shared/data] [--scene out/nus.npz]
        [--out sensors/lidar/hdl32e.drop.yaml]
    .venv/bin/python tools/fit_drop_model.py --dataset argoverse2 [--fit-sensor up_lidar]
        [--apply-sensor down_lidar] [--scene-fit out/av0-up.npz] [--scene-apply out/av0-down.npz]
        [--out sensors/lidar/vlp32c.drop.yaml]

nuScenes (default): builds the VoxSplat of the keyframe (`scube-sim build` defaults) unless
--scene gives one, fits the logistic drop model of `lidar.drop` on the even 30-degree azimuth
sectors (`raydrop.drop_study`), writes it beside the preset, and prints the held-out scores of
the preset's hand-set rules and of the fitted model.

Argoverse 2 (returns only): the firing grid of each VLP-32C is rebuilt from the returns' times
(`raydrop.rebuild_firing_grid`); the model is fitted on every ray of one unit (sweep 0, against
the VoxSplat built from that unit's sweep alone) and scored on every ray of the other unit
(against the VoxSplat built from its own sweep), with the rays into the vehicle and its sensor
rig left out (`AV2_BLIND`, measured below). A sensor YAML selects a file with
``drop: {model: <file>}``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from scube_sim.datasets import open_dataset  # noqa: E402
from scube_sim.realdata.build import BuildOptions, build_from_dataset  # noqa: E402
from scube_sim.realdata.raydrop import blind_sector, drop_study, rebuild_firing_grid, transfer_study  # noqa: E402
from scube_sim.voxsplat import VoxSplat  # noqa: E402

FOLDER = "nuscenes-mmdet3d-demo"
SOURCE = ("nuScenes v1.0-mini keyframe of log n015-2018-07-24-11-22-45+0800 (open-mmlab/mmdetection3d @ "
          "fe25f7a51d36e3702f961e198894580d83c4387b, demo/data/nuscenes), LIDAR_TOP full 32 x 1084 grid, "
          "even 30-degree azimuth sectors, against the VoxSplat `scube-sim build` makes of it "
          "(tools/fit_drop_model.py)")
AV2_FOLDER = "argoverse2-sensor-log-7fab2350"
AV2_SOURCE = ("Argoverse 2 sensor log 7fab2350-7eaf-3b7e-a39d-6937a4c1bede (argoverse/av2-api @ "
              "b7321d1f71f6ce0ecdd151f4f2b648338c191edd, tests/unit/test_data), sweep 0, {sensor}: firing grid "
              "rebuilt from the returns' times (raydrop.rebuild_firing_grid), all rays but the vehicle's blind "
              "sector, against the VoxSplat `scube-sim build --sensors {sensor}` makes of it "
              "(tools/fit_drop_model.py --dataset argoverse2)")
# Where each unit sees its own vehicle or rig (vehicle-frame azimuth from, to (counter-clockwise,
# degrees); highest elevation), read off sweep 0: the 2-degree azimuth bins around the rear in
# which the channels returned nothing in most of their cycles.
# up_lidar: only its lowest laser (-25 degrees) sees the car's roof and trunk, 152 to -154.
# down_lidar (mounted upside down under up_lidar): every laser, even at -15 degrees where the
# ground is 7 m away, is blind from about 168 to -156 (the rig behind it).
AV2_BLIND = {"up_lidar": ((151.0, -153.0), -20.0), "down_lidar": ((166.0, -155.0), 90.0)}


def av2_grid(ds, sample, name):
    sweep = sample.sweep(name)
    sector, max_el = AV2_BLIND[name]
    return rebuild_firing_grid(sweep, sample.lidars[name].config,
                               ego_body=blind_sector(ds.sensor_to_ego[name], sector, max_el))


def argoverse2(args) -> int:
    ds = open_dataset("argoverse2", args.data / AV2_FOLDER)
    sample = ds[0]
    parts = []
    for name, scene_path in ((args.fit_sensor, args.scene_fit), (args.apply_sensor, args.scene_apply)):
        grid = av2_grid(ds, sample, name)
        print(f"{name}: {grid.notes[0]}")
        scene = (VoxSplat.load(scene_path) if scene_path else
                 build_from_dataset(ds, BuildOptions(samples=[0], sensors=[name]))[0])
        parts.append((scene, sample.lidars[name].config, grid.rays, grid.sweep))
    study = transfer_study(parts[0], parts[1], args.out, source=AV2_SOURCE.format(sensor=args.fit_sensor),
                           seed=args.seed)
    print(study.markdown().replace("held-out sectors", f"fitted on {args.fit_sensor}, applied to {args.apply_sensor}"))
    coef = study.model.coefficients
    print("coefficients:", ", ".join(f"{k} {v:+.3f}" for k, v in coef.items() if not k.startswith("ring.")))
    print(f"-> {args.out}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("SCUBE_SIM_SHARED_DATA",
                                                                     REPO.parent / "shared" / "data")))
    ap.add_argument("--dataset", choices=("nuscenes", "argoverse2"), default="nuscenes")
    ap.add_argument("--scene", type=Path, help="nuscenes: the VoxSplat of the keyframe (default: build it)")
    ap.add_argument("--fit-sensor", default="up_lidar", help="argoverse2: the unit the model is fitted on")
    ap.add_argument("--apply-sensor", default="down_lidar", help="argoverse2: the unit it is scored on")
    ap.add_argument("--scene-fit", type=Path, help="argoverse2: VoxSplat of sweep 0 from the fitting unit alone")
    ap.add_argument("--scene-apply", type=Path, help="argoverse2: VoxSplat of sweep 0 from the scored unit alone")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.dataset == "argoverse2":
        args.out = args.out or REPO / "sensors" / "lidar" / "vlp32c.drop.yaml"
        return argoverse2(args)
    args.out = args.out or REPO / "sensors" / "lidar" / "hdl32e.drop.yaml"
    ds = open_dataset("nuscenes", args.data / FOLDER)
    scene = VoxSplat.load(args.scene) if args.scene else build_from_dataset(ds, BuildOptions(samples=[0]))[0]
    sample = ds[0]
    sweep = sample.sweep()
    study = drop_study(scene, sample.lidars[sweep.sensor].config, sweep, args.out, source=SOURCE, seed=args.seed)
    print(study.markdown())
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
