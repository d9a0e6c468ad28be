"""`scube-sim` command line. Errors print one line naming the problem and exit with code 2."""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from .errors import ScubeSimError, ScubeSimWarning

app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode="rich",
                  help="LiDAR simulation on VoxSplats (SCube): hard-opacity Gaussian ray tracing with Embree.")

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report it


class CliError(ScubeSimError):
    """An input problem to report in one line (exit code 2)."""


def _fail(msg: str) -> None:
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(EXIT_USAGE)


def _parse_pose(text: str) -> np.ndarray:
    from .transforms import pose_from_xyz_rpy

    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise CliError(f"--pose: expected six numbers x,y,z,roll,pitch,yaw (metres, degrees), got {text!r}")
    if len(vals) != 6 or not np.all(np.isfinite(vals)):
        raise CliError(f"--pose: expected six finite numbers x,y,z,roll,pitch,yaw (metres, degrees), got {text!r}")
    return pose_from_xyz_rpy(vals[:3], vals[3:])


def _run(fn):
    """Run a command body, turning our errors (`ScubeSimError`) and file-system errors into
    one-line messages and exit code 2, Ctrl-C into one line and exit code 130; anything else is
    a bug and shows its traceback."""
    try:
        return fn()
    except ScubeSimError as exc:
        msg = str(exc).strip().splitlines()
        _fail(msg[0] if len(msg) == 1 else "; ".join(msg))
    except OSError as exc:
        if exc.strerror is None and exc.args:  # raised with a message of ours, e.g. "X: no such scene file"
            _fail(str(exc.args[0]))
        _fail(f"{getattr(exc, 'filename', '') or ''}: {exc.strerror or exc}".lstrip(": "))
    except KeyboardInterrupt:
        # every output is whole (atomic files, sinks closed with the frames completed)
        typer.echo("interrupted: the outputs written so far are complete files", err=True)
        raise typer.Exit(EXIT_INTERRUPTED) from None


@app.command("lidar")
def lidar_cmd(
    scene: Path = typer.Argument(..., help="VoxSplat .npz or any 3DGS .ply"),
    sensor: str = typer.Option(..., "--sensor", "-s", help="preset name (see `scube-sim sensors`) or a sensor YAML path"),
    output: Path = typer.Option(..., "-o", "--output", help="point cloud to write: .pcd, .ply, .bin (KITTI) or .npz"),
    pose: str = typer.Option("0,0,0,0,0,0", "--pose", help="sensor pose in the scene frame: x,y,z,roll,pitch,yaw (m, deg)"),
    mode: str = typer.Option("auto", "--mode", help="entry | max_response | soft | auto (a VoxSplat's own trace_mode, else entry; soft for 3DGS .ply)"),
    backend: Optional[str] = typer.Option(None, "--backend", help="open3d | embreex | compiled: the Embree engine for meshes and the reference core's proxies (default: meshes on the compiled core, proxies on open3d)"),
    core: Optional[str] = typer.Option(None, "--core", help="compiled | reference (default: compiled where built; env SCUBE_SIM_CORE)"),
    threads: int = typer.Option(0, "--threads", help="the compiled core's threads (0: all cores)"),
    k: float = typer.Option(3.0, "--k", help="hard surface: the k-sigma ellipsoid"),
    soft_alpha_min: float = typer.Option(1.0 / 255.0, "--soft-alpha-min", help="soft mode: contributions fainter than this are dropped (converted scenes: 0.1 traces faster at a lower median error, fewer returns)"),
    seed: int = typer.Option(0, "--seed", help="random seed (noise, drops)"),
    png: Optional[Path] = typer.Option(None, "--png", help="also write a bird's-eye view PNG"),
) -> None:
    """Simulate one LiDAR sweep; the output is in the sensor frame (x forward, y left, z up)."""

    def body():
        from .io.pointcloud import write_points
        from .lidar.config import load_lidar_config
        from .lidar.model import Lidar
        from .raytrace.tracer import Tracer
        from .scene_file import load_scene
        from .voxsplat import VoxSplat

        sensor_pose = _parse_pose(pose)
        if output.suffix.lower() not in (".pcd", ".ply", ".bin", ".npz"):
            raise CliError(f"{output}: unknown point cloud format {output.suffix!r}; use .pcd, .ply, .bin or .npz")
        cfg = load_lidar_config(sensor)
        t0 = time.perf_counter()
        sc = load_scene(scene)
        m = mode if mode != "auto" else (sc.metadata.get("trace_mode", "entry") if isinstance(sc, VoxSplat) else "soft")
        if core not in (None, "compiled", "reference"):
            raise CliError(f"--core: expected compiled or reference, got {core!r}")
        tracer = Tracer(sc, backend=backend, mode=m, k=k, core=core, threads=threads, soft_alpha_min=soft_alpha_min)
        t1 = time.perf_counter()
        sweep = Lidar(cfg).scan(tracer, sensor_pose, seed=seed)
        t2 = time.perf_counter()
        write_points(output, sweep.points)
        if png:
            from .viz import bev_png

            bev_png(png, sweep.xyz(), labels=sweep.points["label"], title=f"{cfg.name} on {scene.name}")
        typer.echo(f"{cfg.name}: {len(sweep)} points from {sweep.num_rays} rays -> {output} "
                   f"(load+build {t1 - t0:.2f} s, sweep {t2 - t1:.3f} s, mode {m}, core {tracer.core_name})")
        if len(sweep) < 0.01 * sweep.num_rays:
            typer.echo("note: under 1 % of the rays returned; is the sensor inside a surface or outside the "
                       "scene? (--pose is the sensor pose in the scene frame)", err=True)

    _run(body)


