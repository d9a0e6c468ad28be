"""The `convert` command: posed camera frames -> a VoxSplat, through the SCube converter."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from ..config import CONFIDENCE_SAMPLES, CONTEXT_INSTANTS, DDIM_STEPS, FIT_STEPS, MAX_RANGE_M, SAMPLE_INDEX, SEED
from ..converter.profile import DEFAULT_PROFILE
from ._common import CliError, app, bounded, handle_errors


@app.command("convert")
@handle_errors
@bounded(sample=SAMPLE_INDEX, steps=DDIM_STEPS, seed=SEED, confidence=CONFIDENCE_SAMPLES, max_range=MAX_RANGE_M,
         context=CONTEXT_INSTANTS, fit_steps=FIT_STEPS)
def convert_cmd(
    path: Path = typer.Argument(..., help="a worlds sample folder (DIR/test/000000), or with --dataset any adapter's folder"),
    output: Path = typer.Option(..., "-o", "--output", help="VoxSplat .npz to write"),
    dataset: Optional[str] = typer.Option(None, "--dataset", "-d", help="nuscenes | kitti_raw | kitti_object | kitti360 | tri_dgp | waymo | folder | worlds (DIR/<split>)"),
    sample: int = typer.Option(0, "--sample", help="sample index in the dataset"),
    profile: str = typer.Option(DEFAULT_PROFILE, "--profile", help="a shipped converter profile's name or a profile "
                                "YAML's path (evidence-complete: stereo depth fused, what no camera saw completed, "
                                "for LiDAR; evidence: without the completion; cpu: the paper's route, with camera views)"),
    steps: Optional[int] = typer.Option(None, "--steps", help="DDIM steps of the geometry stage (default: the profile's)"),
    seed: int = typer.Option(0, "--seed", help="the geometry sampler's seed"),
    confidence: int = typer.Option(0, "--confidence", "-k", help="K geometry samples for per-voxel confidence (0: one sample, confidence 1)"),
    sky: bool = typer.Option(True, "--sky/--no-sky", help="decode the sky panorama (--no-sky for LiDAR-only use)"),
    max_range: Optional[float] = typer.Option(None, "--max-range", help="keep voxels within this many metres of the ego (a LiDAR's range)"),
    context: Optional[int] = typer.Option(None, "--context", help="also give the converter the K "
                                "instants before and the K after the sample in the same log or scene (never across a "
                                "scene boundary), counted in the source's instants: nuScenes keyframes are 2 Hz, KITTI "
                                "and KITTI-360 10 Hz, a worlds sample its own stored instants minus the evaluation ones "
                                "(T+5, T+10). Default: the profile's (evidence: 4; the scube profiles: 0, they read "
                                "the reference instant only and record the instants given)"),
    fit_steps: Optional[int] = typer.Option(None, "--fit-steps", help="a test-time fit of the Gaussians to the input views, Adam steps (default: the profile's, 0 in the shipped ones; ~3 s each)"),
) -> None:
    """Convert posed camera frames into a VoxSplat (the SCube converter: geometry, then appearance)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from ..converter.frames import open_frames
    from ..converter.pipeline import Converter

    if output.suffix != ".npz":
        raise CliError(f"-o: expected a .npz path, got {output}")
    if confidence == 1 or confidence < 0:
        raise CliError(f"--confidence: expected 0 (off) or K >= 2 samples, got {confidence}")
    conv = Converter(profile)
    context = conv.profile.context if context is None else context
    frames = open_frames(path, dataset, sample, context=context)
    if context and not frames.context:
        typer.echo(f"note: --context {context}: the set holds no other instant of this sample's log (one keyframe, or "
                   f"a log of one instant); converting from the sample alone", err=True)
    t0 = time.perf_counter()
    n_fit = 0 if conv.profile.appearance is None else (conv.profile.appearance.fit_steps if fit_steps is None else fit_steps)
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
    given = f" (+{len(frames.context)} context instant(s))" if frames.context else ""
    typer.echo(f"{frames.metadata.get('sample', path)}: {len(frames)} camera(s){given} -> {vs.num_voxels} voxels at "
               f"{vs.voxel_size:g} m ({100 * seen:.1f} % observed), {vs.num_gaussians} Gaussians; geometry "
               f"{t['geometry_s']:.1f} s, appearance {t['appearance_s']:.1f} s, peak {t['peak_mb']:.0f} MB, "
               f"{time.perf_counter() - t0:.1f} s -> {output}")
