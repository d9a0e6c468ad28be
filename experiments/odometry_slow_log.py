"""LiDAR odometry on a short, slow log: the 3-sweep KITTI raw excerpt (about 0.23 m per frame),
our open3d ICP (`datasets.odometry.Icp`, the adapters' default) against kiss-icp
(`datasets.odometry.KissIcp`) at its voxel sizes. There is no ground truth: the step lengths are
compared with each other and with the forward motion the images show (see
tests/datasets/test_kitti.py); each step's inlier share and residual come from the same yardstick
(`datasets.icp.step_quality`).

Run: `python -m experiments.odometry_slow_log [--data ../shared/data/kitti-raw-2011_09_26-udacity]`
(under a minute on 2 cores). Results: experiments/results/odometry_slow_log.{json,md}.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from scube_sim.datasets.icp import step_quality
from scube_sim.datasets.kitti import read_velodyne
from scube_sim.datasets.odometry import Icp, KissIcp

from .common import write_results

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti-raw-2011_09_26-udacity"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = ap.parse_args(argv)
    files = sorted((args.data / "velodyne_points" / "data").glob("*.bin"))
    sweeps = [read_velodyne(f)[:, :3].astype(np.float64) for f in files]
    rows = []
    for name, est in (("ours (open3d ICP)", Icp()), ("kiss-icp, voxel 1 m (its default)", KissIcp()),
                      ("kiss-icp, voxel 0.5 m", KissIcp(max_range_m=50.0))):
        t0 = time.perf_counter()
        res = est.estimate(sweeps)
        seconds = time.perf_counter() - t0
        q = step_quality(sweeps, res.poses)
        rows.append({"method": name, "sweeps": len(sweeps), "seconds": seconds,
                     **{f"step{k}_m": float(np.linalg.norm(s.pose[:3, 3])) for k, s in enumerate(q, 1)},
                     **{f"step{k}_fitness": s.fitness for k, s in enumerate(q, 1)},
                     **{f"step{k}_rmse_m": s.rmse for k, s in enumerate(q, 1)}})
        print(rows[-1], flush=True)
    write_results("odometry_slow_log", rows, list(rows[0]),
                  notes=f"{args.data.name}: {len(sweeps)} sweeps; step k: the motion from sweep k - 1 to k; "
                        f"fitness / rmse: sweep k moved onto k - 1 by it (0.2 m voxels, 0.4 m max distance)")


if __name__ == "__main__":
    main()
