"""The `make demo` job on the embedded default scenario: a procedural urban block ->
ground-truth VoxSplat -> HDL-64E sweep -> files in out/, with timings and the VoxSplat's range
error against the same sweep on the exact mesh; then the converter: the world's five camera
images -> a converted VoxSplat -> the same sweep through it, compared with the mesh's and the
ground-truth VoxSplat's in one table."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np

from ..camera.frames import Frames
from ..converter.profile import DEFAULT_PROFILE, load_profile
from ..io.ply3dgs import write_3dgs_ply
from ..io.pointcloud import write_pcd
from ..io.usd import export_usd
from ..lidar.compare import sweep_agreement
from ..lidar.config import load_lidar_config
from ..lidar.model import Lidar
from ..raytrace.tracer import Tracer
from ..transforms import invert_pose, transform_points
from ..viz import bev_compare_png, bev_png, fidelity_png, mosaic_png
from ..worlds.dataset import DatasetConfig, render_frames_with_context
from ..worlds.generator import WorldConfig, generate_world
from ..worlds.groundtruth import gt_voxsplat
from ..worlds.textures import world_albedo

# The embedded default scenario (the same as scenarios/urban-block.yaml).
DEFAULT_WORLD = WorldConfig(style="urban", seed=7, layout="x_junction")
# The demo fits the 51.2 m x 51.2 m around the ego (the whole chunk at 0.2 m holds ~3 M Gaussians).
REGION = (np.array([-10.24, -25.6, -3.23]), np.array([40.96, 25.6, 40.0]))


# The worlds datasets' image scale of the rig presets (the converter's training images).
FRAMES_SCALE = DatasetConfig().image_scale


def run_demo(out: str | Path, *, sensor: str = "hdl64e", voxel_size: float = 0.2, seed: int = 0,
             world: WorldConfig | None = None, echo: Callable[[str], None] = print,
             profile: str | None = DEFAULT_PROFILE) -> dict:
    """Write views.png, scene.npz, scene_3dgs.ply, sweep.pcd, scene.usdc, sweep.usda and bev.png
    into `out`; with a converter `profile` (None: skip) also converted.npz (the VoxSplat the
    converter makes from the camera images), converted_sweep.pcd, mesh_sweep.pcd,
    converted_bev.png and converted_range.png. The converter sees the five cameras at T and, where
    the profile has a context (evidence: 4), the instants around T at 10 Hz. Returns the timings
    and counts it printed."""
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
    # the instants around T the converter's profile looks at (the evidence route's stereo and fusion)
    context = 0
    if profile is not None:
        context = load_profile(profile).context
    frames = render_frames_with_context(w, "waymo-5", context, FRAMES_SCALE, log="demo")
    mosaic_png(out / "views.png", {im.name: im.image for im in frames.images},
               title=f"{wcfg.style} world, seed {wcfg.seed}: the Waymo-like rig at T")
    times[f"render 5 cameras at {2 * context + 1} instants"] = time.perf_counter() - t

    t = time.perf_counter()
    vs = gt_voxsplat(mesh, chunk_to_world, voxel_size, region=REGION, albedo_fn=world_albedo(w, 0.0))
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
    mask = np.zeros(a.shape, bool)
    mask[mesh_sweep.pixels(mesh_sweep.points[inside])] = True
    both = mask & np.isfinite(b)
    err = np.abs(a - b)[both]
    echo(f"world: {wcfg.style}, seed {wcfg.seed}, {w.layout.kind}; {mesh.num_faces} triangles, {len(w.actors)} moving actors")
    echo(f"VoxSplat: {vs}")
    echo(f"sensor: {lidar.config.name}, {sweep.num_rays} rays -> {len(sweep)} returns")
    if err.size:
        echo(f"VoxSplat vs mesh sweep on {int(mask.sum())} rays returning inside the fitted region (noise on both): "
             f"|range error| median {np.median(err) * 100:.1f} cm, p90 {np.percentile(err, 90) * 100:.1f} cm; "
             f"{both.sum() / mask.sum() * 100:.1f} % of them return on the VoxSplat too")
    result = {"times": times, "points": len(sweep), "gaussians": vs.num_gaussians}
    names = "views.png scene.npz scene_3dgs.ply sweep.pcd scene.usdc sweep.usda bev.png"
    if profile is not None:
        result["converted"] = _convert_and_compare(out, frames, profile, lidar, pose, pose_world, mesh_sweep, sweep,
                                                   mask, seed, times, echo)
        names += " converted.npz converted_sweep.pcd mesh_sweep.pcd converted_bev.png converted_range.png"
    for name, sec in times.items():
        echo(f"  {name:<28s} {sec:7.3f} s")
    echo(f"outputs in {out}/: {names}")
    return result


def _convert_and_compare(out: Path, frames: Frames, profile: str, lidar: Lidar, pose: np.ndarray,
                         pose_world: np.ndarray, mesh_sweep, gt_sweep, rays: np.ndarray, seed: int,
                         times: dict, echo: Callable[[str], None]) -> dict:
    """The converter's part of the demo (run_demo's docstring): convert, sweep, compare, write."""
    from ..converter.pipeline import Converter

    t = time.perf_counter()
    conv = Converter(profile)
    done = conv.convert(frames, seed=seed)
    scene = done.scene
    times[f"convert 5 cameras ({conv.profile.name})"] = time.perf_counter() - t
    # the converter's own trace mode (soft: its Gaussians are camera-trained blobs; at hard opacity
    # the sensor sits inside the ground's 3-sigma shells); the ground truth's are thin surfels
    # fitted for hard opacity (`entry`)
    mode = scene.metadata.get("trace_mode", "entry")
    t = time.perf_counter()
    sweep = lidar.scan(Tracer(scene, mode=mode), pose, seed=seed)
    times["LiDAR sweep (converted)"] = time.perf_counter() - t
    t = time.perf_counter()
    scene.save(out / "converted.npz")
    write_pcd(out / "converted_sweep.pcd", sweep.points, viewpoint=pose)
    write_pcd(out / "mesh_sweep.pcd", mesh_sweep.points, viewpoint=pose_world)
    ref = mesh_sweep.range_image()
    rows = {"ground-truth VoxSplat, entry": sweep_agreement(ref, gt_sweep.range_image(), rays),
            f"converted, {mode}": sweep_agreement(ref, sweep.range_image(), rays)}
    conv_img = sweep.range_image()
    fidelity_png(out / "converted_range.png",
                 {"mesh (ground truth)": ref, "converted VoxSplat": conv_img, "error (converted - mesh)": conv_img - ref},
                 title=f"{lidar.config.name}: the converted scene against the mesh, ray for ray",
                 mismatch=np.isfinite(ref) != np.isfinite(conv_img))
    err = np.abs(np.nan_to_num(conv_img - ref, nan=np.inf))
    per_point = err[sweep.pixels()]
    bev_compare_png(out / "converted_bev.png",
                    {"mesh (ground truth)": (mesh_sweep.xyz(), None), "ground-truth VoxSplat": (gt_sweep.xyz(), None),
                     "converted from the cameras, |range error|": (sweep.xyz(), np.minimum(per_point, 5.0))},
                    extent=45.0, value_name="|range error| [m] (5 = 5 or more, or no mesh return)",
                    title=f"{lidar.config.name}, sensor frame: the converted scene beside the ground truth")
    times["write converted outputs"] = time.perf_counter() - t
    echo(f"converter (profile {profile}): {scene}; {100 * float(scene.channel('observed').mean()):.1f} % of voxels "
         f"seen by the cameras; "
         f"{', '.join(f'{k[:-2]} {v:.1f} s' for k, v in done.timings.items() if k.endswith('_s'))}")
    echo(f"{lidar.config.name} on both VoxSplats against the mesh, on the rays whose mesh return lies inside the "
         f"fitted region:")
    echo(f"{'scene':<30s} {'rays':>7s} {'median |dr|':>12s} {'p90 |dr|':>10s} {'hit agreement':>14s}")
    for name, r in rows.items():
        echo(f"{name:<30s} {r['rays']:7d} {100 * r['median_m']:10.1f} cm {100 * r['p90_m']:7.1f} cm "
             f"{100 * r['hit_agreement']:12.1f} %")
    return rows
