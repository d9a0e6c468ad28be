"""The `eval` commands: `eval stage` (a stage's checkpoint on a split), `eval sensor-to-sensor` (the
whole converter end to end) and `eval depth` (per-pixel camera depth against ground truth)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..config import COMMAND_THREADS, CONTEXT_INSTANTS, FINE_VOXEL_M, SEED, Range
from ..converter.profile import DEFAULT_PROFILE
from ._common import CliError, _fail, app, bounded, handle_errors, start_threads, threads_option

eval_app = typer.Typer(no_args_is_help=True, help="Evaluate a stage's checkpoint, the converter end to end, or "
                       "camera depth.")
app.add_typer(eval_app, name="eval")


@eval_app.command("stage")
@handle_errors
@bounded(threads=COMMAND_THREADS)
def eval_stage_cmd(
    stage: str = typer.Argument(..., is_eager=True, callback=lambda v: _eval_stage_name(v),
                                help="the stage the checkpoint belongs to (geometry-vae, geometry, appearance, "
                                "voxel-semantics, completion)"),
    data: Optional[Path] = typer.Option(None, "--data", help="dataset folder (required)"),
    checkpoint: Optional[str] = typer.Option(None, "--checkpoint", help="a run's last.pt or best.pt, or a shipped "
                                             "checkpoint's name (appearance-cpu); geometry, appearance: default "
                                             "the shipped paper-route profile's; another stage needs it"),
    split: str = typer.Option("test", "--split", help="train | val | test"),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="metrics .json to write"),
    data_option: list[str] = typer.Option([], "--data-option", help="KEY=VALUE: a field of the stage's data "
                                          "config to change from the checkpoint's (repeatable; VALUE is YAML), "
                                          "e.g. eval_frames=true"),
    progress: bool = typer.Option(True, "--progress/--no-progress"),
    threads: int = threads_option(),
) -> None:
    """A stage's checkpoint on one split of a dataset folder: the stage's own metrics."""
    start_threads(threads)
    import json

    from ..atomic import atomic_path
    from ..config import parse_key_values
    from ..converter.profile import PAPER_PROFILE
    from ..model.evaluate import evaluate
    from ..model.stages import get_stage

    _require_data(data)
    overrides = parse_key_values(data_option, "--data-option")
    st = get_stage(stage)
    shipped_default = checkpoint is None
    if shipped_default:
        checkpoint = _default_checkpoint(st.name)
    metrics = evaluate(st, checkpoint, data, split=split, data_overrides=overrides, progress=progress)
    if output is not None:
        with atomic_path(output) as tmp:
            tmp.write_text(json.dumps({"stage": st.name, "checkpoint": str(checkpoint), "split": split,
                                       "data_options": overrides, "metrics": metrics}, indent=2) + "\n", encoding="utf-8")
    order = "higher" if st.higher_is_better else "lower"
    for k, v in metrics.items():
        typer.echo(f"{k}: {v:.6g}" + (f"  (primary, {order} is better)" if k == st.primary_metric else ""))
    if shipped_default:
        typer.echo(f"checkpoint: {checkpoint} (the shipped {PAPER_PROFILE} profile's {st.name} checkpoint)")
    if output is not None:
        typer.echo(f"-> {output}")


@eval_app.command("sensor-to-sensor")
@handle_errors
@bounded(context=CONTEXT_INSTANTS, limit=Range(ge=1, integer=True), gt_voxel=FINE_VOXEL_M, seed=SEED)
@bounded(threads=COMMAND_THREADS)
def eval_sensor_to_sensor_cmd(
    data: Optional[Path] = typer.Option(None, "--data", help="a worlds dataset folder (required)"),
    split: str = typer.Option("test", "--split", help="train | val | test"),
    profile: str = typer.Option(DEFAULT_PROFILE, "--profile", help="converter profile (shipped name or YAML)"),
    sensor: str = typer.Option("hdl64e", "--sensor", help="LiDAR preset or YAML"),
    context: Optional[int] = typer.Option(None, "--context", help="the converter sees up to K instants before and "
                                          "after each sample (default: the profile's)"),
    limit: Optional[int] = typer.Option(None, "--limit", help="the split's first N samples"),
    gt_voxel: float = typer.Option(0.4, "--gt-voxel", help="the ground-truth VoxSplat's voxel (m)"),
    seed: int = typer.Option(0, "--seed", help="converter and LiDAR seed"),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="metrics .json to write"),
    progress: bool = typer.Option(True, "--progress/--no-progress"),
    threads: int = threads_option(),
) -> None:
    """The whole converter end to end: each held-out worlds sample's cameras converted, a LiDAR swept
    through the result against the same LiDAR on the world's mesh (converter/eval/sensor_to_sensor.py)."""
    start_threads(threads)
    import json

    from ..atomic import atomic_path
    from ..converter.eval.sensor_to_sensor import evaluate_split, format_table
    from ._common import track

    _require_data(data)
    if not gt_voxel > 0:
        raise CliError(f"--gt-voxel: expected a positive voxel size in metres, got {gt_voxel}")
    bar = (lambda xs: track(xs, description="sensor to sensor")) if progress else None
    res = evaluate_split(data, split=split, profile=profile, sensor=sensor, limit=limit, gt_voxel=gt_voxel,
                         seed=seed, progress=bar, context=context)
    if output is not None:
        with atomic_path(output) as tmp:
            tmp.write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
    for line in format_table(res, split, gt_voxel):
        typer.echo(line)
    if output is not None:
        typer.echo(f"-> {output}")


