"""Commands on one scene file: `lidar` (a sweep), `export` (convert between formats), `render`
(camera views), and `sensors` (the LiDAR presets)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from ..config import COMMAND_THREADS, SCALE_FACTOR, SEED, VOXEL_SIZE_M, Range
from ._common import CliError, app, bounded, handle_errors, parse_pose, start_threads, threads_option


@app.command("lidar")
@handle_errors
@bounded(threads=COMMAND_THREADS, k=Range(gt=0, le=10), soft_alpha_min=Range(ge=0, lt=1), seed=SEED)
def lidar_cmd(
    scene: Path = typer.Argument(..., help="VoxSplat .npz or any 3DGS .ply"),
    sensor: str = typer.Option(..., "--sensor", "-s", help="preset name (see `scube-sim sensors`) or a sensor YAML path"),
    output: Path = typer.Option(..., "-o", "--output", help="point cloud to write: .pcd, .ply, .bin (KITTI) or .npz"),
    pose: str = typer.Option("0,0,0,0,0,0", "--pose", help="sensor pose in the scene frame: x,y,z,roll,pitch,yaw (m, deg)"),
    mode: str = typer.Option("auto", "--mode", help="entry | max_response | soft | auto (a VoxSplat's own trace_mode, else entry; soft for 3DGS .ply)"),
    backend: Optional[str] = typer.Option(None, "--backend", help="open3d | embreex | compiled: the Embree engine of the reference core's proxies (default open3d)"),
    core: Optional[str] = typer.Option(None, "--core", help="compiled | reference (default: compiled where built; env SCUBE_SIM_CORE)"),
    threads: int = threads_option(),
    k: float = typer.Option(3.0, "--k", help="hard surface: the k-sigma ellipsoid"),
    soft_alpha_min: float = typer.Option(1.0 / 255.0, "--soft-alpha-min", help="soft mode: contributions fainter than this are dropped (converted scenes: 0.1 traces faster at a lower median error, fewer returns)"),
    seed: int = typer.Option(0, "--seed", help="random seed (noise, drops)"),
    png: Optional[Path] = typer.Option(None, "--png", help="also write a bird's-eye view PNG"),
) -> None:
    """Simulate one LiDAR sweep; the output is in the sensor frame (x forward, y left, z up)."""
    threads = start_threads(threads)
    from ..io.pointcloud import write_points
    from ..lidar.config import load_lidar_config
    from ..lidar.model import Lidar
    from ..raytrace import DEFAULT_BACKEND, MODES, CompiledCore, HardMode, ReferenceCore, SoftMode, Tracer
    from ..raytrace.compiled import default_core_name
    from ..scene_file import load_scene
    from ..voxsplat import VoxSplat

    sensor_pose = parse_pose(pose)
    if output.suffix.lower() not in (".pcd", ".ply", ".bin", ".npz"):
        raise CliError(f"{output}: unknown point cloud format {output.suffix!r}; use .pcd, .ply, .bin or .npz")
    cfg = load_lidar_config(sensor)
    t0 = time.perf_counter()
    sc = load_scene(scene)
    m = mode if mode != "auto" else (sc.metadata.get("trace_mode", "entry") if isinstance(sc, VoxSplat) else "soft")
    if core not in (None, "compiled", "reference"):
        raise CliError(f"--core: expected compiled or reference, got {core!r}")
    if m not in MODES:
        raise CliError(f"--mode: expected one of {', '.join(MODES)} or auto, got {m!r}")
    trace = SoftMode(k=k, alpha_min=soft_alpha_min) if m == "soft" else HardMode(m, k=k)
    if (core or default_core_name()) == "compiled":
        engine = CompiledCore(threads)
    else:
        engine = ReferenceCore(backend or DEFAULT_BACKEND)
    tracer = Tracer(sc, trace, core=engine)
    t1 = time.perf_counter()
    sweep = Lidar(cfg).scan(tracer, sensor_pose, seed=seed)
    t2 = time.perf_counter()
    write_points(output, sweep.points)
    if png:
        from ..viz import bev_png

        bev_png(png, sweep.xyz(), labels=sweep.points["label"], title=f"{cfg.name} on {scene.name}")
    typer.echo(f"{cfg.name}: {len(sweep)} points from {sweep.num_rays} rays -> {output} "
               f"(load+build {t1 - t0:.2f} s, sweep {t2 - t1:.3f} s, mode {m}, core {tracer.core_name})")
    if len(sweep) < 0.01 * sweep.num_rays:
        typer.echo("note: under 1 % of the rays returned; is the sensor inside a surface or outside the "
                   "scene? (--pose is the sensor pose in the scene frame)", err=True)


@app.command("export")
@handle_errors
@bounded(voxel_size=VOXEL_SIZE_M, max_gaussians=Range(ge=1, integer=True))
@bounded(threads=COMMAND_THREADS)
def export_cmd(
    scene: Path = typer.Argument(..., help="VoxSplat .npz or 3DGS .ply"),
    to: str = typer.Option(..., "--to", help="ply (3DGS, Inria layout) | usd (.usda) | usdc | npz (VoxSplat)"),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="default: SCENE with the new suffix"),
    voxel_size: Optional[float] = typer.Option(None, "--voxel-size", help="for --to npz from a .ply (default: automatic)"),
    max_gaussians: Optional[int] = typer.Option(
        None, "--max-gaussians", help="--to ply: keep the N Gaussians with the largest opacity x area (a 3DGS "
                                      "trainer's initialisation)"),
    threads: int = threads_option(),
) -> None:
    """Convert a scene between VoxSplat .npz, 3DGS .ply and USD."""
    start_threads(threads)
    from ..scene_file import as_voxsplat, load_scene
    from ..voxsplat import VoxSplat

    suffixes = {"ply": ".ply", "usd": ".usda", "usda": ".usda", "usdc": ".usdc", "npz": ".npz"}
    if to not in suffixes:
        raise CliError(f"--to: expected one of {', '.join(suffixes)}, got {to!r}")
    if max_gaussians is not None and (to != "ply" or max_gaussians < 1):
        raise CliError(f"--max-gaussians: expected a count >= 1 with --to ply, got {max_gaussians} with --to {to}")
    out = output or scene.with_name(scene.stem + ("_3dgs" if to == "ply" and scene.suffix == ".ply" else "")
                                    + suffixes[to])
    sc = load_scene(scene)
    if to == "ply":
        from ..io.ply3dgs import write_3dgs_ply

        g = sc.gaussians() if isinstance(sc, VoxSplat) else sc
        if max_gaussians is not None:
            g = g.strongest(max_gaussians)
        write_3dgs_ply(out, g)
    elif to == "npz":
        as_voxsplat(sc, voxel_size).save(out)
    else:
        from ..io.usd import export_usd

        if isinstance(sc, VoxSplat):
            export_usd(out, voxsplat=sc)
        else:
            export_usd(out, gaussians=sc)
    typer.echo(f"wrote {out}")


@app.command("render")
@handle_errors
@bounded(scale=SCALE_FACTOR)
@bounded(threads=COMMAND_THREADS)
def render_cmd(
    scene: Path = typer.Argument(..., help="VoxSplat .npz or any 3DGS .ply"),
    rig: str = typer.Option(..., "--rig", help="camera rig preset (waymo-5, nuscenes-6) or a rig YAML"),
    output: Path = typer.Option(..., "-o", "--output", help="PNG mosaic of the rig's views"),
    pose: str = typer.Option("0,0,0,0,0,0", "--pose", help="ego pose in the scene frame: x,y,z,roll,pitch,yaw (m, deg)"),
    scale: float = typer.Option(0.25, "--scale", help="of each camera's resolution (CPU time grows with pixels)"),
    threads: int = threads_option(),
) -> None:
    """Render camera views of a scene through a rig with the CPU Gaussian renderer."""
    start_threads(threads)
    from ..camera.rig import load_rig
    from ..model.nn.views import render_rig
    from ..scene_file import load_scene
    from ..viz import mosaic_png

    if output.suffix.lower() != ".png":
        raise CliError(f"{output}: expected a .png path")
    ego = parse_pose(pose)
    cams = load_rig(rig)
    sc = load_scene(scene)
    t0 = time.perf_counter()
    views = render_rig(sc, cams, ego, scale=scale)
    mosaic_png(output, {k: (v * 255).round().astype(np.uint8) for k, v in views.items()},
               title=f"{scene.name} through {cams.name}")
    typer.echo(f"{cams.name}: {len(views)} views of {scene.name} in {time.perf_counter() - t0:.1f} s -> {output}")


@app.command("sensors")
@handle_errors
def sensors_cmd() -> None:
    """List the LiDAR presets: channels, vertical field of view, rate, columns, range."""
    from rich.console import Console
    from rich.table import Table

    from ..lidar.config import SpinningPattern, list_presets

    table = Table(title="LiDAR presets (sensors/lidar/*.yaml)")
    for col in ("id", "name", "channels", "vertical FOV [deg]", "rate [Hz]", "columns", "range [m]"):
        table.add_column(col)
    for cfg in list_presets():
        p = cfg.pattern
        if isinstance(p, SpinningPattern):
            el = p.channels.elevation_deg
            fov, rate, cols = f"{min(el):+.1f} .. {max(el):+.1f}", f"{p.rotation_hz:g}", str(p.columns)
        else:
            fov, rate, cols = "table", f"{1 / p.period_s:g}", "-"
        table.add_row(cfg.id or "", cfg.name, str(cfg.channels), fov, rate, cols,
                      f"{cfg.range.min_m:g} .. {cfg.range.max_m:g}")
    Console().print(table)