@app.command("export")
def export_cmd(
    scene: Path = typer.Argument(..., help="VoxSplat .npz or 3DGS .ply"),
    to: str = typer.Option(..., "--to", help="ply (3DGS, Inria layout) | usd (.usda) | usdc | npz (VoxSplat)"),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="default: SCENE with the new suffix"),
    voxel_size: Optional[float] = typer.Option(None, "--voxel-size", help="for --to npz from a .ply (default: automatic)"),
    max_gaussians: Optional[int] = typer.Option(
        None, "--max-gaussians", help="--to ply: keep the N Gaussians with the largest opacity x area (a 3DGS "
                                      "trainer's initialisation)"),
) -> None:
    """Convert a scene between VoxSplat .npz, 3DGS .ply and USD."""

    def body():
        from .scene_file import as_voxsplat, load_scene
        from .voxsplat import VoxSplat

        suffixes = {"ply": ".ply", "usd": ".usda", "usda": ".usda", "usdc": ".usdc", "npz": ".npz"}
        if to not in suffixes:
            raise CliError(f"--to: expected one of {', '.join(suffixes)}, got {to!r}")
        if max_gaussians is not None and (to != "ply" or max_gaussians < 1):
            raise CliError(f"--max-gaussians: expected a count >= 1 with --to ply, got {max_gaussians} with --to {to}")
        out = output or scene.with_name(scene.stem + ("_3dgs" if to == "ply" and scene.suffix == ".ply" else "")
                                        + suffixes[to])
        sc = load_scene(scene)
        if to == "ply":
            from .io.ply3dgs import write_3dgs_ply

            g = sc.gaussians() if isinstance(sc, VoxSplat) else sc
            if max_gaussians is not None:
                g = g.strongest(max_gaussians)
            write_3dgs_ply(out, g)
        elif to == "npz":
            as_voxsplat(sc, voxel_size).save(out)
        else:
            from .io.usd import export_usd

            if isinstance(sc, VoxSplat):
                export_usd(out, voxsplat=sc)
            else:
                export_usd(out, gaussians=sc)
        typer.echo(f"wrote {out}")

    _run(body)


@app.command("render")
def render_cmd(
    scene: Path = typer.Argument(..., help="VoxSplat .npz or any 3DGS .ply"),
    rig: str = typer.Option(..., "--rig", help="camera rig preset (waymo-5, nuscenes-6) or a rig YAML"),
    output: Path = typer.Option(..., "-o", "--output", help="PNG mosaic of the rig's views"),
    pose: str = typer.Option("0,0,0,0,0,0", "--pose", help="ego pose in the scene frame: x,y,z,roll,pitch,yaw (m, deg)"),
    scale: float = typer.Option(0.25, "--scale", help="of each camera's resolution (CPU time grows with pixels)"),
) -> None:
    """Render camera views of a scene through a rig with the CPU Gaussian renderer."""

    def body():
        from .camera.rig import load_rig
        from .model.views import render_rig
        from .scene_file import load_scene
        from .viz import mosaic_png

        if not 0 < scale <= 1:
            raise CliError(f"--scale: expected a factor in (0, 1], got {scale}")
        if output.suffix.lower() != ".png":
            raise CliError(f"{output}: expected a .png path")
        ego = _parse_pose(pose)
        cams = load_rig(rig)
        sc = load_scene(scene)
        t0 = time.perf_counter()
        views = render_rig(sc, cams, ego, scale=scale)
        mosaic_png(output, {k: (v * 255).round().astype(np.uint8) for k, v in views.items()},
                   title=f"{scene.name} through {cams.name}")
        typer.echo(f"{cams.name}: {len(views)} views of {scene.name} in {time.perf_counter() - t0:.1f} s -> {output}")

    _run(body)


@app.command("sensors")
def sensors_cmd() -> None:
    """List the LiDAR presets: channels, vertical field of view, rate, columns, range."""

    def body():
        from rich.console import Console
        from rich.table import Table

        from .lidar.config import SpinningPattern, list_presets

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

    _run(body)


