"""Training configurations: one YAML file per run, validated strictly.

A run config has four sections::

    stage: geometry            # the converter stage it trains (see `scube_sim.model.stages`)
    train: {seed: 0, epochs: 40, batch_size: 4, lr: 1.0e-4}   # TrainConfig, shared by all stages
    model: {...}               # validated by the stage's own `model_config` class
    data: {...}                # validated by the stage's own `data_config` class

Shipped configs live in `scube_sim/model/configs/<name>.yaml` and resolve by name with case and
punctuation ignored, as sensor presets do ('Geometry-Waymo' == 'geometry_waymo').
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any, Literal

import torch
from pydantic import BaseModel, Field, PrivateAttr, create_model, field_validator, model_validator

from ..config import ConfigError, StrictModel, load_yaml, normalize_name, validate_model
from ..cpus import share_threads


class TrainConfig(StrictModel):
    """The optimisation loop, the same for every stage.

    The run is `epochs` passes over the training set or `steps` optimiser steps (exactly one of
    the two). `batch_size` is the global batch: with N ranks each rank takes batch_size / N
    samples of every batch. An epoch is len(train set) // batch_size batches (the remainder is
    left out of that epoch; the order is reshuffled every epoch).
    """

    seed: int = Field(default=0, ge=0)
    epochs: int | None = Field(default=None, ge=1)
    steps: int | None = Field(default=None, ge=1)
    batch_size: int = Field(default=1, ge=1)
    lr: float = Field(default=1e-4, gt=0)
    # The learning rate at each step: `constant`, or a linear warm-up over `warmup_steps` then a
    # cosine decay to lr * lr_final_ratio at the run's last step (a function of the step alone, so a
    # resumed run follows the same curve; extending `steps` on resume stretches what is left of it).
    lr_schedule: Literal["constant", "cosine"] = "constant"
    warmup_steps: int = Field(default=0, ge=0)
    lr_final_ratio: float = Field(default=0.0, ge=0, le=1)
    # Adam as in the SCube paper: beta1 = 0.9, beta2 = 0.999.
    betas: tuple[float, float] = (0.9, 0.999)
    eps: float = Field(default=1e-8, gt=0)
    weight_decay: float = Field(default=0.0, ge=0)  # Adam's L2 term (torch.optim.Adam)
    grad_clip: float | None = Field(default=None, gt=0)  # max global L2 norm of the gradient
    checkpoint_every: int | None = Field(default=None, ge=1)  # steps; a checkpoint also ends each epoch
    validate_every: int = Field(default=1, ge=1)  # epochs; the last step is always validated
    keep_best: bool = True  # also keep best.pt, the checkpoint with the best primary metric
    num_workers: int = Field(default=0, ge=0)  # DataLoader worker processes per rank
    ranks: int = Field(default=1, ge=1)  # processes (torch.distributed, gloo backend)
    threads: int | None = Field(default=None, ge=1)  # torch intra-op threads per rank (None: torch's default)
    deterministic: bool = True  # torch.use_deterministic_algorithms during the run
    # Warm start: the model's weights from this checkpoint (a path or a shipped checkpoint's name,
    # the same stage and model config) at step 0, with a fresh optimiser and schedule (a
    # fine-tune: for example a learning-rate decay after a run at a constant rate flattened).
    init: str | None = None

    @field_validator("betas")
    @classmethod
    def _betas_in_range(cls, v):
        if not all(0.0 <= b < 1.0 for b in v):
            raise ValueError(f"each beta must lie in [0, 1), got {list(v)}")
        return v

    @model_validator(mode="after")
    def _length(self):
        if (self.epochs is None) == (self.steps is None):
            raise ValueError("give exactly one of 'epochs' and 'steps'")
        return self


class RunConfig(StrictModel):
    """One run: the stage's name, the shared loop and the stage's own `model` and `data` sections
    (plain mappings here; `stage_configs` validates them with the stage's classes)."""

    stage: str = Field(min_length=1)
    train: TrainConfig
    model: dict[str, Any] = Field(default_factory=dict)
    data: dict[str, Any] = Field(default_factory=dict)
    _source: str = PrivateAttr(default="<dict>")

    @property
    def source(self) -> str:
        """The file this config came from ('<dict>' when built in code), for error messages."""
        return self._source


def configs_dir() -> Path:
    """The folder of shipped training configs (inside the package, so it ships in the wheel)."""
    return Path(__file__).resolve().parent / "configs"


def config_paths() -> dict[str, Path]:
    """Normalised name -> YAML path of every shipped config."""
    return {normalize_name(p.stem): p for p in sorted(configs_dir().glob("*.yaml"))}


def config_names() -> list[str]:
    """The shipped configs' names (file stems), sorted."""
    return sorted(p.stem for p in config_paths().values())


def config_from_dict(data: object, source: str = "<dict>") -> RunConfig:
    """Validate a mapping; ConfigError names `source` and the key path."""
    cfg = validate_model(RunConfig, data, source, "training settings")
    cfg._source = source
    return cfg


def load_config(name_or_path: str | Path) -> RunConfig:
    """A shipped config by name (case and punctuation ignored) or a YAML path."""
    s = str(name_or_path)
    p = Path(s)
    if p.suffix.lower() in (".yaml", ".yml") or p.is_file():
        return config_from_dict(load_yaml(p), str(p))
    shipped = config_paths()
    key = normalize_name(s)
    if key in shipped:
        return config_from_dict(load_yaml(shipped[key]), str(shipped[key]))
    names = ", ".join(config_names()) or "(none)"
    raise ConfigError(f"unknown training config {s!r}: not a file and not a shipped config; shipped: {names}")


def stage_configs(run: RunConfig, model_cls: type[BaseModel], data_cls: type[BaseModel]) -> tuple[BaseModel, BaseModel]:
    """The run's `model` and `data` sections validated by a stage's classes; a ConfigError names
    the file and the key path (`run.yaml: model.width: unknown key`)."""
    sections = create_model("StageSections", __base__=StrictModel, model=(model_cls, ...), data=(data_cls, ...))
    out = validate_model(sections, {"model": run.model, "data": run.data}, run.source, "stage settings")
    return out.model, out.data


def resolved_config(run: RunConfig, model_cfg: BaseModel, data_cfg: BaseModel) -> dict:
    """The full config with every default filled in, as plain JSON values (stored in checkpoints)."""
    return {"stage": run.stage, "train": run.train.model_dump(mode="json"),
            "model": model_cfg.model_dump(mode="json"), "data": data_cfg.model_dump(mode="json")}


@contextlib.contextmanager
def torch_settings(tc: TrainConfig, world: int):
    """Threads and deterministic algorithms for the run, restored afterwards (the caller's process
    keeps its own settings)."""
    threads, det, warn = (torch.get_num_threads(), torch.are_deterministic_algorithms_enabled(),
                          torch.is_deterministic_algorithms_warn_only_enabled())
    if tc.threads is not None:
        torch.set_num_threads(tc.threads)
    elif world > 1:  # ranks share the cores
        torch.set_num_threads(share_threads(world))
    # Only on a change: the call also sets torch._inductor's flag, importing it (seconds) if needed.
    if (det, warn) != (tc.deterministic, False):
        torch.use_deterministic_algorithms(tc.deterministic)
    try:
        yield
    finally:
        if (det, warn) != (tc.deterministic, False):
            torch.use_deterministic_algorithms(det, warn_only=warn)
        torch.set_num_threads(threads)


