"""Stage `appearance` as the trainer sees it: model, dataset, loss and metrics."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.utils.data import Dataset

from ..stages import Stage, register_stage
from .data import AppearanceDataConfig, AppearanceDataset
from .losses import evaluate_item, view_losses
from .net import AppearanceModelConfig, AppearanceNet


class AppearanceStage(Stage):
    name = "appearance"
    model_config = AppearanceModelConfig
    data_config = AppearanceDataConfig
    primary_metric = "psnr"
    higher_is_better = True

    def build_model(self, model_cfg: AppearanceModelConfig) -> nn.Module:
        return AppearanceNet(model_cfg)

    def dataset(self, data_dir: Path, data_cfg: AppearanceDataConfig, split: str, seed: int) -> Dataset:
        return AppearanceDataset(Path(data_dir), split, data_cfg, seed)

    def collate(self, samples: list) -> list:
        return list(samples)  # one sample at a time through the network: grids and rigs differ

    def loss(self, model: nn.Module, batch: list) -> tuple[torch.Tensor, dict[str, float]]:
        total, logs = 0.0, {}
        for item in batch:
            loss, lg = view_losses(model, model(item), item, item.get("loss_views"))
            total = total + loss
            for k, v in lg.items():
                logs[k] = logs.get(k, 0.0) + v / len(batch)
        return total / len(batch), logs

    def evaluate(self, model: nn.Module, batches: Iterable[list]) -> dict[str, float]:
        sums: dict[str, list[float]] = {}
        for batch in batches:
            for item in batch:
                for k, v in evaluate_item(model, item, item.get("eval_cameras", "front")).items():
                    sums.setdefault(k, []).extend(v)
        metrics = {k: float(np.mean(v)) for k, v in sums.items()}
        metrics["views_t0"] = float(len(sums.get("psnr_t0", [])))
        metrics["psnr"] = metrics.get("psnr_t0", 0.0)
        return metrics


register_stage(AppearanceStage())


