"""Metrics of predicted voxel labels against the truth, from a confusion matrix: the stages that
predict labels (semantics, completion) and the converter's end-to-end evaluation share them."""

from __future__ import annotations

import torch

from ...labels import LABEL_NAMES

__all__ = ["semantic_metrics"]


def semantic_metrics(conf: torch.Tensor) -> dict[str, float]:
    """conf[true, predicted] counts -> {'miou': mean IoU over labels that occur in either,
    'accuracy', and 'iou_<label>' per such label}."""
    tp = conf.diag().double()
    union = conf.sum(0).double() + conf.sum(1).double() - tp
    present = union > 0
    iou = torch.where(present, tp / union.clamp_min(1), torch.zeros_like(tp))
    out = {"miou": float(iou[present].mean()) if bool(present.any()) else 0.0,
           "accuracy": float(tp.sum() / conf.sum().clamp_min(1))}
    for i in torch.nonzero(present).squeeze(1).tolist():
        out[f"iou_{LABEL_NAMES[i]}"] = float(iou[i])
    return out
