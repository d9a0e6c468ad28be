"""Commands that run the program's jobs: `demo`, `replay` (a scenario end to end) and `batch`
(one job over many inputs, locally or on Ray)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..config import COMMAND_THREADS, SCENE_VOXEL_M, SEED, THREADS, WORKERS, Range
from ..converter.profile import DEFAULT_PROFILE
from ._common import CliError, app, bounded, handle_errors, start_threads, threads_option


@app.command("demo")
@handle_errors
@bounded(voxel_size=SCENE_VOXEL_M, seed=SEED)
@bounded(threads=COMMAND_THREADS)
def demo_cmd(
    output: Path = typer.Option(Path("out"), "-o", "--output", help="output folder"),
    sensor: str = typer.Option("hdl64e", "--sensor", "-s", help="LiDAR preset or YAML"),
    voxel_size: float = typer.Option(0.2, "--voxel-size", help="VoxSplat voxel size [m]"),
    seed: int = typer.Option(0, "--seed"),
    profile: str = typer.Option(DEFAULT_PROFILE, "--profile", help="converter profile for the camera-to-LiDAR part "
                                "(the default: stereo depth over the cameras at T and 4 instants either side, fused, "
                                "what no camera saw completed; evidence: without the completion; "
                                "cpu-lidar: the paper's route, one Gaussian per voxel, no context instants)"),
    convert: bool = typer.Option(True, "--convert/--no-convert", help="also convert the camera images and compare"),
    threads: int = threads_option(),
) -> None:
    """Build a VoxSplat of the default scene, sweep a LiDAR through it and write out/; convert the
    scene's camera images (and the instants around them the profile asks for) and sweep that too."""
    start_threads(threads)
    from ..runs.demo import run_demo

    run_demo(output, sensor=sensor, voxel_size=voxel_size, seed=seed, echo=typer.echo,
             profile=profile if convert else None)


@app.command("replay")
@handle_errors
@bounded(duration=Range(gt=0, le=86_400, unit="seconds"), seed=SEED)
@bounded(threads=COMMAND_THREADS)
def replay_cmd(
    scenario: Path = typer.Argument(..., help="scenario YAML (see scenarios/)"),
    output: Path = typer.Option(..., "-o", "--output", help="output folder (new or empty; see --overwrite, --resume)"),
    duration: Optional[float] = typer.Option(None, "--duration", help="seconds to simulate (default: the scenario's)"),
    seed: Optional[int] = typer.Option(None, "--seed", help="override the scenario's seed"),
    overwrite: bool = typer.Option(False, "--overwrite", help="clear the output folder's earlier run first "
                                   "(the VoxSplat chunk cache scene_chunks/ is kept)"),
    resume: bool = typer.Option(False, "--resume", help="continue the same run (same inputs and settings, "
                                "by its manifest.json): nothing to do if complete, else run it again"),
    threads: int = threads_option(),
) -> None:
    """Run a scenario end to end: frames (PCD/BIN/NPZ + manifest), a USD stage, CAN out."""
    start_threads(threads)
    from ..runs.replay import replay

    r = replay(scenario, output, duration=duration, seed=seed, overwrite=overwrite, resume=resume,
               echo=lambda m: typer.echo(m))
    if r.state == "complete":
        typer.echo(f"{r.name}: {output} already holds this run, complete ({r.outputs} output "
                   f"files, checksums verified); nothing to do")
        return
    typer.echo(f"{r.name}: {r.ticks} ticks ({r.simulated_s:.1f} s simulated), {r.sweeps} sweeps, {r.points} points "
               f"in {r.run_s:.1f} s ({r.ticks / max(r.run_s, 1e-9):.1f} ticks/s; scene set-up {r.setup_s:.1f} s) "
               f"-> {output}" + (" (run again: the earlier attempt was incomplete)" if r.state == "redo" else ""))


@app.command("batch")
@handle_errors
@bounded(workers=WORKERS, retries=Range(ge=0, le=100, integer=True), threads=THREADS)
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
    from ..config import load_yaml, parse_key_values
    from ..parallel.runner import run_batch
    from ..runs.batch_jobs import make_job

    data = {}
    if settings is not None:
        data = load_yaml(settings, error=CliError) or {}  # names the file; refuses a key given twice
        if not isinstance(data, dict):
            raise CliError(f"--settings {settings}: expected a YAML mapping of settings")
    data.update(parse_key_values(set_, "--set"))
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


@app.command("bag-reindex")
@handle_errors
def bag_reindex_cmd(
    folder: Path = typer.Argument(..., help="the rosbag2 folder (metadata.yaml + .mcap) a replay wrote"),
) -> None:
    """Make a ROS 2 bag that a killed replay left readable again (like `ros2 bag reindex`): keep its
    whole chunks, cut an unfinished write, rewrite the MCAP's summary and metadata.yaml. A bag that
    reads as it is stays as it is."""
    from ..sim.sinks.rosbag import reindex_bag

    r = reindex_bag(folder)
    if not r.changed:
        typer.echo(f"{folder}: reads as it is ({r.messages} messages in {r.chunks} chunks); nothing to do")
        return
    cut = f"; cut {r.cut_bytes} bytes of an unfinished write" if r.cut_bytes else ""
    typer.echo(f"{folder}: {r.messages} messages in {r.chunks} chunks{cut}; summary and metadata.yaml rewritten")
