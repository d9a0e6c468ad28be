"""The `convert` command: posed camera frames -> a VoxSplat, through the SCube converter."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from ..config import (
    COMMAND_THREADS,
    CONFIDENCE_SAMPLES,
    CONTEXT_INSTANTS,
    DDIM_STEPS,
    FIT_STEPS,
    MAX_RANGE_M,
    SAMPLE_INDEX,
    SEED,
)
from ..converter.profile import DEFAULT_PROFILE, load_profile
from ._common import CliError, app, bounded, handle_errors, stage_lines, start_threads, threads_option


@app.command("convert")
@handle_errors
@bounded(sample=SAMPLE_INDEX, steps=DDIM_STEPS, seed=SEED, confidence=CONFIDENCE_SAMPLES, max_range=MAX_RANGE_M,
         context=CONTEXT_INSTANTS, fit_steps=FIT_STEPS)
@bounded(threads=COMMAND_THREADS)
def convert_cmd(
    path: Path = typer.Argument(..., help="a worlds sample folder (DIR/test/000000), or with --dataset any adapter's folder"),
    output: Path = typer.Option(..., "-o", "--output", help="VoxSplat .npz to write"),
    dataset: Optional[str] = typer.Option(None, "--dataset", "-d", help="nuscenes | kitti_raw | kitti_object | kitti360 | tri_dgp | waymo | folder | worlds (DIR/<split>)"),
    sample: int = typer.Option(0, "--sample", help="sample index in the dataset"),
    profile: str = typer.Option(DEFAULT_PROFILE, "--profile", help="a shipped converter profile's name or a profile "
                                "YAML's path (the default: stereo depth fused, what no camera saw completed, "
                                "for LiDAR; evidence: without the completion; cpu: the paper's route, with camera views)"),
    steps: Optional[int] = typer.Option(None, "--steps", help="the paper's route: DDIM steps of the geometry stage "
                                        "(default: the profile's)"),
    seed: Optional[int] = typer.Option(None, "--seed", help="the paper's route: the geometry sampler's seed "
                                       "(default 0)"),
    confidence: Optional[int] = typer.Option(None, "--confidence", "-k", help="the paper's route: K geometry samples "
                                             "for per-voxel confidence (default: one sample, confidence 1)"),
    sky: Optional[bool] = typer.Option(None, "--sky/--no-sky", help="the paper's route: decode the sky panorama "
                                       "(default; --no-sky for LiDAR-only use)"),
    max_range: Optional[float] = typer.Option(None, "--max-range", help="keep voxels within this many metres of the ego (a LiDAR's range)"),
    context: Optional[int] = typer.Option(None, "--context", help="also give the converter the K "
                                "instants before and the K after the sample in the same log or scene (never across a "
                                "scene boundary), counted in the source's instants: nuScenes keyframes are 2 Hz, KITTI "
                                "and KITTI-360 10 Hz, a worlds sample its own stored instants minus the evaluation ones "
                                "(T+5, T+10). Default: the profile's (evidence: 4; the scube profiles: 0, they read "
                                "the reference instant only and record the instants given)"),
    fit_steps: Optional[int] = typer.Option(None, "--fit-steps", help="the paper's route: a test-time fit of the "
                                            "Gaussians to the input views, Adam steps (default: the profile's)"),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="one line on stderr as each stage "
                                  "(each stereo image, the fusion, the completion) starts"),
    threads: int = threads_option(),
) -> None:
    """Convert posed camera frames into a VoxSplat (the profile's route: measured evidence with the learned
    completion by default, or the paper's two networks)."""
    start_threads(threads)
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from ..converter.frames import open_frames
    from ..converter.pipeline import Converter

    if output.suffix != ".npz":
        raise CliError(f"-o: expected a .npz path, got {output}")
    if confidence is not None and (confidence == 1 or confidence < 0):
        raise CliError(f"--confidence: expected 0 (off) or K >= 2 samples, got {confidence}")
    chosen = load_profile(profile)
    paper = {"--steps": steps, "--seed": seed, "--confidence": confidence, "--sky" if sky else "--no-sky": sky,
             "--fit-steps": fit_steps}
    given = [name for name, value in paper.items() if value is not None]
    if given and chosen.route != "scube":
        raise CliError(f"{', '.join(given)}: profile {chosen.name!r} is route {chosen.route}, which does "
                       f"not use {'it' if len(given) == 1 else 'them'} (the paper's route does: --profile cpu)")
    status = stage_lines(progress)
    if status:
        status(f"loading profile {chosen.name}'s networks")
    conv = Converter(chosen)
    options = {} if conv.profile.route != "scube" else {
        "steps": steps, "confidence": bool(confidence and confidence > 1), "confidence_samples": confidence or None,
        "sky": True if sky is None else sky, "fit_steps": fit_steps}
    context = conv.profile.context if context is None else context
    if status:
        status(f"opening {path} (sample {sample}, {context} context instant(s) either side)")
    frames = open_frames(path, dataset, sample, context=context)
    if context and not frames.context:
        typer.echo(f"note: --context {context}: the set holds no other instant of this sample's log (one keyframe, or "
                   f"a log of one instant); converting from the sample alone", err=True)
    t0 = time.perf_counter()
    n_fit = 0 if conv.profile.appearance is None else (conv.profile.appearance.fit_steps if fit_steps is None else fit_steps)
    with Progress(TextColumn("fitting the Gaussians to the input views"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), transient=True, disable=not n_fit) as bar:
        task = bar.add_task("", total=n_fit)
        if options:
            options["progress"] = lambda step, total: bar.update(task, completed=step, total=total)
        done = conv.convert(frames, seed=seed or 0, max_range=max_range, status=status, **options)
    vs, t = done.scene, done.timings
    if status:
        status(f"writing {output}")
    output.parent.mkdir(parents=True, exist_ok=True)
    vs.save(output)
    seen = float(vs.channel("observed").mean()) if vs.num_voxels else 0.0
    given = f" (+{len(frames.context)} context instant(s))" if frames.context else ""
    typer.echo(f"{frames.metadata.get('sample', path)}: {len(frames)} camera(s){given} -> {vs.num_voxels} voxels at "
               f"{vs.voxel_size:g} m ({100 * seen:.1f} % observed), {vs.num_gaussians} Gaussians; "
               f"{', '.join(f'{k[:-2]} {v:.1f} s' for k, v in t.items() if k.endswith('_s'))}, "
               f"peak {t['peak_mb']:.0f} MB, "
               f"{time.perf_counter() - t0:.1f} s -> {output}")