@app.command("demo")
def demo_cmd(
    output: Path = typer.Option(Path("out"), "-o", "--output", help="output folder"),
    sensor: str = typer.Option("hdl64e", "--sensor", "-s", help="LiDAR preset or YAML"),
    voxel_size: float = typer.Option(0.2, "--voxel-size", help="VoxSplat voxel size [m]"),
    seed: int = typer.Option(0, "--seed"),
    profile: str = typer.Option("cpu-lidar", "--profile", help="converter profile for the camera-to-LiDAR part "
                                "(cpu-lidar: one Gaussian per voxel; cpu-lidar-fine: with the fine geometry level, "
                                "half its range error at about twice the conversion time)"),
    convert: bool = typer.Option(True, "--convert/--no-convert", help="also convert the camera images and compare"),
) -> None:
    """Build a VoxSplat of the default scene, sweep a LiDAR through it and write out/; convert the
    scene's camera images with the SCube converter and sweep that too."""

    def body():
        from .demo import run_demo

        run_demo(output, sensor=sensor, voxel_size=voxel_size, seed=seed, echo=typer.echo,
                 profile=profile if convert else None)

    _run(body)


@app.command("replay")
def replay_cmd(
    scenario: Path = typer.Argument(..., help="scenario YAML (see scenarios/)"),
    output: Path = typer.Option(..., "-o", "--output", help="output folder (new or empty; see --overwrite, --resume)"),
    duration: Optional[float] = typer.Option(None, "--duration", help="seconds to simulate (default: the scenario's)"),
    seed: Optional[int] = typer.Option(None, "--seed", help="override the scenario's seed"),
    overwrite: bool = typer.Option(False, "--overwrite", help="clear the output folder's earlier run first "
                                   "(the VoxSplat chunk cache scene_chunks/ is kept)"),
    resume: bool = typer.Option(False, "--resume", help="continue the same run (same inputs and settings, "
                                "by its manifest.json): nothing to do if complete, else run it again"),
) -> None:
    """Run a scenario end to end: frames (PCD/BIN/NPZ + manifest), a USD stage, CAN out."""

    def body():
        from .sim.replay import replay

        r = replay(scenario, output, duration=duration, seed=seed, overwrite=overwrite, resume=resume,
                   echo=lambda m: typer.echo(m))
        if r.state == "complete":
            typer.echo(f"{r.name}: {output} already holds this run, complete ({r.outputs} output "
                       f"files, checksums verified); nothing to do")
            return
        typer.echo(f"{r.name}: {r.ticks} ticks ({r.simulated_s:.1f} s simulated), {r.sweeps} sweeps, {r.points} points "
                   f"in {r.run_s:.1f} s ({r.ticks / max(r.run_s, 1e-9):.1f} ticks/s; scene set-up {r.setup_s:.1f} s) "
                   f"-> {output}" + (" (run again: the earlier attempt was incomplete)" if r.state == "redo" else ""))

    _run(body)


def _int_list(text: str, flag: str) -> list[int]:
    try:
        vals = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise CliError(f"{flag}: expected comma-separated sample indices, got {text!r}")
    return vals


