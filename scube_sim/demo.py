"""The `make demo` job: scene -> VoxSplat -> LiDAR sweep -> files in out/, with timings."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np

from .fit import fit_voxsplat
from .io.ply3dgs import write_3dgs_ply
from .io.pointcloud import write_pcd
from .io.usd import export_usd
from .lidar.config import load_lidar_config
from .lidar.model import Lidar
from .raytrace.tracer import Tracer
from .viz import bev_png
from .worlds.street import street_scene


def run_demo(out: str | Path, *, sensor: str = "hdl64e", voxel_size: float = 0.2, seed: int = 0,
             echo: Callable[[str], None] = print) -> dict:
    """Write scene.npz, scene_3dgs.ply, sweep.pcd, scene.usdc, sweep.usda and bev.png into `out`; returns the
    timings and counts it printed."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    times = {}
    t = time.perf_counter()
    mesh = street_scene()
    samples = mesh.sample_surface_grid(voxel_size / 2)
    vs = fit_voxsplat(samples["points"], voxel_size, colors=samples["colors"], labels=samples["labels"],
                      weights=samples["weights"], origin=mesh.origin)
    vs.metadata.update({"scene": "street_scene", "voxel_size": voxel_size})
    times["fit VoxSplat"] = time.perf_counter() - t

    t = time.perf_counter()
    tracer = Tracer(vs, mode="entry")
    times["build tracer"] = time.perf_counter() - t
    lidar = Lidar(load_lidar_config(sensor))
    ego = np.eye(4)
    ego[:3, 3] = [0.0, -2.0, 0.0]  # on the road, right lane
    pose = lidar.sensor_pose(ego)
    t = time.perf_counter()
    sweep = lidar.scan(tracer, pose, seed=seed)
    times["LiDAR sweep"] = time.perf_counter() - t
    t = time.perf_counter()
    mesh_sweep = lidar.scan(Tracer(mesh), pose, seed=seed)
    times["reference sweep on the mesh"] = time.perf_counter() - t

    t = time.perf_counter()
    vs.save(out / "scene.npz")
    write_3dgs_ply(out / "scene_3dgs.ply", vs.gaussians())
    write_pcd(out / "sweep.pcd", sweep.points, viewpoint=pose)
    # The million Gaussians go into a binary crate (.usda text would be ~200 MB); the sweep alone
    # is also written as readable .usda.
    export_usd(out / "scene.usdc", voxsplat=vs, points={"lidar": sweep.points}, points_poses={"lidar": pose})
    export_usd(out / "sweep.usda", points={"lidar": sweep.points}, points_poses={"lidar": pose})
    bev_png(out / "bev.png", sweep.xyz(), labels=sweep.points["label"], extent=45.0,
            title=f"{lidar.config.name} sweep on a {voxel_size:g} m VoxSplat ({len(sweep)} points), sensor frame")
    times["write outputs"] = time.perf_counter() - t

    a, b = mesh_sweep.range_image(), sweep.range_image()
    both = np.isfinite(a) & np.isfinite(b)
    err = np.abs(a - b)[both]
    echo(f"scene: street mesh, {mesh.num_faces} triangles -> {vs}")
    echo(f"sensor: {lidar.config.name}, {sweep.num_rays} rays -> {len(sweep)} returns")
    if err.size:
        echo(f"VoxSplat vs mesh sweep (same rays, both noisy): |range error| median {np.median(err) * 100:.1f} cm, "
             f"p90 {np.percentile(err, 90) * 100:.1f} cm; return agreement {(np.isfinite(a) == np.isfinite(b)).mean():.3f}")
    for name, sec in times.items():
        echo(f"  {name:<28s} {sec:7.3f} s")
    echo(f"outputs in {out}/: scene.npz scene_3dgs.ply sweep.pcd scene.usdc sweep.usda bev.png")
    return {"times": times, "points": len(sweep), "gaussians": vs.num_gaussians}
