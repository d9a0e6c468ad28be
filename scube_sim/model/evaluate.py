"""A checkpoint's metrics on one split of a data folder (`evaluate`), and the stage's metrics over
a dataset (`evaluate_model`, which the trainer's validation uses too), with the progress bars
both share.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import torch
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from torch import nn
from torch.utils.data import DataLoader, Dataset

from ..errors import InputError
from .checkpoint import load_model, resolve_checkpoint
from .config import stage_configs, torch_settings
from .stages import Stage, StageError, get_stage


def evaluate_model(stage: Stage, model: nn.Module, dataset: Dataset, batch_size: int,
                   num_workers: int = 0, progress: bool = False) -> dict[str, float]:
    """The stage's metrics over the whole `dataset`, in order, in eval mode without gradients
    (`progress`: a bar over the batches)."""
    loader = DataLoader(dataset, batch_size=batch_size, shuffle=False, collate_fn=stage.collate,
                        num_workers=num_workers, generator=torch.Generator().manual_seed(0))
    was_training = model.training
    model.eval()
    batches = iter(loader)
    try:
        with torch.no_grad(), batch_bar(progress, len(loader), f"eval {stage.name}") as tick:
            metrics = stage.evaluate(model, (tick(b) for b in batches))
    finally:
        model.train(was_training)
        # A sample that fails in a worker leaves the iterator (and its worker processes) held by
        # the traceback; stop the workers now, not when the garbage collector gets to them (which
        # waits out torch's 5 s join timeout).
        getattr(batches, "_shutdown_workers", lambda: None)()
    if stage.primary_metric not in metrics:
        raise StageError(f"stage {stage.name!r}: evaluate returned no {stage.primary_metric!r} "
                         f"(got {', '.join(metrics) or 'nothing'})")
    return {str(k): float(v) for k, v in metrics.items()}


def bar_columns() -> tuple:
    """The progress bar's columns, for training and evaluation alike."""
    return (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
            TimeRemainingColumn())


@contextlib.contextmanager
def batch_bar(enabled: bool, total: int, what: str):
    """A rich progress bar over `total` batches; yields tick(batch) -> batch."""
    if not enabled:
        yield lambda b: b
        return
    with Progress(*bar_columns()) as bar:
        task = bar.add_task(what, total=total)

        def tick(b):
            bar.advance(task)
            return b

        yield tick


def evaluate(stage: Stage | str, checkpoint: str | Path, data_dir: str | Path, split: str = "test",
             data_overrides: dict | None = None, progress: bool = False) -> dict[str, float]:
    """The stage's metrics of a checkpoint's weights on one split of a data folder.
    data_overrides: fields of the stage's data config to change from the checkpoint's (e.g.
    ``{"eval_frames": True}``; validated like the config)."""
    stage = get_stage(stage) if isinstance(stage, str) else stage
    checkpoint, data_dir = resolve_checkpoint(checkpoint), Path(data_dir)
    model, run = load_model(stage, checkpoint)
    if split not in stage.splits:
        raise InputError(f"split: {split!r} is not a split of stage {stage.name!r} ({', '.join(stage.splits)})")
    if not data_dir.is_dir():
        raise InputError(f"{data_dir}: no such data folder")
    _, data_cfg = stage_configs(run, stage.model_config, stage.data_config)
    if data_overrides:
        unknown = sorted(set(data_overrides) - set(type(data_cfg).model_fields))
        if unknown:
            raise InputError(f"data option {', '.join(unknown)}: not a field of stage {stage.name!r}'s data config "
                             f"(fields: {', '.join(type(data_cfg).model_fields)})")
        try:
            data_cfg = type(data_cfg)(**{**data_cfg.model_dump(), **data_overrides})
        except ValueError as exc:
            raise InputError(f"data options {data_overrides}: {exc}") from None
    with torch_settings(run.train, 1):
        dataset = stage.dataset(data_dir, data_cfg, split, run.train.seed)
        if len(dataset) == 0:
            raise InputError(f"{data_dir}: the {split} split has no samples")
        return evaluate_model(stage, model, dataset, run.train.batch_size, run.train.num_workers, progress)


