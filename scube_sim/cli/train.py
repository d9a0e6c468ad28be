"""The `train` command: one learned stage of the converter, resumable bit for bit."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..config import Range
from ._common import CliError, app, bounded, handle_errors


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
