"""Commands on real sensor datasets: `build` (a VoxSplat from real sweeps), `fidelity` (simulated
against real, ray for ray) and `datasets export` (to the generic folder format)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from ..config import COMMAND_THREADS, SAMPLE_INDEX
from ..realdata.options import BUILD_RANGES
from ._common import (
    CliError,
    app,
    bounded,
    datasets_app,
    handle_errors,
    int_list,
    name_list,
    start_threads,
    threads_option,
)


@app.command("build")
@handle_errors
@bounded(**{k: BUILD_RANGES[k] for k in ("voxel_size", "gaussians_per_voxel", "patch_scale", "max_patch_sigma",
                                             "max_normal_scale", "mesh_max_edge_rel")})
@bounded(threads=COMMAND_THREADS)
def build_cmd(
    path: Path = typer.Argument(..., help="dataset folder"),
    dataset: str = typer.Option(..., "--dataset", "-d", help="nuscenes | kitti_raw | kitti_object | kitti360 | tri_dgp | argoverse2 | waymo | folder"),
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
    threads: int = threads_option(),
) -> None:
    """Build a VoxSplat from real LiDAR sweeps (accumulate, remove moving objects, fit, colour)."""
    start_threads(threads)
    from ..datasets import open_dataset
    from ..realdata.build import BuildOptions, build_from_dataset

    if output.suffix != ".npz":
        raise CliError(f"-o: expected a .npz path, got {output}")
    opts = BuildOptions(samples=int_list(samples, "--samples"),
                        sensors=name_list([s for s in sensors.split(",") if s], "--sensors") if sensors else None,
                        remove=remove, carve_with=int_list(carve_with, "--carve-with"), voxel_size=voxel_size,
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


@app.command("fidelity")
@handle_errors
@bounded(sample=SAMPLE_INDEX)
@bounded(threads=COMMAND_THREADS)
def fidelity_cmd(
    path: Path = typer.Argument(..., help="dataset folder"),
    dataset: str = typer.Option(..., "--dataset", "-d", help="dataset format (as for `build`)"),
    scene: Path = typer.Option(..., "--scene", help="VoxSplat .npz (from `scube-sim build`)"),
    sample: int = typer.Option(0, "--sample", help="index of the real sweep to compare with"),
    sensor: Optional[str] = typer.Option(None, "--sensor", help="sensor name (default: the sample's first sweep)"),
    output: Path = typer.Option(Path("out/fidelity"), "-o", "--output", help="folder for report.md/.json/.png"),
    mode: Optional[str] = typer.Option(None, "--mode", help="tracer depth: max_response | entry (default: the scene's "
                                       "metadata trace_mode, else max_response)"),
    baselines: bool = typer.Option(True, "--baselines/--no-baselines", help="voxel cubes and Poisson next to the VoxSplat"),
    noise: bool = typer.Option(False, "--noise/--no-noise", help="add the sensor model's range noise"),
    raw: bool = typer.Option(False, "--raw", help="compare with the sweep as measured (undo motion compensation): tests the motion model"),
    static_from: str = typer.Option("", "--static-from", help="sample indices whose sweeps find returns on moving objects; adds [static rays] rows"),
    assume_single_origin: bool = typer.Option(False, "--assume-single-origin", help="trace a sweep that looks merged from several LiDARs from its stated origin anyway"),
    ground_plane: bool = typer.Option(False, "--ground-plane", help="add a flat road plane under the ego as a floor row"),
    regions: bool = typer.Option(False, "--regions", help="also score the returns within 40 m inside the sample's cameras, "
                                 "ground and above ground apart, beside a plane fitted to the sweep, and the surface "
                                 "distances both ways (converted scenes)"),
    threads: int = threads_option(),
) -> None:
    """Simulate the real sensor at the real pose and compare with the real sweep, ray for ray."""
    start_threads(threads)
    from ..datasets import open_dataset
    from ..realdata.fidelity import FidelityOptions, run_fidelity, write_report
    from ..voxsplat import VoxSplat

    # every argument checked before the dataset is read (a log without poses estimates them first)
    if mode is not None and mode not in ("entry", "max_response", "soft"):
        raise CliError(f"--mode: expected entry, max_response or soft, got {mode!r}")
    static = int_list(static_from, "--static-from")
    vs = VoxSplat.load(scene)
    ds = open_dataset(dataset, path)
    for flag, index in [("--sample", sample)] + [("--static-from", i) for i in static]:
        if index >= len(ds):
            raise CliError(f"{flag}: {index} is past the dataset's last sample ({len(ds) - 1}): {path}")
    mode = mode or (vs.metadata.get("trace_mode") if isinstance(vs.metadata, dict) else None) or "max_response"
    opts = FidelityOptions(sensor=sensor, mode=mode, baselines=baselines, noise=noise,
                           static_from=static, raw=raw,
                           assume_single_origin=assume_single_origin, ground_plane=ground_plane, regions=regions)
    res = run_fidelity(ds, vs, sample, opts, progress=lambda m: typer.echo(m + " ..."))
    paths = write_report(res, output)
    typer.echo(res.markdown())
    typer.echo(f"-> {paths['markdown']}, {paths['png']}")


@datasets_app.command("export")
@handle_errors
def datasets_export_cmd(
    path: Path = typer.Argument(..., help="dataset folder"),
    dataset: str = typer.Option(..., "--dataset", "-d", help="nuscenes | kitti_raw | kitti_object | kitti360 | tri_dgp | argoverse2 | waymo"),
    output: Path = typer.Option(..., "-o", "--output", help="folder to write (docs/dataset-folder-format.md)"),
    points_format: str = typer.Option("npz", "--points", help="npz (exact float64) | pcd | ply | bin"),
    image_format: str = typer.Option("png", "--images", help="png (lossless) | jpg"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace an existing folder dataset"),
) -> None:
    """Write a dataset in scube-sim's generic folder format (what other datasets convert to)."""
    from rich.progress import track

    from ..datasets import open_dataset
    from ..datasets.folder import write_folder_dataset

    ds = open_dataset(dataset, path)
    samples = track((ds[i] for i in range(len(ds))), total=len(ds), description=f"exporting {ds.name}",
                    transient=True)  # gone when done, so that an error is the one line left
    write_folder_dataset(samples, output, points_format=points_format, image_format=image_format,
                         name=ds.name, overwrite=overwrite)
    typer.echo(f"{ds.name}: {len(ds)} sample(s) -> {output}")
