"""The `make demo` job on the embedded default scenario: a procedural urban block ->
ground-truth VoxSplat -> HDL-64E sweep -> files in out/, with timings and the VoxSplat's range
error against the same sweep on the exact mesh."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np

from .camera.render import render_camera
from .camera.rig import load_rig
from .io.ply3dgs import write_3dgs_ply
from .io.pointcloud import write_pcd
from .io.usd import export_usd
from .lidar.config import load_lidar_config
from .lidar.model import Lidar
from .mesh import TriangleMesh
from .raytrace.tracer import Tracer
from .transforms import invert_pose, transform_points
from .viz import bev_png, mosaic_png
from .worlds.generator import WorldConfig, generate_world
from .worlds.groundtruth import gt_voxsplat
from .worlds.textures import albedo

# The embedded default scenario (the same as scenarios/urban-block.yaml).
DEFAULT_WORLD = WorldConfig(style="urban", seed=7, layout="x_junction")
# The demo fits the 51.2 m x 51.2 m around the ego (the whole chunk at 0.2 m holds ~3 M Gaussians).
REGION = (np.array([-10.24, -25.6, -3.23]), np.array([40.96, 25.6, 40.0]))


def run_demo(out: str | Path, *, sensor: str = "hdl64e", voxel_size: float = 0.2, seed: int = 0,
             world: WorldConfig | None = None, echo: Callable[[str], None] = print) -> dict:
    """Write views.png, scene.npz, scene_3dgs.ply, sweep.pcd, scene.usdc, sweep.usda and bev.png
    into `out`; returns the timings and counts it printed."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    times = {}
    t = time.perf_counter()
    wcfg = world or DEFAULT_WORLD
    w = generate_world(wcfg)
    mesh = w.mesh_at(0.0)
    chunk_to_world = w.ego_pose_at(0.0)
    times["generate world"] = time.perf_counter() - t

    t = time.perf_counter()
    rig = load_rig("waymo-5")
    tracers = [Tracer(w.static)] + ([Tracer(TriangleMesh.concatenate(w.actor_meshes_at(0.0)))] if w.actors else [])
    views = {c.name: render_camera(tracers, c.intrinsics().scaled(0.3), chunk_to_world @ c.cam_to_ego(),
                                   sun_dir=w.sun_dir, albedo_fn=albedo)["rgb"] for c in rig.cameras}
    mosaic_png(out / "views.png", views, title=f"{wcfg.style} world, seed {wcfg.seed}: the Waymo-like rig at T")
    times["render 5 cameras"] = time.perf_counter() - t

    t = time.perf_counter()
    vs = gt_voxsplat(mesh, chunk_to_world, voxel_size, region=REGION)
    vs.metadata.update({"scene": "demo", "world": wcfg.model_dump()})
    times["fit VoxSplat"] = time.perf_counter() - t

    t = time.perf_counter()
    tracer = Tracer(vs, mode="entry")
    times["build tracer"] = time.perf_counter() - t
    lidar = Lidar(load_lidar_config(sensor))
    pose_world = lidar.sensor_pose(chunk_to_world)
    pose = invert_pose(chunk_to_world) @ pose_world  # the VoxSplat lives in the chunk frame
    t = time.perf_counter()
    sweep = lidar.scan(tracer, pose, seed=seed)
    times["LiDAR sweep"] = time.perf_counter() - t
    t = time.perf_counter()
    mesh_sweep = lidar.scan(Tracer(mesh), pose_world, seed=seed)
    times["reference sweep on the mesh"] = time.perf_counter() - t

    t = time.perf_counter()
    vs.save(out / "scene.npz")
    write_3dgs_ply(out / "scene_3dgs.ply", vs.gaussians())
    write_pcd(out / "sweep.pcd", sweep.points, viewpoint=pose)
    # A million Gaussians as .usda text would be ~200 MB: the scene goes into a binary crate,
    # the sweep alone into readable .usda.
    export_usd(out / "scene.usdc", voxsplat=vs, points={"lidar": sweep.points}, points_poses={"lidar": pose})
    export_usd(out / "sweep.usda", points={"lidar": sweep.points}, points_poses={"lidar": pose})
    bev_png(out / "bev.png", sweep.xyz(), labels=sweep.points["label"], extent=45.0,
            title=f"{lidar.config.name} on a {voxel_size:g} m VoxSplat ({len(sweep)} points), sensor frame")
    times["write outputs"] = time.perf_counter() - t

    # Compare rays whose mesh return lies inside the fitted region.
    a, b = mesh_sweep.range_image(), sweep.range_image()
    pts_c = transform_points(pose, mesh_sweep.xyz().astype(np.float64))
    inside = np.all((pts_c >= REGION[0] + 0.5) & (pts_c < REGION[1] - 0.5), axis=1)
    row = np.empty(mesh_sweep.channels, np.int64)
    row[np.argsort(-mesh_sweep.ring_elevation_deg, kind="stable")] = np.arange(mesh_sweep.channels)
    mask = np.zeros(a.shape, bool)
    mask[row[mesh_sweep.points["ring"][inside]], mesh_sweep.points["column"][inside]] = True
    both = mask & np.isfinite(b)
    err = np.abs(a - b)[both]
    echo(f"world: {wcfg.style}, seed {wcfg.seed}, {w.layout.kind}; {mesh.num_faces} triangles, {len(w.actors)} moving actors")
    echo(f"VoxSplat: {vs}")
    echo(f"sensor: {lidar.config.name}, {sweep.num_rays} rays -> {len(sweep)} returns")
    if err.size:
        echo(f"VoxSplat vs mesh sweep on {int(mask.sum())} rays returning inside the fitted region (noise on both): "
             f"|range error| median {np.median(err) * 100:.1f} cm, p90 {np.percentile(err, 90) * 100:.1f} cm; "
             f"{both.sum() / mask.sum() * 100:.1f} % of them return on the VoxSplat too")
    for name, sec in times.items():
        echo(f"  {name:<28s} {sec:7.3f} s")
    echo(f"outputs in {out}/: views.png scene.npz scene_3dgs.ply sweep.pcd scene.usdc sweep.usda bev.png")
    return {"times": times, "points": len(sweep), "gaussians": vs.num_gaussians}