@app.command("build")
def build_cmd(
    path: Path = typer.Argument(..., help="dataset folder"),
    dataset: str = typer.Option(..., "--dataset", "-d", help="nuscenes | kitti_raw | kitti_object | argoverse2 | waymo | folder"),
    output: Path = typer.Option(..., "-o", "--output", help="VoxSplat .npz to write"),
    samples: str = typer.Option("0", "--samples", help="sample indices to accumulate, e.g. 0 or 0,1,2"),
    sensors: Optional[str] = typer.Option(None, "--sensors", help="comma-separated sensor names (default: all)"),
    voxel_size: float = typer.Option(0.1, "--voxel-size", help="metres"),
    gaussians_per_voxel: int = typer.Option(4, "--gaussians-per-voxel", "-M"),
    remove: str = typer.Option("none", "--remove", help="points in labelled boxes to drop: none | dynamic | all"),
    carve_with: str = typer.Option("", "--carve-with", help="sample indices whose sweeps carve away moving objects"),
    patch_scale: float = typer.Option(0.5, "--patch-scale", help="share of the neighbourhood spread each point covers"),
    max_patch_sigma: float = typer.Option(0.03, "--max-patch-sigma", help="cap on a point's patch (std, metres)"),
    max_normal_scale: float = typer.Option(0.02, "--max-normal-scale", help="cap on Gaussian thickness (std, metres)"),
    mesh: bool = typer.Option(True, "--mesh/--no-mesh", help="connect neighbouring returns into triangles before fitting"),
    mesh_max_edge_rel: float = typer.Option(0.2, "--mesh-max-edge-rel", help="longest triangle edge, as a share of the range"),
    all_points: bool = typer.Option(False, "--all-points/--mesh-points", help="every return adds its own patch, not only those in no triangle"),
    color: bool = typer.Option(True, "--color/--no-color", help="colour from the camera images, where present"),
    assume_single_origin: bool = typer.Option(False, "--assume-single-origin", help="build sweeps that look merged from several LiDARs from their stated origin anyway"),
) -> None:
    """Build a VoxSplat from real LiDAR sweeps (accumulate, remove moving objects, fit, colour)."""

    def body():
        from .datasets import open_dataset
        from .reconstruct import BuildOptions, build_from_dataset

        if output.suffix != ".npz":
            raise CliError(f"-o: expected a .npz path, got {output}")
        opts = BuildOptions(samples=_int_list(samples, "--samples"),
                            sensors=[s for s in sensors.split(",") if s] if sensors else None,
                            remove=remove, carve_with=_int_list(carve_with, "--carve-with"), voxel_size=voxel_size,
                            gaussians_per_voxel=gaussians_per_voxel, patch_scale=patch_scale,
                            max_patch_sigma=max_patch_sigma, max_normal_scale=max_normal_scale,
                            all_points=all_points, color=color, mesh=mesh, mesh_max_edge_rel=mesh_max_edge_rel,
                            assume_single_origin=assume_single_origin)
        if not opts.samples:
            raise CliError("--samples: give at least one sample index")
        t0 = time.perf_counter()
        ds = open_dataset(dataset, path)
        vs, rep, acc = build_from_dataset(ds, opts)
        output.parent.mkdir(parents=True, exist_ok=True)
        vs.save(output)
        if getattr(ds, "poses_from_icp", False):
            fits = [f"{r.fitness:.2f}/{100 * r.rmse:.1f} cm" for r in ds.icp_results]
            typer.echo(f"poses: registered with open3d ICP (the set has none); fitness/rmse per step: {', '.join(fits)}")
        for note in acc.notes:
            typer.echo(note)
        typer.echo(f"{ds.name}: {rep.points} points ({rep.removed} removed, {rep.colored} coloured) -> "
                   f"{rep.voxels} voxels, {rep.gaussians} Gaussians at {rep.voxel_size:g} m, M = "
                   f"{rep.gaussians_per_voxel} in {time.perf_counter() - t0:.1f} s -> {output}")

    _run(body)


@app.command("convert")
def convert_cmd(
    path: Path = typer.Argument(..., help="a worlds sample folder (DIR/test/000000), or with --dataset any adapter's folder"),
    output: Path = typer.Option(..., "-o", "--output", help="VoxSplat .npz to write"),
    dataset: Optional[str] = typer.Option(None, "--dataset", "-d", help="nuscenes | kitti_raw | kitti_object | waymo | folder | worlds (DIR/<split>)"),
    sample: int = typer.Option(0, "--sample", help="sample index in the dataset"),
    profile: str = typer.Option("cpu", "--profile", help="a shipped converter profile's name or a profile YAML's path"),
    steps: Optional[int] = typer.Option(None, "--steps", help="DDIM steps of the geometry stage (default: the profile's)"),
    seed: int = typer.Option(0, "--seed", help="the geometry sampler's seed"),
    confidence: int = typer.Option(0, "--confidence", "-k", help="K geometry samples for per-voxel confidence (0: one sample, confidence 1)"),
    sky: bool = typer.Option(True, "--sky/--no-sky", help="decode the sky panorama (--no-sky for LiDAR-only use)"),
    max_range: Optional[float] = typer.Option(None, "--max-range", help="keep voxels within this many metres of the ego (a LiDAR's range)"),
    fit_steps: Optional[int] = typer.Option(None, "--fit-steps", help="a test-time fit of the Gaussians to the input views, Adam steps (default: the profile's, 0 in the shipped ones; ~3 s each)"),
) -> None:
    """Convert posed camera frames into a VoxSplat (the SCube converter: geometry, then appearance)."""

    def body():
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        from .model.converter import Converter, open_frames

        if output.suffix != ".npz":
            raise CliError(f"-o: expected a .npz path, got {output}")
        if confidence == 1 or confidence < 0:
            raise CliError(f"--confidence: expected 0 (off) or K >= 2 samples, got {confidence}")
        if fit_steps is not None and fit_steps < 0:
            raise CliError(f"--fit-steps: expected an integer >= 0, got {fit_steps}")
        frames = open_frames(path, dataset, sample)
        conv = Converter(profile)
        t0 = time.perf_counter()
        n_fit = conv.profile.appearance.fit_steps if fit_steps is None else fit_steps
        with Progress(TextColumn("fitting the Gaussians to the input views"), BarColumn(), MofNCompleteColumn(),
                      TimeElapsedColumn(), transient=True, disable=not n_fit) as bar:
            task = bar.add_task("", total=n_fit)
            vs = conv.convert(frames, steps=steps, seed=seed, confidence=confidence > 1, k=confidence or None, sky=sky,
                              max_range=max_range, fit_steps=fit_steps,
                              progress=lambda step, total: bar.update(task, completed=step, total=total))
        output.parent.mkdir(parents=True, exist_ok=True)
        vs.save(output)
        t = conv.timings
        seen = float(vs.channel("observed").mean()) if vs.num_voxels else 0.0
        typer.echo(f"{frames.metadata.get('sample', path)}: {len(frames)} camera(s) -> {vs.num_voxels} voxels at "
                   f"{vs.voxel_size:g} m ({100 * seen:.1f} % observed), {vs.num_gaussians} Gaussians; geometry "
                   f"{t['geometry_s']:.1f} s, appearance {t['appearance_s']:.1f} s, peak {t['peak_mb']:.0f} MB, "
                   f"{time.perf_counter() - t0:.1f} s -> {output}")

    _run(body)


