"""Poses for logs that have none: register consecutive LiDAR sweeps with open3d ICP.

Each sweep is aligned to the previous one (point-to-plane ICP, coarse-to-fine, started from a
constant-velocity guess), and the relative motions are chained, so the first sweep's sensor frame
is the world frame. Drift grows with the sequence; over a few frames it stays at centimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError

# (voxel size m, max correspondence distance m, iterations): coarse to fine.
_SCHEDULE = ((1.0, 3.0, 30), (0.4, 1.0, 30), (0.2, 0.4, 50), (0.1, 0.2, 50))


@dataclass
class IcpResult:
    """pose (4, 4) T_target_source; fitness: inlier fraction; rmse metres, of the finest stage."""

    pose: np.ndarray
    fitness: float
    rmse: float


def _o3d():
    """open3d, imported on first use (slow to import): `kitti` imports this module, but only logs
    without poses run ICP."""
    import open3d

    return open3d


def _cloud(points: np.ndarray, voxel: float):
    o3d = _o3d()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    pc = pc.voxel_down_sample(voxel)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel, max_nn=30))
    return pc


def icp(source: np.ndarray, target: np.ndarray, init: np.ndarray | None = None, *,
        min_range: float = 2.5, max_range: float = 60.0) -> IcpResult:
    """Align `source` (N, 3) to `target` (M, 3), both metres in their own sensor frames.
    Points nearer than `min_range` (the ego vehicle) or beyond `max_range` are left out."""
    o3d = _o3d()

    def keep(p):
        r = np.linalg.norm(p, axis=1)
        return p[(r > min_range) & (r < max_range)]

    src, tgt = keep(np.asarray(source, np.float64)), keep(np.asarray(target, np.float64))
    if src.shape[0] < 100 or tgt.shape[0] < 100:
        raise InputError(f"icp: too few points to register ({src.shape[0]} and {tgt.shape[0]} within "
                         f"{min_range}-{max_range} m)")
    pose = np.eye(4) if init is None else np.asarray(init, np.float64).copy()
    reg = o3d.pipelines.registration
    result = None
    for voxel, dist, iters in _SCHEDULE:
        s, t = _cloud(src, voxel), _cloud(tgt, voxel)
        result = reg.registration_icp(s, t, dist, pose, reg.TransformationEstimationPointToPlane(),
                                      reg.ICPConvergenceCriteria(max_iteration=iters))
        pose = np.asarray(result.transformation, np.float64)
    # open3d sums in parallel, so the last bits differ from run to run; rounding far below ICP's
    # own accuracy makes the same sweeps give the same poses (and scenes), bit for bit.
    return IcpResult(np.round(pose, 10), round(float(result.fitness), 10), round(float(result.inlier_rmse), 10))


def register_sequence(sweeps: list[np.ndarray], *, refine_to_first: int = 10) -> tuple[np.ndarray, list[IcpResult]]:
    """Sensor-to-world poses (K, 4, 4) for K consecutive sweeps ((N_k, 3) each, sensor frame),
    world = the first sweep's frame, and the K - 1 ICP results.

    Each sweep is first aligned to the previous one; the first `refine_to_first` sweeps are then
    aligned directly to the first sweep, started from the chained pose: short sequences get no
    chaining drift (frame-to-frame steps of a few decimetres came out ~2 cm short each on KITTI)."""
    poses = [np.eye(4)]
    results: list[IcpResult] = []
    step = np.eye(4)
    for k in range(1, len(sweeps)):
        res = icp(sweeps[k], sweeps[k - 1], init=step)  # T_{k-1, k}
        results.append(res)
        step = res.pose  # constant velocity: the next step starts from this one
        poses.append(poses[-1] @ res.pose)
    for k in range(1, min(len(sweeps), refine_to_first)):
        res = icp(sweeps[k], sweeps[0], init=poses[k])
        results[k - 1] = res
        poses[k] = res.pose
    return np.stack(poses), results


def step_quality(sweeps: list[np.ndarray], poses: np.ndarray, voxel: float = 0.2, max_dist: float = 0.4,
                  min_range: float = 2.5, max_range: float = 60.0) -> list[IcpResult]:
    """The K - 1 steps of `poses` (K, 4, 4) as `IcpResult`s: each relative pose with the inlier
    share and point-to-plane residual (metres) of sweep k moved onto sweep k - 1 by it (open3d's
    evaluation, the yardstick `icp` reports), for poses another estimator made."""
    def keep(p):
        r = np.linalg.norm(p, axis=1)
        return p[(r > min_range) & (r < max_range)]

    reg = _o3d().pipelines.registration
    out = []
    clouds = [_cloud(keep(np.asarray(s, np.float64)), voxel) for s in sweeps]
    for k in range(1, len(sweeps)):
        rel = np.linalg.inv(poses[k - 1]) @ poses[k]
        ev = reg.evaluate_registration(clouds[k], clouds[k - 1], max_dist, rel)
        out.append(IcpResult(np.round(rel, 10), round(float(ev.fitness), 6), round(float(ev.inlier_rmse), 6)))
    return out
