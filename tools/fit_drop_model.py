"""Fit the HDL-32E ray-drop model on nuScenes' full firing grid and score it on held-out sectors.

    .venv/bin/python tools/fit_drop_model.py [--data ../shared/data] [--scene out/nus.npz]
        [--out sensors/lidar/hdl32e.drop.yaml]

Builds the VoxSplat of the nuScenes keyframe (`scube-sim build` defaults) unless --scene gives
one, fits the logistic drop model of `lidar.drop` on the even 30-degree azimuth sectors
(`raydrop.drop_study`), writes it beside the preset, and prints the held-out scores of the
preset's hand-set rules and of the fitted model. A sensor YAML selects the file with
``drop: {model: hdl32e.drop.yaml}``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from scube_sim.datasets import open_dataset  # noqa: E402
from scube_sim.raydrop import drop_study  # noqa: E402
from scube_sim.reconstruct import BuildOptions, build_from_dataset  # noqa: E402
from scube_sim.voxsplat import VoxSplat  # noqa: E402

FOLDER = "nuscenes-mmdet3d-demo"
SOURCE = ("nuScenes v1.0-mini keyframe of log n015-2018-07-24-11-22-45+0800 (open-mmlab/mmdetection3d @ "
          "fe25f7a51d36e3702f961e198894580d83c4387b, demo/data/nuscenes), LIDAR_TOP full 32 x 1084 grid, "
          "even 30-degree azimuth sectors, against the VoxSplat `scube-sim build` makes of it "
          "(tools/fit_drop_model.py)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("SCUBE_SIM_SHARED_DATA",
                                                                     REPO.parent / "shared" / "data")))
    ap.add_argument("--scene", type=Path, help="the VoxSplat of the keyframe (default: build it)")
    ap.add_argument("--out", type=Path, default=REPO / "sensors" / "lidar" / "hdl32e.drop.yaml")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
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