@app.command("fidelity")
def fidelity_cmd(
    path: Path = typer.Argument(..., help="dataset folder"),
    dataset: str = typer.Option(..., "--dataset", "-d", help="dataset format (as for `build`)"),
    scene: Path = typer.Option(..., "--scene", help="VoxSplat .npz (from `scube-sim build`)"),
    sample: int = typer.Option(0, "--sample", help="index of the real sweep to compare with"),
    sensor: Optional[str] = typer.Option(None, "--sensor", help="sensor name (default: the sample's first sweep)"),
    output: Path = typer.Option(Path("out/fidelity"), "-o", "--output", help="folder for report.md/.json/.png"),
    mode: str = typer.Option("max_response", "--mode", help="tracer depth: max_response | entry"),
    baselines: bool = typer.Option(True, "--baselines/--no-baselines", help="voxel cubes and Poisson next to the VoxSplat"),
    noise: bool = typer.Option(False, "--noise/--no-noise", help="add the sensor model's range noise"),
    raw: bool = typer.Option(False, "--raw", help="compare with the sweep as measured (undo motion compensation): tests the motion model"),
    static_from: str = typer.Option("", "--static-from", help="sample indices whose sweeps find returns on moving objects; adds [static rays] rows"),
    assume_single_origin: bool = typer.Option(False, "--assume-single-origin", help="trace a sweep that looks merged from several LiDARs from its stated origin anyway"),
    ground_plane: bool = typer.Option(False, "--ground-plane", help="add a flat road plane under the ego as a floor row"),
) -> None:
    """Simulate the real sensor at the real pose and compare with the real sweep, ray for ray."""

    def body():
        from .datasets import open_dataset
        from .fidelity import run_fidelity, write_report
        from .voxsplat import VoxSplat

        ds = open_dataset(dataset, path)
        vs = VoxSplat.load(scene)
        res = run_fidelity(ds, vs, sample=sample, sensor=sensor, mode=mode, baselines=baselines, noise=noise,
                           static_from=_int_list(static_from, "--static-from"), raw=raw, progress=lambda m: typer.echo(m + " ..."),
                           assume_single_origin=assume_single_origin, ground_plane=ground_plane)
        paths = write_report(res, output)
        typer.echo(res.markdown())
        typer.echo(f"-> {paths['markdown']}, {paths['png']}")

    _run(body)


datasets_app = typer.Typer(no_args_is_help=True, help="Real sensor datasets: export to the generic folder format.")
app.add_typer(datasets_app, name="datasets")