@eval_app.command("depth")
@handle_errors
@bounded(context=CONTEXT_INSTANTS, limit=Range(ge=1, integer=True))
@bounded(threads=COMMAND_THREADS)
def eval_depth_cmd(
    data: Optional[Path] = typer.Option(None, "--data", help="dataset folder (required)"),
    dataset: Optional[str] = typer.Option(None, "--dataset", help="the dataset adapter (worlds, nuscenes, "
                                          "kitti_raw, ...); worlds: --data DIR --split S or --data DIR/<split>"),
    method: str = typer.Option("mono", "--method", help="the depth method (mono: the geometry checkpoint's "
                               "monocular depth head; stereo: plane-sweep multi-view stereo over the other cameras "
                               "and the --context instants, confident pixels only; fused: stereo where confident, "
                               "the monocular head elsewhere)"),
    checkpoint: Optional[str] = typer.Option(None, "--checkpoint", help="the geometry checkpoint of --method mono or "
                                             "fused (default geometry-coarse-cpu)"),
    context: int = typer.Option(0, "--context", help="the method sees up to K instants before and after each "
                                "sample (stereo needs them; 0: the sample's frames alone)"),
    split: str = typer.Option("test", "--split", help="worlds: train | val | test"),
    limit: Optional[int] = typer.Option(None, "--limit", help="the dataset's first N samples"),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="metrics .json to write"),
    progress: bool = typer.Option(True, "--progress/--no-progress"),
    threads: int = threads_option(),
) -> None:
    """A depth method on each sample's camera images against the rendered depth maps, else the
    sample's LiDAR projected into the cameras (converter/eval/depth.py)."""
    start_threads(threads)
    _require_data(data)
    if checkpoint is not None and method == "stereo":
        raise CliError("--checkpoint: --method stereo uses no checkpoint (mono and fused do)")
    _eval_depth(data, dataset, split, limit, method, checkpoint, output, progress, context)


def _require_data(data: Path | None) -> None:
    if data is None:
        raise CliError("--data: required (the dataset folder)")


def _eval_stage_name(stage: str) -> str:
    """`eval stage`'s STAGE, checked before any option (an eager callback): a registered stage;
    otherwise one line naming it and listing the stages (exit 2)."""
    from ..config import normalize_name
    from ..model.stages import stage_names

    names = stage_names()
    if normalize_name(stage) not in {normalize_name(n) for n in names}:
        _fail(f"unknown stage {stage!r}; eval stage takes {', '.join(sorted(names))}")
    return stage


def _default_checkpoint(stage: str) -> str:
    """The checkpoint `eval STAGE` uses without --checkpoint: the one the shipped paper-route
    profile (`converter.PAPER_PROFILE`) names for the stage; a stage it names none for is an error
    listing the shipped checkpoints of that stage."""
    from ..converter.profile import PAPER_PROFILE, load_profile
    from ..model.checkpoint import load_checkpoint, shipped_checkpoints

    prof = load_profile(PAPER_PROFILE)
    named = {"geometry": prof.geometry.checkpoint, "appearance": prof.appearance.checkpoint}
    if stage in named:
        return named[stage]
    own = [name for name, path in shipped_checkpoints().items() if load_checkpoint(path).get("stage") == stage]
    raise CliError(f"--checkpoint: required to evaluate the {stage} stage (the shipped profiles name no {stage} "
                   f"checkpoint); a run's last.pt or best.pt, or a shipped one: {', '.join(own) or 'none ships'}")


def _eval_depth(data: Path, dataset: str | None, split: str, limit: int | None, method: str,
                checkpoint: str | None, output: Path | None, progress: bool, context: int = 0) -> None:
    import json

    from ..atomic import atomic_path
    from ..converter.eval.depth import depth_method, evaluate_depth, format_table, json_ready
    from ..datasets import open_dataset
    from ..datasets.worlds import DATASET_FILE as WORLDS_HEADER
    from ._common import track

    if dataset is None:
        raise CliError("--dataset: required for eval depth (worlds, nuscenes, kitti_raw, ...)")
    if dataset.lower() == "worlds":  # DIR with --split, or DIR/<split> (as `convert --dataset worlds`)
        if (data / WORLDS_HEADER).is_file():
            ds = open_dataset("worlds", data, split=split, eval_frames=False)
        else:
            ds = open_dataset("worlds", data.parent, split=data.name, eval_frames=False)
    else:
        ds = open_dataset(dataset, data)
    n = len(ds) if limit is None else min(limit, len(ds))
    if n == 0:
        raise CliError(f"{data}: the {dataset} dataset has no samples")
    m = depth_method(method, checkpoint=checkpoint)
    bar = (lambda xs: track(xs, description=f"depth ({m.name})")) if progress else None
    res = evaluate_depth(ds, range(n), m, progress=bar, context=context)
    if output is not None:
        with atomic_path(output) as tmp:
            tmp.write_text(json.dumps(json_ready(res), indent=2) + "\n", encoding="utf-8")
    for line in format_table(res):
        typer.echo(line)
    if output is not None:
        typer.echo(f"-> {output}")
