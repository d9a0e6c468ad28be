"""LiDAR odometry on the 20-frame KITTI-360 excerpt: our open3d ICP (`scube_sim.datasets.icp`,
what the `kitti360` adapter uses where a drive has no poses) against kiss-icp (PyPI, MIT).

There is no ground-truth pose in the excerpt, so this measures what can be measured:

- **seconds** for the 20 sweeps (wall clock, this machine);
- **per-step motion**: the translation between consecutive poses (the car drives ~10 m/s at
  10 Hz, so ~1 m, steady) and the rotation (degrees);
- **end-point disagreement** with our default: frame 19's pose of each method against ours
  (metres, degrees; world = frame 0's Velodyne frame for all);
- **loop-free consistency**: every sweep moved by the method's relative pose onto an earlier
  sweep, 1 and 5 frames back; point-to-plane residual of the points whose nearest neighbour is
  within 0.5 m (0.1 m voxels, normals from 30 neighbours), median |residual| and the inlier
  fraction. The same yardstick for all methods, on the raw (not deskewed) sweeps.

Methods: ours (`register_sequence`: frame to frame, the first 10 then refined onto frame 0);
ours chained only (`refine_to_first=0`); kiss-icp 1.x with its KITTI defaults (max range 100 m,
voxel 1 m, adaptive threshold) with deskew (per-point times from the azimuth, as its kitti_raw
loader makes them) and without.

Run: `python -m experiments.kitti360_odometry [--data ../shared/data/kitti360-2013_05_28-seq]`
(~1 minute on 2 cores; needs `pip install kiss-icp`, which is not a dependency of the package).
Results: experiments/results/kitti360_odometry.{json,md}.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from scube_sim.datasets import open_dataset
from scube_sim.datasets.icp import register_sequence
from scube_sim.datasets.kitti import read_velodyne

from .common import write_results

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti360-2013_05_28-seq"
RANGE_M = (2.5, 60.0)
VOXEL_M, NN_MAX_M = 0.1, 0.5


def _rot_deg(r: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r[:3, :3]) - 1) / 2, -1, 1))))


def kiss_icp_poses(clouds: list[np.ndarray], deskew: bool) -> np.ndarray:
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    cfg = KISSConfig()
    cfg.data.deskew = deskew
    cfg.mapping.voxel_size = cfg.data.max_range / 100.0  # what kiss-icp's config loader sets
    odo = KissICP(cfg)
    poses = []
    for pts in clouds:
        # kiss-icp's kitti_raw loader: scan time in [0, 1] from the azimuth, 0.5 straight ahead
        ts = 0.5 * (-np.arctan2(pts[:, 1], pts[:, 0]) / np.pi + 1.0) if deskew else np.array([])
        odo.register_frame(pts, ts)
        poses.append(odo.last_pose.copy())
    return np.stack(poses)


class Yardstick:
    """Point-to-plane residuals of one sweep moved onto another (the same for every method)."""

    def __init__(self, clouds: list[np.ndarray]):
        import open3d as o3d
        from scipy.spatial import cKDTree

        self.src, self.tgt = [], []
        for pts in clouds:
            r = np.linalg.norm(pts, axis=1)
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[(r > RANGE_M[0]) & (r < RANGE_M[1])]))
            pc = pc.voxel_down_sample(VOXEL_M)
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30))
            p, n = np.asarray(pc.points), np.asarray(pc.normals)
            self.src.append(p)
            self.tgt.append((cKDTree(p), p, n))

    def residual(self, t_target_source: np.ndarray, target: int, source: int) -> tuple[float, float]:
        """(median |point-to-plane| m, inlier fraction) of sweep `source` moved into `target`."""
        tree, p, n = self.tgt[target]
        s = self.src[source] @ t_target_source[:3, :3].T + t_target_source[:3, 3]
        d, idx = tree.query(s, distance_upper_bound=NN_MAX_M)
        ok = np.isfinite(d)
        res = np.abs(np.einsum("ij,ij->i", s[ok] - p[idx[ok]], n[idx[ok]]))
        return float(np.median(res)), float(ok.mean())


def measure(data: Path) -> list[dict]:
    ds = open_dataset("kitti360", data, poses="identity")  # the files, in order (poses estimated below)
    clouds = [read_velodyne(Path(ds[i].sweep().source))[:, :3].astype(np.float64) for i in range(len(ds))]
    methods = {
        "ours (open3d ICP, refine to frame 0)": lambda: register_sequence(clouds)[0],
        "ours, chained only": lambda: register_sequence(clouds, refine_to_first=0)[0],
        "kiss-icp, deskew": lambda: kiss_icp_poses(clouds, True),
        "kiss-icp, no deskew": lambda: kiss_icp_poses(clouds, False),
    }
    ruler = Yardstick(clouds)
    rows, ref = [], None
    for name, run in methods.items():
        t0 = time.perf_counter()
        poses = run()
        seconds = time.perf_counter() - t0
        poses = np.linalg.inv(poses[0]) @ poses  # world = frame 0's Velodyne frame
        if ref is None:
            ref = poses
        steps = [np.linalg.inv(poses[k - 1]) @ poses[k] for k in range(1, len(poses))]
        step_m = np.array([np.linalg.norm(s[:3, 3]) for s in steps])
        step_deg = np.array([_rot_deg(s) for s in steps])
        end = np.linalg.inv(ref[-1]) @ poses[-1]
        r1 = [ruler.residual(steps[k - 1], k - 1, k) for k in range(1, len(poses))]
        r5 = [ruler.residual(np.linalg.inv(poses[k - 5]) @ poses[k], k - 5, k) for k in range(5, len(poses))]
        rows.append({
            "method": name, "frames": len(poses), "seconds": seconds, "s_per_frame": seconds / len(poses),
            "step_m_mean": float(step_m.mean()), "step_m_std": float(step_m.std()),
            "step_m_min": float(step_m.min()), "step_m_max": float(step_m.max()),
            "step_deg_mean": float(step_deg.mean()), "path_m": float(step_m.sum()),
            "end_vs_ours_m": float(np.linalg.norm(end[:3, 3])), "end_vs_ours_deg": _rot_deg(end),
            "res1_median_cm": 100 * float(np.median([r[0] for r in r1])),
            "res1_inliers": float(np.mean([r[1] for r in r1])),
            "res5_median_cm": 100 * float(np.median([r[0] for r in r5])),
            "res5_inliers": float(np.mean([r[1] for r in r5])),
            "end_position_m": poses[-1][:3, 3].round(4).tolist(),
            "steps_m": step_m.round(4).tolist(),
        })
        print(f"{name}: {seconds:.1f} s, steps {step_m.mean():.3f} +- {step_m.std():.3f} m, "
              f"end vs ours {rows[-1]['end_vs_ours_m']:.3f} m / {rows[-1]['end_vs_ours_deg']:.3f} deg, "
              f"residual 1 back {rows[-1]['res1_median_cm']:.2f} cm, 5 back {rows[-1]['res5_median_cm']:.2f} cm",
              flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the KITTI-360 excerpt (or a drive)")
    args = ap.parse_args(argv)
    rows = measure(args.data)
    header = ["method", "seconds", "step_m_mean", "step_m_std", "step_m_min", "step_m_max", "step_deg_mean",
              "end_vs_ours_m", "end_vs_ours_deg", "res1_median_cm", "res1_inliers", "res5_median_cm", "res5_inliers"]
    notes = (f"{args.data.name}: {rows[0]['frames']} sweeps, no ground truth. step: consecutive-pose motion "
             f"(~1 m expected at ~10 m/s, 10 Hz); end_vs_ours: frame {rows[0]['frames'] - 1}'s pose against our "
             f"default's; res1/res5: median point-to-plane residual (cm) of each sweep moved onto the sweep 1 / 5 "
             f"frames back, points with a neighbour within {NN_MAX_M} m ({VOXEL_M} m voxels, {RANGE_M[0]}-"
             f"{RANGE_M[1]} m), and that inlier fraction. Sweeps are not deskewed for the residuals.")
    print(write_results("kitti360_odometry", rows, header, notes))


if __name__ == "__main__":
    main()