@datasets_app.command("export")
def datasets_export_cmd(
    path: Path = typer.Argument(..., help="dataset folder"),
    dataset: str = typer.Option(..., "--dataset", "-d", help="nuscenes | kitti_raw | kitti_object | argoverse2 | waymo"),
    output: Path = typer.Option(..., "-o", "--output", help="folder to write (docs/dataset-folder-format.md)"),
    points_format: str = typer.Option("npz", "--points", help="npz (exact float64) | pcd | ply | bin"),
    image_format: str = typer.Option("png", "--images", help="png (lossless) | jpg"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace an existing folder dataset"),
) -> None:
    """Write a dataset in scube-sim's generic folder format (what other datasets convert to)."""

    def body():
        from rich.progress import track

        from .datasets import open_dataset
        from .datasets.folder import write_folder_dataset

        ds = open_dataset(dataset, path)
        samples = track((ds[i] for i in range(len(ds))), total=len(ds), description=f"exporting {ds.name}")
        write_folder_dataset(samples, output, points_format=points_format, image_format=image_format,
                             name=ds.name, overwrite=overwrite)
        typer.echo(f"{ds.name}: {len(ds)} sample(s) -> {output}")

    _run(body)


@app.command("batch")
def batch_cmd(
    job: str = typer.Argument(..., help="worlds | build | replay | convert"),
    inputs: list[str] = typer.Option(..., "--inputs", "-i", help="inputs: comma-separated, a glob, or a list file "
                                     "(@FILE, one per line); worlds: SPLIT:INDEX or SPLIT:FIRST-LAST (repeatable)"),
    output: Path = typer.Option(..., "-o", "--output", help="batch folder (created, or resumed: complete tasks are skipped)"),
    workers: int = typer.Option(1, "--workers", "-w", help="tasks at a time (worker processes)"),
    executor: str = typer.Option("local", "--executor", help="local (a process pool here) | ray"),
    address: Optional[str] = typer.Option(None, "--address", help="Ray cluster address (default: start a local Ray)"),
    retries: int = typer.Option(1, "--retries", help="further attempts after a failed one"),
    threads: int = typer.Option(1, "--threads", help="BLAS / OpenMP / torch threads per worker"),
    settings: Optional[Path] = typer.Option(None, "--settings", help="YAML mapping of the job's settings "
                                            "(docs/batch.md)"),
    set_: list[str] = typer.Option([], "--set", help="KEY=VALUE (YAML value): one setting, over --settings"),
    progress: bool = typer.Option(True, "--progress/--no-progress"),
) -> None:
    """Run one job over many inputs, resumably: locally or on Ray (docs/batch.md)."""

    def body():
        import yaml

        from .batch.jobs import make_job
        from .batch.runner import run_batch

        data = {}
        if settings is not None:
            data = yaml.safe_load(settings.read_text(encoding="utf-8")) or {}
            if not isinstance(data, dict):
                raise CliError(f"--settings {settings}: expected a YAML mapping of settings")
        for item in set_:
            key, eq, value = item.partition("=")
            if not eq or not key:
                raise CliError(f"--set {item!r}: expected KEY=VALUE")
            data[key.strip()] = yaml.safe_load(value)
        rep = run_batch(make_job(job, data), inputs, output, executor=executor, workers=workers, retries=retries,
                        threads=threads, address=address, progress=progress)
        rate = f", {rep.tasks_per_minute:.1f} tasks/min" if rep.completed else ""
        typer.echo(f"batch {job}: {rep.total} task(s): {rep.completed} done, {rep.skipped} already complete, "
                   f"{rep.failed} failed ({rep.attempts} attempt(s) in {rep.seconds:.1f} s{rate}; {executor}, "
                   f"{workers} worker(s)) -> {output / 'batch.json'}")
        if rep.failed:
            for key, r in rep.records.items():
                if r["status"] == "failed":
                    typer.echo(f"failed: {key} ({r['input']}): {r['error']}", err=True)
            raise typer.Exit(1)

    _run(body)


worlds_app = typer.Typer(no_args_is_help=True, help="Procedural driving worlds and their datasets.")
app.add_typer(worlds_app, name="worlds")


@worlds_app.command("generate")
def worlds_generate_cmd(
    output: Path = typer.Option(..., "-o", "--output", help="dataset folder (created, or resumed)"),
    split: str = typer.Option("train", "--split", help="train | val | test (fixed seeds per split)"),
    count: int = typer.Option(10, "--count", help="number of samples"),
    start: int = typer.Option(0, "--start", help="index of the first sample"),
    jobs: int = typer.Option(1, "--jobs", "-j", help="worker processes"),
    rig: Optional[str] = typer.Option(None, "--rig", help="camera rig (default waymo-5), or rigs separated by "
                                      "commas that the samples cycle through; only for a new folder"),
    image_scale: Optional[float] = typer.Option(None, "--image-scale", help="of the rig's resolution (default 0.25)"),
    frame_offsets: Optional[str] = typer.Option(None, "--frame-offsets",
                                                help="stored instants in frames after T, comma-separated, "
                                                "starting at 0 (default 0,5,10); only for a new folder"),
    fine_voxel: Optional[float] = typer.Option(None, "--fine-voxel", help="fine ground-truth voxel size in metres "
                                               "(default 0.1); only for a new folder"),
    coarse_factor: Optional[int] = typer.Option(None, "--coarse-factor", help="coarse voxel = factor x fine "
                                                "(default 4); only for a new folder"),
) -> None:
    """Write dataset samples: images at T, T+5, T+10 (or --frame-offsets), depth, semantics, poses, boxes, GT
    voxels and LiDAR."""

    def body():
        from .config import validate_model
        from .worlds.dataset import DatasetConfig, generate_dataset

        if count < 0 or start < 0 or jobs < 1:
            raise CliError("--count and --start must be >= 0 and --jobs >= 1")
        cfg = None
        new = any(v is not None for v in (rig, image_scale, frame_offsets, fine_voxel, coarse_factor))
        if new or not (output / "dataset.json").exists():
            kw = {}
            if frame_offsets is not None:
                try:
                    kw["frame_offsets"] = [int(k) for k in frame_offsets.split(",") if k.strip()]
                except ValueError:
                    raise CliError(f"--frame-offsets: expected integers separated by commas, got {frame_offsets!r}")
            if rig is not None:
                kw["rigs"] = [r.strip() for r in rig.split(",") if r.strip()]
            if image_scale is not None:
                kw["image_scale"] = image_scale
            if fine_voxel is not None:
                kw["fine_voxel_m"] = fine_voxel
            if coarse_factor is not None:
                kw["coarse_factor"] = coarse_factor
            cfg = validate_model(DatasetConfig, kw, "worlds generate options", error=CliError)
        res = generate_dataset(output, split, count, cfg, start=start, jobs=jobs)
        typer.echo(f"{split}: wrote {res['written']}, skipped {res['skipped']} complete; "
                   f"{res['seconds_per_sample']:.2f} s per sample (wall, {jobs} job(s)) -> {output}")

    _run(body)


@worlds_app.command("preview")
def worlds_preview_cmd(
    scenario: Optional[Path] = typer.Argument(None, help="scenario YAML with a `world:` section"),
    style: str = typer.Option("urban", "--style", help="urban | suburban | intersection | boulevard"),
    seed: int = typer.Option(0, "--seed"),
    output: Path = typer.Option(Path("out"), "-o", "--output", help="folder for the PNGs"),
    rig: str = typer.Option("waymo-5", "--rig"),
) -> None:
    """Render a world's camera views and a top view of its ground-truth voxels."""

    def body():
        from .worlds.generator import WorldConfig
        from .worlds.preview import preview_world

        cfg = WorldConfig.from_yaml(scenario) if scenario else WorldConfig(style=style, seed=seed)
        name = scenario.stem if scenario else None
        res = preview_world(cfg, output, name=name, rig=rig)
        typer.echo(f"wrote {res['views']} and {res['voxels']} ({res['num_voxels']} voxels, "
                   f"{res['visible'] * 100:.0f} % seen by the cameras)")

    _run(body)


@app.command("train")
def train_cmd(
    stage: str = typer.Argument(..., help="converter stage to train (geometry, appearance)"),
    data: Path = typer.Option(..., "--data", help="dataset folder"),
    config: Optional[str] = typer.Option(None, "--config", "-c", help="shipped training config name or a YAML path "
                                         "(with --resume, default: the run's own)"),
    output: Path = typer.Option(..., "-o", "--output", help="run folder (checkpoints, metrics.jsonl, loss.png)"),
    resume: bool = typer.Option(False, "--resume", help="continue the run in -o from its last.pt"),
    ranks: Optional[int] = typer.Option(None, "--ranks", help="processes (torch.distributed, gloo); default: the config's train.ranks"),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="show a progress bar"),
) -> None:
    """Train a converter stage (Adam; resumable bit for bit; data-parallel over CPU processes)."""

    def body():
        from .model.checkpoint import load_checkpoint
        from .model.config import config_from_dict, load_config
        from .model.stages import get_stage
        from .model.trainer import LAST, train

        st = get_stage(stage)
        if config is not None:
            cfg = load_config(config)
        elif resume:
            last = output / LAST
            if not last.is_file():
                raise CliError(f"{last}: no checkpoint to resume from")
            cfg = config_from_dict(load_checkpoint(last)["config"], f"{last} (config)")
        else:
            raise CliError("--config: required for a new run (a shipped config name or a YAML path)")
        res = train(st, cfg, data, output, resume=resume, progress=progress, ranks=ranks)
        shown = ", ".join(f"{k} {v:.4g}" for k, v in res.metrics.items())
        best = f"; best {st.primary_metric} {res.best_metric:.4g} at step {res.best_step}" if res.best_metric is not None else ""
        typer.echo(f"{st.name}: step {res.step}, epoch {res.epoch}; val {shown}{best} -> {res.last}")

    _run(body)


