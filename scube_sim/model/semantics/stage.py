"""Stage `voxel-semantics` as the trainer sees it, and its metrics (mean IoU, voxel accuracy)."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.data import Dataset

from ...labels import NUM_LABELS
from ..nn.label_metrics import semantic_metrics
from ..stages import Stage, register_stage
from .data import VoxelGridDataset, VoxelSemanticsData, collate_grids
from .net import VoxelSemanticsModel, VoxelSemanticsNet


class VoxelSemanticsStage(Stage):
    name = "voxel-semantics"
    model_config = VoxelSemanticsModel
    data_config = VoxelSemanticsData
    primary_metric = "miou"
    higher_is_better = True

    def build_model(self, model_cfg: VoxelSemanticsModel) -> nn.Module:
        return VoxelSemanticsNet(model_cfg)

    def dataset(self, data_dir: Path, data_cfg: VoxelSemanticsData, split: str, seed: int) -> Dataset:
        return VoxelGridDataset(Path(data_dir), split, data_cfg)

    def collate(self, samples: list) -> dict:
        return collate_grids(samples)

    def loss(self, model: nn.Module, batch: dict) -> tuple[torch.Tensor, dict[str, float]]:
        logits, labels, b = model(batch), batch["labels"], batch["coords"][:, 0]
        per_voxel = F.cross_entropy(logits, labels, reduction="none")
        n = torch.bincount(b, minlength=batch["batch_size"]).clamp_min(1).to(per_voxel.dtype)
        per_sample = per_voxel.new_zeros(batch["batch_size"]).index_add(0, b, per_voxel) / n
        acc = float((logits.argmax(1) == labels).float().mean()) if len(labels) else 0.0
        return per_sample.mean(), {"accuracy": acc}

    def evaluate(self, model: nn.Module, batches: Iterable[dict]) -> dict[str, float]:
        conf = torch.zeros(NUM_LABELS, NUM_LABELS, dtype=torch.int64)
        for batch in batches:
            logits, labels = model(batch), batch["labels"]
            conf += torch.bincount(labels * NUM_LABELS + logits.argmax(1), minlength=NUM_LABELS ** 2
                                   ).reshape(NUM_LABELS, NUM_LABELS)
        return semantic_metrics(conf)


register_stage(VoxelSemanticsStage())


