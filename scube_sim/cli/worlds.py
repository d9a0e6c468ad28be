"""The `worlds` commands: `worlds generate` (dataset samples of procedural driving worlds) and
`worlds preview` (a world's camera views and ground-truth voxels)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..config import COARSE_FACTOR, COMMAND_THREADS, FINE_VOXEL_M, SCALE_FACTOR, SEED, WORKERS, Range
from ..cpus import share_threads
from ._common import CliError, bounded, handle_errors, start_threads, threads_option, worlds_app


@worlds_app.command("generate")
@handle_errors
@bounded(count=Range(ge=0, le=1_000_000, integer=True), start=Range(ge=0, le=999_999, integer=True), jobs=WORKERS,
         image_scale=SCALE_FACTOR, fine_voxel=FINE_VOXEL_M, coarse_factor=COARSE_FACTOR)
@bounded(threads=COMMAND_THREADS)
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
                                                "increasing and including 0 (the input instant T; default "
                                                "0,5,10); negative ones are instants before T, context for "
                                                "the converter like any but 0, 5 and 10 (e.g. "
                                                "-8,-4,-2,-1,0,1,2,4,5,8,10); only for a new folder"),
    fine_voxel: Optional[float] = typer.Option(None, "--fine-voxel", help="fine ground-truth voxel size in metres "
                                               "(default 0.1); only for a new folder"),
    coarse_factor: Optional[int] = typer.Option(None, "--coarse-factor", help="coarse voxel = factor x fine "
                                                "(default 4); only for a new folder"),
    threads: int = threads_option(),
) -> None:
    """Write dataset samples: images at T, T+5, T+10 (or --frame-offsets), depth, semantics, poses, boxes, GT
    voxels and LiDAR."""
    start_threads(share_threads(jobs, threads))  # each worker's share
    from ..config import validate_model
    from ..worlds.dataset import DatasetConfig, generate_dataset

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


@worlds_app.command("preview")
@handle_errors
@bounded(seed=SEED)
@bounded(threads=COMMAND_THREADS)
def worlds_preview_cmd(
    scenario: Optional[Path] = typer.Argument(None, help="scenario YAML with a `world:` section"),
    style: str = typer.Option("urban", "--style", help="urban | suburban | intersection | boulevard"),
    seed: int = typer.Option(0, "--seed"),
    output: Path = typer.Option(Path("out"), "-o", "--output", help="folder for the PNGs"),
    rig: str = typer.Option("waymo-5", "--rig"),
    threads: int = threads_option(),
) -> None:
    """Render a world's camera views and a top view of its ground-truth voxels."""
    start_threads(threads)
    from ..worlds.generator import WorldConfig
    from ..worlds.preview import preview_world

    cfg = WorldConfig.from_yaml(scenario) if scenario else WorldConfig(style=style, seed=seed)
    name = scenario.stem if scenario else None
    res = preview_world(cfg, output, name=name, rig=rig)
    typer.echo(f"wrote {res['views']} and {res['voxels']} ({res['num_voxels']} voxels, "
               f"{res['visible'] * 100:.0f} % seen by the cameras)")


@worlds_app.command("evidence")
@handle_errors
@bounded(count=Range(ge=1, le=1_000_000, integer=True), start=Range(ge=0, le=999_999, integer=True), jobs=WORKERS)
@bounded(threads=COMMAND_THREADS)
def worlds_evidence_cmd(
    data: Path = typer.Argument(..., help="worlds dataset folder (generated with context instants)"),
    split: str = typer.Option("train", "--split", help="train | val | test"),
    count: Optional[int] = typer.Option(None, "--count", help="number of samples (default: all from --start)"),
    start: int = typer.Option(0, "--start", help="index of the first sample"),
    profile: str = typer.Option("evidence", "--profile", help="the evidence-route profile that measures"),
    jobs: int = typer.Option(1, "--jobs", "-j", help="worker processes (one thread each; the cache does not "
                             "depend on it)"),
    threads: int = threads_option(),
) -> None:
    """Measure the evidence of worlds samples with the real stereo pipeline and cache it for the completion
    stage (DATA/evidence/<split>/<sample>.npz); resumable: cached samples with the same settings are skipped."""
    start_threads(share_threads(jobs, threads))  # each worker's share
    from ..converter.profile import load_profile
    from ..model.completion.data import cache_evidence

    if split not in ("train", "val", "test"):
        raise CliError(f"--split: expected train, val or test, got {split!r}")
    res = cache_evidence(data, split, load_profile(profile), count=count, start=start, jobs=jobs)
    typer.echo(f"{split}: measured {res['written']}, skipped {res['skipped']} cached; "
               f"{res['seconds_per_sample']:.1f} s per sample -> {data / 'evidence' / split}")
