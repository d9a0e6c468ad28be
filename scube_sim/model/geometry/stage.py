"""Stages `geometry-vae` and `geometry`: the structure VAE and the conditional model as the
trainer sees them (datasets, losses, metrics), and the frozen VAE a conditional model is built
with (`frozen_vae`).
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.utils.data import Dataset

from ...errors import InputError
from ...labels import NUM_LABELS
from ...memory import peak_mb, reset_peak, rss_mb
from ..checkpoint import CheckpointError, load_model, resolve_checkpoint
from ..stages import Stage, register_stage
from .data import GeometryDataConfig, GeometryDataset, dense_target
from .dense_nets import StructureVAE, VAEConfig, prune_decode
from .metrics import geometry_sample_metrics, summarise, visible_voxels
from .net import GeometryModelConfig, GeometryNet, GeometryVAEModelConfig
from .sparse_nets import SparseStructureVAE, decoded_voxels


def grid_metrics(pred: list[tuple[torch.Tensor, torch.Tensor]], items: list[dict], split: bool) -> dict[str, float]:
    """`geometry_metrics.summarise` of predicted against ground-truth voxels: IoU (mean over
    samples), mIoU (semantic scene completion convention, over the summed confusion), voxel Chamfer
    quantiles; with `split`, each also over the voxels visible / invisible from the item's input
    cameras (`visible_voxels`, applied to both grids alike)."""
    samples = []
    for (ijk, lab), item in zip(pred, items):
        gt_ijk = item["gt_ijk"]
        if split:
            grid = item["gt_grid"]

            def seen(g):
                return visible_voxels(g, grid.voxel_size, grid.origin, item["intrinsics"], item["distortion"],
                                      item["cam_to_chunk"], item["depth"], item["image_size"])

            pv, gv = seen(ijk), seen(gt_ijk)
        else:
            pv, gv = np.ones(len(ijk), bool), np.ones(len(gt_ijk), bool)
        samples.append(geometry_sample_metrics(ijk, lab, gt_ijk, item["gt_labels"], NUM_LABELS, pv, gv))
    out = summarise(samples)
    if not split:
        out = {k: v for k, v in out.items() if "visible" not in k}
    return out


class GeometryVAEStage(Stage):
    name = "geometry-vae"
    model_config = GeometryVAEModelConfig
    data_config = GeometryDataConfig
    primary_metric = "iou"
    higher_is_better = True

    def build_model(self, model_cfg: GeometryVAEModelConfig) -> nn.Module:
        net = nn.Module()
        net.level = model_cfg.level
        net.vae = SparseStructureVAE(model_cfg.vae) if model_cfg.level == "fine" else StructureVAE(model_cfg.vae)
        return net

    def dataset(self, data_dir: Path, data_cfg: GeometryDataConfig, split: str, seed: int) -> Dataset:
        return _VoxelsOnly(GeometryDataset(Path(data_dir), split, data_cfg, seed))

    def collate(self, samples: list) -> list:
        return list(samples)

    def loss(self, model: nn.Module, batch: list) -> tuple[torch.Tensor, dict[str, float]]:
        _check_vae_level(model, batch)
        if model.level == "fine":
            coords, labels = _sparse_batch(batch)
            return model.vae.loss(coords, labels, len(batch))
        occ, lab = _dense_batch(batch)
        return model.vae.loss(occ, lab)

    def evaluate(self, model: nn.Module, batches: Iterable[list]) -> dict[str, float]:
        preds, items = [], []
        for batch in batches:
            _check_vae_level(model, batch)
            if model.level == "fine":
                coords, labels = _sparse_batch(batch)
                mu, _ = model.vae.encode(coords, labels, len(batch))
                c, lab = decoded_voxels(model.vae.decode(mu))
                preds += [(c[c[:, 0] == b, 1:], lab[c[:, 0] == b]) for b in range(len(batch))]
            else:
                occ, lab = _dense_batch(batch)
                _, _, occ_levels, occ_final, logits = model.vae(occ, lab, sample=False)
                ijks, labs = prune_decode(occ_levels, occ_final, logits)
                preds += list(zip(ijks, labs))
            items += batch
        return grid_metrics(preds, items, split=False)


def calibrate_latent_std(model: nn.Module, dataset: Dataset, limit: int | None = None) -> float:
    """Set a `geometry-vae` model's latent_std to its final encoder's RMS of the posterior means
    over `dataset` (a `geometry-vae` stage dataset; the first `limit` items), instead of the
    running RMS over training that `track_latent_rms` leaves. Returns the new value."""
    vae = model.vae
    was = vae.training
    vae.eval()
    sq, n = 0.0, 0
    with torch.no_grad():
        for i in range(len(dataset) if limit is None else min(limit, len(dataset))):
            batch = [dataset[i]]
            if model.level == "fine":
                coords, labels = _sparse_batch(batch)
                mu = vae.encode(coords, labels, 1)[0].feats
            else:
                occ, lab = _dense_batch(batch)
                mu = vae.encode(occ, lab)[0]
            sq += float(mu.double().pow(2).mean())
            n += 1
    vae.train(was)
    if n:
        vae._latent_sq.fill_(sq)
        vae._latent_n.fill_(n)
        vae.latent_std.fill_(max((sq / n) ** 0.5, 1e-3))
    return float(vae.latent_std)


def _check_vae_level(model: nn.Module, batch: list[dict]) -> None:
    for it in batch:
        if it["level"] != model.level:
            raise InputError(f"{it['sample']}: a {it['level']} level item for the {model.level} level's VAE "
                             f"(data.level and model.level must agree)")


class _VoxelsOnly(Dataset):
    """The VAE reads the ground-truth grid alone."""

    def __init__(self, ds: GeometryDataset):
        self.ds = ds

    def __len__(self):
        return len(self.ds)

    def set_epoch(self, epoch: int) -> None:
        self.ds.set_epoch(epoch)

    def __getitem__(self, index: int) -> dict:
        item = self.ds[index]
        return {k: item[k] for k in ("gt_ijk", "gt_labels", "gt_visible", "sample", "level", "gt_grid")}


def _dense_batch(batch: list[dict]) -> tuple[torch.Tensor, torch.Tensor]:
    occ, lab = zip(*(dense_target(it["gt_ijk"], it["gt_labels"], it["gt_grid"].dims) for it in batch))
    return torch.stack(occ), torch.stack(lab)


def _sparse_batch(batch: list[dict]) -> tuple[torch.Tensor, torch.Tensor]:
    """Fine voxels of a batch: ((N, 4) [b, i, j, k], (N,) labels)."""
    coords = torch.cat([torch.cat([torch.full((len(it["gt_ijk"]), 1), b, dtype=torch.int64), it["gt_ijk"]], 1)
                        for b, it in enumerate(batch)])
    return coords, torch.cat([it["gt_labels"] for it in batch])


class GeometryStage(Stage):
    name = "geometry"
    model_config = GeometryModelConfig
    data_config = GeometryDataConfig
    primary_metric = "iou"
    higher_is_better = True

    def build_model(self, model_cfg: GeometryModelConfig) -> nn.Module:
        return GeometryNet(model_cfg, load_vae=lambda name: frozen_vae(name, model_cfg))

    def dataset(self, data_dir: Path, data_cfg: GeometryDataConfig, split: str, seed: int) -> Dataset:
        return GeometryDataset(Path(data_dir), split, data_cfg, seed)

    def collate(self, samples: list) -> list:
        return list(samples)

    def loss(self, model: nn.Module, batch: list) -> tuple[torch.Tensor, dict[str, float]]:
        total, logs = 0.0, {}
        for item in batch:
            loss, lg = model.loss(item)
            total = total + loss
            for k, v in lg.items():
                logs[k] = logs.get(k, 0.0) + v / len(batch)
        return total / len(batch), logs

    def evaluate(self, model: nn.Module, batches: Iterable[list]) -> dict[str, float]:
        preds, items, seconds, peaks = [], [], [], []
        for batch in batches:
            for item in batch:
                base = rss_mb() if reset_peak() else float("nan")
                t0 = time.perf_counter()
                preds.append(model.predict(item, seed=sample_seed(item)))
                seconds.append(time.perf_counter() - t0)
                peaks.append(peak_mb() - base)
                items.append(item)
        out = grid_metrics(preds, items, split=True)
        # the conversion's cost per sample: wall seconds and peak resident memory above the start
        out["seconds_per_sample"] = float(np.mean(seconds)) if seconds else 0.0
        out["peak_mb_per_sample"] = float(np.max(peaks)) if peaks else 0.0
        return out


def sample_seed(item: dict) -> int:
    """The sampler's seed of an item: from its sample name, so the same input gives the same grid."""
    return zlib.crc32(str(item.get("sample", "")).encode())


register_stage(GeometryVAEStage())


register_stage(GeometryStage())


def frozen_vae(name: str, cfg: GeometryModelConfig) -> nn.Module | None:
    """The structure VAE of the `geometry-vae` checkpoint `name` (a path or a shipped name) for
    the conditional model `cfg`, or None where no such checkpoint exists (a checkpoint of the
    conditional model holds the VAE's weights). Its architecture and level must be cfg's."""
    try:
        path = resolve_checkpoint(name)
    except CheckpointError:
        return None
    vae_net, run = load_model("geometry-vae", path)
    got = VAEConfig(**run.model.get("vae", {}))
    level = run.model.get("level", "coarse")
    if got != cfg.vae or level != cfg.level:
        raise InputError(f"vae_checkpoint {name}: its VAE is the {level} level's {got.model_dump()}, the "
                         f"config's is the {cfg.level} level's {cfg.vae.model_dump()}")
    return vae_net.vae