@app.command("eval")
def eval_cmd(
    stage: str = typer.Argument(..., help="converter stage the checkpoint belongs to (geometry-vae, geometry, "
                                "appearance), or sensor-to-sensor: the whole converter, end to end"),
    data: Path = typer.Option(..., "--data", help="dataset folder"),
    checkpoint: Optional[str] = typer.Option(None, "--checkpoint", help="a run's last.pt or best.pt, or a shipped "
                                             "checkpoint's name (appearance-cpu); a stage's evaluation needs it"),
    split: str = typer.Option("test", "--split", help="train | val | test"),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="metrics .json to write"),
    data_option: list[str] = typer.Option([], "--data-option", help="KEY=VALUE: a field of the stage's data "
                                          "config to change from the checkpoint's (repeatable; VALUE is YAML), "
                                          "e.g. eval_frames=true"),
    progress: bool = typer.Option(True, "--progress/--no-progress"),
    profile: str = typer.Option("cpu", "--profile", help="sensor-to-sensor: converter profile (shipped name or YAML)"),
    sensor: str = typer.Option("hdl64e", "--sensor", help="sensor-to-sensor: LiDAR preset or YAML"),
    limit: Optional[int] = typer.Option(None, "--limit", min=1, help="sensor-to-sensor: the split's first N samples"),
    gt_voxel: float = typer.Option(0.4, "--gt-voxel", help="sensor-to-sensor: the ground-truth VoxSplat's voxel (m)"),
    seed: int = typer.Option(0, "--seed", min=0, help="sensor-to-sensor: converter and LiDAR seed"),
) -> None:
    """Evaluate a checkpoint on one split of a dataset folder; `eval sensor-to-sensor` converts
    each held-out worlds sample's cameras and sweeps a LiDAR through the result against the same
    LiDAR on the world's mesh (model/sensor_to_sensor.py)."""

    def body():
        import json

        import yaml

        from .atomic import atomic_path
        from .model.stages import get_stage
        from .model.trainer import evaluate

        if stage == "sensor-to-sensor":
            _eval_sensor_to_sensor(data, split, profile, sensor, limit, gt_voxel, seed, output, progress)
            return
        if checkpoint is None:
            raise CliError(f"--checkpoint: required to evaluate the {stage} stage")

        overrides = {}
        for opt in data_option:
            key, sep, value = opt.partition("=")
            if not sep or not key.strip():
                raise CliError(f"--data-option {opt!r}: expected KEY=VALUE")
            try:
                overrides[key.strip()] = yaml.safe_load(value)
            except yaml.YAMLError as exc:
                raise CliError(f"--data-option {opt!r}: VALUE is not YAML ({exc})") from None
        st = get_stage(stage)
        metrics = evaluate(st, checkpoint, data, split=split, data_overrides=overrides, progress=progress)
        if output is not None:
            with atomic_path(output) as tmp:
                tmp.write_text(json.dumps({"stage": st.name, "checkpoint": str(checkpoint), "split": split,
                                           "data_options": overrides, "metrics": metrics}, indent=2) + "\n", encoding="utf-8")
        order = "higher" if st.higher_is_better else "lower"
        for k, v in metrics.items():
            typer.echo(f"{k}: {v:.6g}" + (f"  (primary, {order} is better)" if k == st.primary_metric else ""))
        if output is not None:
            typer.echo(f"-> {output}")

    _run(body)


