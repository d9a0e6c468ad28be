"""Stage `completion` as the trainer sees it: the completion network (`net`) on cached worlds
evidence (`data`), its loss (occupancy BCE + label cross-entropy on occupied cells) and metrics
(IoU, mIoU, and IoU over the cells the evidence holds nothing in)."""

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
from .data import CompletionData, CompletionDataset
from .features import FEATURES
from .net import CompletionModel, CompletionNet

_OCCUPIED, _FREE = FEATURES.index("occupied"), FEATURES.index("free_images")


class CompletionStage(Stage):
    name = "completion"
    model_config = CompletionModel
    data_config = CompletionData
    primary_metric = "iou"
    higher_is_better = True
    epoch_aware = True

    def build_model(self, model_cfg: CompletionModel) -> nn.Module:
        return CompletionNet(model_cfg)

    def dataset(self, data_dir: Path, data_cfg: CompletionData, split: str, seed: int) -> Dataset:
        return CompletionDataset(Path(data_dir), split, data_cfg, seed)

    def loss(self, model: nn.Module, batch: dict) -> tuple[torch.Tensor, dict[str, float]]:
        occ_logit, lab_logit, sub_logit = model.forward_with_subcells(batch["features"])
        occ, labels = batch["occupancy"], batch["labels"]
        label_weight, pos_weight = model.cfg.label_weight, model.cfg.pos_weight
        bce = F.binary_cross_entropy_with_logits(occ_logit, occ, pos_weight=torch.tensor(pos_weight),
                                                 reduction="none").flatten(1).mean(1)
        ce = F.cross_entropy(lab_logit, labels.clamp_min(0), reduction="none")
        mask = (labels >= 0).float()
        ce = (ce * mask).flatten(1).sum(1) / mask.flatten(1).sum(1).clamp_min(1)
        loss = (bce + label_weight * ce).mean()
        logs = {"bce": float(bce.detach().mean()), "ce": float(ce.detach().mean())}
        if sub_logit is not None:
            sub_bce = _subcell_bce(sub_logit, batch, model.cfg.subcells)
            loss = loss + model.cfg.subcell_weight * sub_bce.mean()
            logs["subcell_bce"] = float(sub_bce.detach().mean())
        return loss, logs

    def evaluate(self, model: nn.Module, batches: Iterable[dict]) -> dict[str, float]:
        tp = fp = fn = 0
        utp = ufp = ufn = 0
        conf = torch.zeros(NUM_LABELS, NUM_LABELS, dtype=torch.int64)
        stp = sfp = sfn = 0
        for batch in batches:
            if isinstance(model, CompletionNet):
                occ_logit, lab_logit, sub_logit = model.forward_with_subcells(batch["features"])
            else:
                (occ_logit, lab_logit), sub_logit = model(batch["features"]), None
            pred, gt = occ_logit > 0, batch["occupancy"] > 0.5
            if sub_logit is not None:  # where in the truth's occupied cells
                s = model.cfg.subcells
                inside = _up(gt, s)
                sp_, sg = (sub_logit > 0) & inside, _subcell_truth(batch, s, gt.shape) & inside
                stp += int((sp_ & sg).sum())
                sfp += int((sp_ & ~sg).sum())
                sfn += int((~sp_ & sg).sum())
            # cells the evidence holds nothing in and no camera saw through: the completion's own
            unseen = (batch["features"][:, _OCCUPIED] == 0) & (batch["features"][:, _FREE] == 0)
            tp += int((pred & gt).sum())
            fp += int((pred & ~gt).sum())
            fn += int((~pred & gt).sum())
            utp += int((pred & gt & unseen).sum())
            ufp += int((pred & ~gt & unseen).sum())
            ufn += int((~pred & gt & unseen).sum())
            both = pred & gt
            t, p = batch["labels"][both], lab_logit.argmax(1)[both]
            conf += torch.bincount(t * NUM_LABELS + p, minlength=NUM_LABELS ** 2).reshape(NUM_LABELS, NUM_LABELS)
        sem = semantic_metrics(conf)
        out = {"iou": tp / max(tp + fp + fn, 1), "iou_unseen": utp / max(utp + ufp + ufn, 1),
               "precision": tp / max(tp + fp, 1), "recall": tp / max(tp + fn, 1),
               "miou": sem["miou"], "label_accuracy": sem["accuracy"]}
        if stp + sfp + sfn:
            out["subcell_iou"] = stp / (stp + sfp + sfn)
        return out


def _up(cells: torch.Tensor, s: int) -> torch.Tensor:
    """(B, X, Y, Z) -> (B, sX, sY, sZ): each cell's value in its s x s x s sub-cells."""
    return cells.repeat_interleave(s, 1).repeat_interleave(s, 2).repeat_interleave(s, 3)


def _subcell_truth(batch: dict, s: int, cells: torch.Size) -> torch.Tensor:
    """(B, sX, sY, sZ) bool: the sub-cells the truth occupies (the stored voxels pooled to them)."""
    fine = batch["fine_occupancy"]
    f = fine.shape[1] // cells[1]
    if f % s or fine.shape[1] != f * cells[1]:
        raise ValueError(f"completion: {s} sub-cells per cell side need the truth at a divisor of the cell; it is "
                         f"stored at 1/{fine.shape[1] / cells[1]:g} of it")
    r = f // s
    if r == 1:
        return fine
    return F.max_pool3d(fine[:, None].float(), r)[:, 0] > 0.5


def _subcell_bce(sub_logit: torch.Tensor, batch: dict, s: int) -> torch.Tensor:
    """(B,) the sub-cells' BCE, averaged over the sub-cells of the truth's occupied cells."""
    occ = batch["occupancy"] > 0.5
    inside = _up(occ, s).float()
    target = _subcell_truth(batch, s, occ.shape).float()
    bce = F.binary_cross_entropy_with_logits(sub_logit, target, reduction="none")
    return (bce * inside).flatten(1).sum(1) / inside.flatten(1).sum(1).clamp_min(1)


register_stage(CompletionStage())
