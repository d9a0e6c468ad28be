"""The converter's model commands: `train` (a stage) and `eval` (a checkpoint, the whole
converter end to end with `eval sensor-to-sensor`, or per-pixel depth with `eval depth`)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..config import CONTEXT_INSTANTS, FINE_VOXEL_M, SEED, Range
from ._common import CliError, _fail, app, bounded, handle_errors

# what `eval` evaluates besides one stage's checkpoint: the whole converter, per-pixel depth
EVAL_MODES = ("sensor-to-sensor", "depth")


@app.command("train")
@handle_errors
@bounded(ranks=Range(ge=1, le=256, integer=True))
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
    from ..model.checkpoint import load_checkpoint
    from ..model.config import config_from_dict, load_config
    from ..model.stages import get_stage
    from ..model.trainer import LAST, train

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


@app.command("eval")
@handle_errors
@bounded(context=CONTEXT_INSTANTS, limit=Range(ge=1, integer=True), gt_voxel=FINE_VOXEL_M, seed=SEED)
def eval_cmd(
    stage: str = typer.Argument(..., is_eager=True, callback=lambda v: _eval_stage_name(v),
                                help="converter stage the checkpoint belongs to (geometry-vae, geometry, "
                                "appearance), sensor-to-sensor: the whole converter, end to end, or depth: "
                                "per-pixel depth of the camera images against ground truth"),
    data: Optional[Path] = typer.Option(None, "--data", help="dataset folder (required)"),
    checkpoint: Optional[str] = typer.Option(None, "--checkpoint", help="a run's last.pt or best.pt, or a shipped "
                                             "checkpoint's name (appearance-cpu); geometry, appearance: default "
                                             "the shipped paper-route (cpu) profile's; another stage needs it; "
                                             "depth: the geometry checkpoint of --method mono or fused "
                                             "(default geometry-coarse-cpu); sensor-to-sensor: none (the "
                                             "profile names them)"),
    dataset: Optional[str] = typer.Option(None, "--dataset", help="depth: the dataset adapter (worlds, nuscenes, "
                                          "kitti_raw, ...); worlds: --data DIR --split S or --data DIR/<split>"),
    method: str = typer.Option("mono", "--method", help="depth: the depth method (mono: the geometry "
                               "checkpoint's monocular depth head; stereo: plane-sweep multi-view stereo over "
                               "the other cameras and the --context instants, confident pixels only; fused: "
                               "stereo where confident, the monocular head elsewhere)"),
    context: Optional[int] = typer.Option(None, "--context", help="depth: the method sees up to K instants "
                                          "before and after each sample (stereo needs them; default 0: the sample's "
                                          "frames alone); sensor-to-sensor: the converter does (default: the "
                                          "profile's, evidence 4)"),
    split: str = typer.Option("test", "--split", help="train | val | test"),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="metrics .json to write"),
    data_option: list[str] = typer.Option([], "--data-option", help="KEY=VALUE: a field of the stage's data "
                                          "config to change from the checkpoint's (repeatable; VALUE is YAML), "
                                          "e.g. eval_frames=true"),
    progress: bool = typer.Option(True, "--progress/--no-progress"),
    profile: str = typer.Option("evidence-complete", "--profile", help="sensor-to-sensor: converter profile (shipped name "
                                "or YAML)"),
    sensor: str = typer.Option("hdl64e", "--sensor", help="sensor-to-sensor: LiDAR preset or YAML"),
    limit: Optional[int] = typer.Option(None, "--limit", help="sensor-to-sensor, depth: the split's (the "
                                        "dataset's) first N samples"),
    gt_voxel: float = typer.Option(0.4, "--gt-voxel", help="sensor-to-sensor: the ground-truth VoxSplat's voxel (m)"),
    seed: int = typer.Option(0, "--seed", help="sensor-to-sensor: converter and LiDAR seed"),
) -> None:
    """Evaluate a checkpoint on one split of a dataset folder; `eval sensor-to-sensor` converts
    each held-out worlds sample's cameras and sweeps a LiDAR through the result against the same
    LiDAR on the world's mesh (model/eval/sensor_to_sensor.py); `eval depth --dataset NAME` scores a
    depth method on each sample's camera images against the rendered depth maps, else the sample's
    LiDAR projected into the cameras (model/eval/depth.py)."""
    import json

    from ..atomic import atomic_path
    from ..config import parse_key_values
    from ..model.eval.evaluate import evaluate
    from ..model.stages import get_stage

    if data is None:
        raise CliError("--data: required (the dataset folder)")
    if stage == "sensor-to-sensor":
        if checkpoint is not None:
            raise CliError("--checkpoint: eval sensor-to-sensor uses the checkpoints its --profile names")
        _eval_sensor_to_sensor(data, split, profile, sensor, limit, gt_voxel, seed, output, progress, context)
        return
    if stage == "depth":
        if checkpoint is not None and method == "stereo":
            raise CliError("--checkpoint: --method stereo uses no checkpoint (mono and fused do)")
        _eval_depth(data, dataset, split, limit, method, checkpoint, output, progress, context or 0)
        return

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
        from ..model.converter import PAPER_PROFILE

        typer.echo(f"checkpoint: {checkpoint} (the shipped {PAPER_PROFILE} profile's {st.name} checkpoint)")
    if output is not None:
        typer.echo(f"-> {output}")


def _eval_stage_name(stage: str) -> str:
    """`eval`'s STAGE, checked before any option (an eager callback): a registered stage or one of
    EVAL_MODES; otherwise one line naming it and listing what eval takes (exit 2)."""
    from ..config import normalize_name
    from ..model.stages import stage_names

    names = stage_names()
    if stage not in EVAL_MODES and normalize_name(stage) not in {normalize_name(n) for n in names}:
        _fail(f"unknown stage {stage!r}; eval takes {', '.join(sorted([*names, *EVAL_MODES]))}")
    return stage


def _default_checkpoint(stage: str) -> str:
    """The checkpoint `eval STAGE` uses without --checkpoint: the one the shipped paper-route
    profile (`converter.PAPER_PROFILE`) names for the stage; a stage it names none for is an error
    listing the shipped checkpoints of that stage."""
    from ..model.checkpoint import load_checkpoint, shipped_checkpoints
    from ..model.converter import PAPER_PROFILE, load_profile

    prof = load_profile(PAPER_PROFILE)
    named = {"geometry": prof.geometry.checkpoint, "appearance": prof.appearance.checkpoint}
    if stage in named:
        return named[stage]
    own = [name for name, path in shipped_checkpoints().items() if load_checkpoint(path).get("stage") == stage]
    raise CliError(f"--checkpoint: required to evaluate the {stage} stage (the shipped profiles name no {stage} "
                   f"checkpoint); a run's last.pt or best.pt, or a shipped one: {', '.join(own) or 'none ships'}")


def _eval_sensor_to_sensor(data: Path, split: str, profile: str, sensor: str, limit: int | None, gt_voxel: float,
                           seed: int, output: Path | None, progress: bool, context: int | None = None) -> None:
    import json

    from ..atomic import atomic_path
    from ..model.eval.sensor_to_sensor import evaluate_split, format_table
    from ._common import track

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


def _eval_depth(data: Path, dataset: str | None, split: str, limit: int | None, method: str,
                checkpoint: str | None, output: Path | None, progress: bool, context: int = 0) -> None:
    import json

    from ..atomic import atomic_path
    from ..datasets import open_dataset
    from ._common import track
    from ..datasets.worlds import DATASET_FILE as WORLDS_HEADER
    from ..model.eval.depth import depth_method, evaluate_depth, format_table, json_ready

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