def _eval_sensor_to_sensor(data: Path, split: str, profile: str, sensor: str, limit: int | None, gt_voxel: float,
                           seed: int, output: Path | None, progress: bool) -> None:
    import json

    from rich.progress import track

    from .atomic import atomic_path
    from .model.sensor_to_sensor import evaluate_split

    if not gt_voxel > 0:
        raise CliError(f"--gt-voxel: expected a positive voxel size in metres, got {gt_voxel}")
    bar = (lambda xs: track(xs, description="sensor to sensor")) if progress else None
    res = evaluate_split(data, split=split, profile=profile, sensor=sensor, limit=limit, gt_voxel=gt_voxel,
                         seed=seed, progress=bar)
    if output is not None:
        with atomic_path(output) as tmp:
            tmp.write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
    typer.echo(f"{res['samples_n']} {split} samples, profile {res['profile']}, {res['sensor']}, against the mesh; "
               f"ground-truth VoxSplat at {gt_voxel:g} m")
    typer.echo(f"{'ahead':>6s} {'rays':>7s} {'scene':<22s} {'split':<7s} {'median |dr|':>11s} {'p90 |dr|':>9s} "
               f"{'hits':>7s} {'Chamfer':>8s}")
    for r in res["rows"]:
        typer.echo(f"{r['ahead_m']:5.0f}m {r['rays']:7d} {r['scene']:<22s} {r['split']:<7s} {r['median_m']:9.3f} m "
                   f"{r['p90_m']:7.3f} m {100 * r['hit_agreement']:6.1f}% {r['chamfer_m']:6.3f} m")
    typer.echo("stages (mean per sample): " + ", ".join(f"{k} {v:.4g}" for k, v in res["stages"].items()))
    if output is not None:
        typer.echo(f"-> {output}")


def _show_warning(message, category, filename, lineno, file=None, line=None):
    # Ours are for the user, one line each; anyone else's keep Python's format.
    if issubclass(category, ScubeSimWarning):
        typer.echo(f"warning: {message}", err=True)
    else:
        _python_showwarning(message, category, filename, lineno, file, line)


_python_showwarning = warnings.showwarning


def main() -> None:
    warnings.showwarning = _show_warning
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
