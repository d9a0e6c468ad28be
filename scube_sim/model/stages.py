"""The converter's learned stages, as the trainer sees them, and their registry.

A stage (geometry, appearance) subclasses `Stage` and registers an instance when its module is
imported::

    class GeometryStage(Stage):
        name = "geometry"
        model_config = GeometryModelConfig      # pydantic classes for the run config's
        data_config = GeometryDataConfig        # `model:` and `data:` sections
        primary_metric = "iou"
        higher_is_better = True
        ...

    register_stage(GeometryStage())

and adds its module to `STAGE_MODULES`, so `get_stage("geometry")` finds it without the caller
importing it first.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections.abc import Iterable
from pathlib import Path
from typing import Any, ClassVar

import torch
from pydantic import BaseModel
from torch import nn
from torch.utils.data import Dataset, default_collate

from ..config import normalize_name
from ..errors import NotFoundError, ScubeSimError

# Modules that register a stage when imported (each stage folder's `stage` module).
STAGE_MODULES: list[str] = ["scube_sim.model.semantics.stage", "scube_sim.model.appearance.stage",
                             "scube_sim.model.geometry.stage", "scube_sim.model.completion.stage"]


class StageError(ScubeSimError):
    """A stage that breaks its contract (e.g. `evaluate` without the primary metric)."""


class Stage(ABC):
    """What the trainer needs from a learned stage.

    Determinism contract: a dataset item must be a function of its index only (seed any
    augmentation from the index and the `seed` argument), and `loss` must be the MEAN over the
    samples of the batch, so that the average of the ranks' equal-sized shard gradients is the
    full-batch gradient.
    """

    name: ClassVar[str]
    model_config: ClassVar[type[BaseModel]]  # validates the run config's `model:` section
    data_config: ClassVar[type[BaseModel]]  # validates the run config's `data:` section
    primary_metric: ClassVar[str]  # key of `evaluate`'s result that picks best.pt
    higher_is_better: ClassVar[bool]
    splits: ClassVar[tuple[str, ...]] = ("train", "val", "test")
    # the trainer calls the train dataset's `set_epoch(epoch)` before each epoch's loader, so that
    # its augmentation draws anew each epoch (opt-in: the shipped stages' runs replay without it)
    epoch_aware: ClassVar[bool] = False

    @abstractmethod
    def build_model(self, model_cfg: BaseModel) -> nn.Module:
        """A freshly initialised network (the trainer seeds torch first, so init is reproducible)."""

    @abstractmethod
    def dataset(self, data_dir: Path, data_cfg: BaseModel, split: str, seed: int) -> Dataset:
        """The samples of one split (one of `splits`) of the data folder."""

    def datasets(self, data_dir: Path, data_cfg: BaseModel, seed: int) -> tuple[Dataset, Dataset]:
        """(train, val) datasets."""
        return self.dataset(data_dir, data_cfg, "train", seed), self.dataset(data_dir, data_cfg, "val", seed)

    def collate(self, samples: list[Any]) -> Any:
        """Samples -> one batch (default: torch's default_collate, which stacks tensors)."""
        return default_collate(samples)

    @abstractmethod
    def loss(self, model: nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, float]]:
        """(scalar loss, the mean over the batch's samples; extra terms to log as plain floats)."""

    @abstractmethod
    def evaluate(self, model: nn.Module, batches: Iterable[Any]) -> dict[str, float]:
        """Metrics over all `batches` (the whole split, in order); must contain `primary_metric`.
        Called in eval mode under torch.no_grad()."""


_REGISTRY: dict[str, Stage] = {}


def _class_path(obj: object) -> str:
    return f"{type(obj).__module__}.{type(obj).__qualname__}"


def register_stage(stage: Stage) -> Stage:
    """Add a stage under its (normalised) name. Registering the same class again replaces it
    (a re-imported module); another class under a taken name is an error."""
    if not isinstance(stage, Stage):
        raise TypeError(f"register_stage: expected a Stage instance, got {type(stage).__name__}")
    key = normalize_name(stage.name)
    old = _REGISTRY.get(key)
    if old is not None and _class_path(old) != _class_path(stage):
        raise StageError(f"stage {stage.name!r} is already registered by {_class_path(old)}")
    _REGISTRY[key] = stage
    return stage


def _import_stage_modules() -> None:
    for module in STAGE_MODULES:
        importlib.import_module(module)


def stage_names() -> list[str]:
    """Names of every registered stage, sorted."""
    _import_stage_modules()
    return sorted(s.name for s in _REGISTRY.values())


def get_stage(name: str) -> Stage:
    """The registered stage called `name` (case and punctuation ignored)."""
    _import_stage_modules()
    stage = _REGISTRY.get(normalize_name(name))
    if stage is None:
        known = ", ".join(stage_names()) or "(none)"
        raise NotFoundError(f"unknown stage {name!r}; known stages: {known}")
    return stage
