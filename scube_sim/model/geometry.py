"""Stages `geometry-vae` and `geometry` (paper section 3.1, appendix A-C): posed camera images to a
semantic voxel grid, through a structure VAE and an image-conditioned latent diffusion (XCube).

One level of the hierarchy at a time (`level: coarse | fine` in the data config; this module
holds the dense coarse level, whose box is small enough to be dense on a CPU: 128 x 128 x 32 cells
of 0.8 m, 0.5 M cells, of which ~9 % are occupied).

**Structure VAE** (`StructureVAE`): the ground-truth grid (occupancy + one-hot label per voxel) is
encoded by strided 3D convolutions to a latent of `latent_channels` at 2^L times the voxel size
(L = len(widths); the cpu profile: 3.2 m, a 32 x 32 x 8 latent). The decoder goes back up one
level at a time and predicts occupancy at every level; the final level's 8 children of each voxel
come from a per-parent linear head (occupancy and label logits), and a voxel exists only where
it and all its ancestors are predicted occupied (subdivide and prune).

**Conditional latent diffusion** (`GeometryNet`, mode `diffusion`): an image encoder
(`image_encoder`) and a conv head give each feature pixel C features and a softmax over D depth
bins; Eq. 1 lifts them into the level's box (`lifting`), strided convolutions bring them to the
latent's resolution, and a 3D U-Net with a timestep embedding predicts v from the noisy latent
concatenated with that condition (`diffusion`: 1000 linear steps, v-parameterisation, DDIM at
inference). Loss: diffusion + depth_weight * focal(depth bins) (the paper: weight 1), with the
ground-truth depth of the worlds' depth maps. Mode `predictor`: the same network, no sampling: it
sees a zero latent at the last step and regresses the clean latent in one pass (the fast end of
the trade, and the baseline the diffusion has to beat).

Frames: chunk (x forward, y left, z up, metres; `CHUNK_CORNER`); voxel (i, j, k) of the level's
box spans region[:3] + [ijk, ijk + 1) * voxel_size.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field, model_validator
from torch import nn
from torch.utils.data import Dataset

from ..config import StrictModel
from ..errors import InputError
from ..labels import LABEL_NAMES
from ..worlds.groundtruth import CHUNK_CORNER, CHUNK_SIZE
from .augment import AugmentConfig, CameraSelection
from .data import DataConfig, WorldsTorchDataset
from .diffusion import NoiseSchedule, ddim_sample
from .geometry_nets import Denoiser3d, StructureVAE, VAEConfig, prune_decode
from .geometry_metrics import geometry_sample_metrics, summarise, visible_voxels
from .image_encoder import ImageEncoderConfig, build_image_encoder
from .lifting import LiftGrid, depth_bin_centres, depth_bin_edges, depth_focal_loss, depth_to_bin, \
    feature_intrinsics, frustum_points, lift
from .stages import Stage, register_stage

NUM_LABELS = len(LABEL_NAMES)
# The cpu profile's box: the whole 102.4 m chunk in x and y, the lowest 25.6 m in z.
DEFAULT_REGION = (float(CHUNK_CORNER[0]), float(CHUNK_CORNER[1]), float(CHUNK_CORNER[2]),
                  float(CHUNK_CORNER[0] + CHUNK_SIZE), float(CHUNK_CORNER[1] + CHUNK_SIZE),
                  float(CHUNK_CORNER[2] + 25.6))


# ---------------------------------------------------------------------------- configs
class GeometryDataConfig(StrictModel):
    """The level's grid: `voxel_size` metres (the stored coarse grid coarsened by an integer
    factor; the cpu profile's data stores 0.8 m) over `region` (x_min, y_min, z_min, x_max, y_max,
    z_max, chunk frame metres, a whole number of voxels from CHUNK_CORNER); the input images at
    `image_scale` of the stored ones; in training, rig randomisation and photometric
    augmentation of the inputs."""

    level: str = Field(default="coarse", pattern="^coarse$")
    voxel_size: float = Field(default=0.8, gt=0)
    region: tuple[float, float, float, float, float, float] = DEFAULT_REGION
    image_scale: float = Field(default=0.67, gt=0, le=1)
    augment: AugmentConfig = Field(default_factory=AugmentConfig)
    cameras: CameraSelection = Field(default_factory=CameraSelection)

    @model_validator(mode="after")
    def _whole_voxels(self):
        lo, hi = np.array(self.region[:3]), np.array(self.region[3:])
        for name, v in (("region's corner", (lo - CHUNK_CORNER) / self.voxel_size), ("region's size", (hi - lo) / self.voxel_size)):
            if np.any(np.abs(v - np.round(v)) > 1e-6) or (name == "region's size" and np.any(np.round(v) < 1)):
                raise ValueError(f"{name} must be a positive whole number of {self.voxel_size} m voxels "
                                 f"(from CHUNK_CORNER {CHUNK_CORNER.tolist()}), got region {list(self.region)}")
        return self

    def grid(self) -> LiftGrid:
        lo, hi = np.array(self.region[:3]), np.array(self.region[3:])
        dims = np.round((hi - lo) / self.voxel_size).astype(int)
        return LiftGrid(tuple(float(v) for v in lo), float(self.voxel_size), tuple(int(d) for d in dims))


class GeometryVAEModelConfig(StrictModel):
    vae: VAEConfig = Field(default_factory=VAEConfig)


class GeometryModelConfig(StrictModel):
    """The conditional model of one level. mode: diffusion | predictor. vae_checkpoint: the
    trained `geometry-vae` run of this level (path or shipped name), frozen; `vae` must be its
    architecture. encoder: the image backbone; feature_channels C and depth_bins D of the conv
    head (paper: 32, 64; bins from near to far metres); lifting: depth (Eq. 1) | broadcast (the
    ablation); depth_weight: lambda of the focal depth loss (paper 1). Denoiser: a 3D U-Net of
    `widths` (one level each, halving between) with `blocks` residual blocks per level,
    condition channels `cond_channels`. Diffusion: `train_steps` linear steps from beta_start to
    beta_end, `sample_steps` DDIM steps at inference (validation uses them too)."""

    mode: str = Field(default="diffusion", pattern="^(diffusion|predictor)$")
    vae_checkpoint: str | None = None
    vae: VAEConfig = Field(default_factory=VAEConfig)
    encoder: ImageEncoderConfig = Field(default_factory=ImageEncoderConfig)
    feature_channels: int = Field(default=32, ge=1)
    depth_bins: int = Field(default=64, ge=2)
    near: float = Field(default=0.1, gt=0)
    far: float = Field(default=90.0, gt=0)
    lifting: str = Field(default="depth", pattern="^(depth|broadcast)$")
    depth_weight: float = Field(default=1.0, ge=0)
    cond_channels: int = Field(default=64, ge=1)
    widths: tuple[int, ...] = Field(default=(64, 128, 256), min_length=1, max_length=5)
    blocks: int = Field(default=2, ge=1)
    groups: int = Field(default=8, ge=1)
    attention_levels: tuple[int, ...] = ()  # U-Net levels (0: the latent's resolution) with self-attention
    heads: int = Field(default=8, ge=1)
    train_steps: int = Field(default=1000, ge=1)
    beta_start: float = Field(default=1e-4, gt=0)
    beta_end: float = Field(default=2e-2, gt=0)
    sample_steps: int = Field(default=10, ge=1)

    @model_validator(mode="after")
    def _check(self):
        if self.far <= self.near:
            raise ValueError(f"far ({self.far}) must exceed near ({self.near})")
        if self.sample_steps > self.train_steps:
            raise ValueError(f"sample_steps ({self.sample_steps}) cannot exceed train_steps ({self.train_steps})")
        return self


# ---------------------------------------------------------------------------- data
class GeometryDataset(Dataset):
    """Worlds samples as the geometry stage reads them: the `WorldsTorchDataset` item (images at
    `image_scale`, cameras, depth, valid) plus ``gt_ijk`` (V, 3) int64 the level's ground-truth
    voxels inside the region (relative to the region's corner), ``gt_labels`` (V,) int64,
    ``gt_visible`` (V,) bool. Training items keep the cameras `cameras` picks and augment the
    input images (seeded by seed, epoch and index)."""

    def __init__(self, root: Path, split: str, cfg: GeometryDataConfig, seed: int = 0):
        self.cfg = cfg
        self.grid = cfg.grid()
        train = split == "train"
        self.base = WorldsTorchDataset(root, split=split, train=train,
                                       config=DataConfig(image_scale=cfg.image_scale, seed=seed,
                                                         augment=cfg.augment, cameras=cfg.cameras))

    def __len__(self) -> int:
        return len(self.base)

    def set_epoch(self, epoch: int) -> None:
        self.base.set_epoch(epoch)

    def __getitem__(self, index: int) -> dict:
        item = self.base[index]
        stored = float(item["coarse_voxel_size"])
        ratio = self.cfg.voxel_size / stored
        factor = int(round(ratio))
        if factor < 1 or abs(ratio - factor) > 1e-6:
            raise InputError(f"{item['sample']}: voxel_size {self.cfg.voxel_size} m is not a whole multiple of "
                             f"the stored coarse grid's {stored} m")
        gt = grid_in_box(item["coarse_ijk"], item["coarse_labels"], item["coarse_visible"], factor,
                         stored, self.grid)
        item["gt_ijk"], item["gt_labels"], item["gt_visible"] = gt
        item["lift_grid"] = self.grid
        return item


def grid_in_box(ijk: torch.Tensor, labels: torch.Tensor, visible: torch.Tensor, factor: int, stored_size: float,
                grid: LiftGrid):
    """A chunk grid (ijk from CHUNK_CORNER at `stored_size`) coarsened by `factor` (a coarse voxel
    takes the most frequent label of its children and is visible if any child is) and cut to
    `grid`'s box: (ijk (V, 3) relative to the box's corner, labels, visible), sorted by voxel."""
    ijk = ijk.to(torch.int64) // factor
    shift = torch.round((torch.tensor(grid.origin, dtype=torch.float64) - torch.as_tensor(CHUNK_CORNER))
                        / grid.voxel_size).to(torch.int64)
    rel = ijk - shift
    dims = torch.tensor(grid.dims)
    keep = ((rel >= 0) & (rel < dims)).all(1)
    rel, labels, visible = rel[keep], labels[keep].to(torch.int64), visible[keep]
    key = (rel[:, 0] * dims[1] + rel[:, 1]) * dims[2] + rel[:, 2]
    uniq, inv = torch.unique(key, return_inverse=True)
    counts = torch.zeros(len(uniq), NUM_LABELS, dtype=torch.int64).index_put_(
        (inv, labels), torch.ones_like(inv), accumulate=True)
    vis = torch.zeros(len(uniq), dtype=torch.bool).index_put_((inv,), visible, accumulate=True)
    out = torch.stack([uniq // (dims[1] * dims[2]), (uniq // dims[2]) % dims[1], uniq % dims[2]], 1)
    return out, counts.argmax(1), vis


def dense_target(ijk: torch.Tensor, labels: torch.Tensor, dims) -> tuple[torch.Tensor, torch.Tensor]:
    """(occupancy (X, Y, Z) float, labels (X, Y, Z) long, -1 where empty) of a box's voxels."""
    occ = torch.zeros(tuple(dims), dtype=torch.float32)
    lab = torch.full(tuple(dims), -1, dtype=torch.int64)
    if len(ijk):
        occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = 1.0
        lab[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = labels
    return occ, lab


# ---------------------------------------------------------------------------- conditional model
class ImageConditioner(nn.Module):
    """Images -> per-pixel features (C) and depth distributions (D) -> Eq. 1 into the level's box
    -> strided convolutions to the latent's resolution (module docstring)."""

    def __init__(self, cfg: GeometryModelConfig, latent_stride: int):
        super().__init__()
        self.cfg = cfg
        self.encoder = build_image_encoder(cfg.encoder)
        e = self.encoder.out_channels
        self.head = nn.Sequential(nn.Conv2d(e, e, 3, padding=1), nn.ReLU(inplace=True),
                                  nn.Conv2d(e, cfg.feature_channels + cfg.depth_bins, 1))
        self.register_buffer("bin_edges", depth_bin_edges(cfg.depth_bins, cfg.near, cfg.far), persistent=False)
        self.register_buffer("bin_centres", depth_bin_centres(cfg.depth_bins, cfg.near, cfg.far), persistent=False)
        levels = int(round(math.log2(latent_stride)))
        down, cin = [], cfg.feature_channels + 1  # + log(1 + frustum points per voxel)
        for i in range(levels):
            cout = cfg.cond_channels if i == levels - 1 else max(cfg.feature_channels, cfg.cond_channels // 2)
            down += [nn.Conv3d(cin, cout, 2, stride=2), nn.SiLU()]
            cin = cout
        self.down = nn.Sequential(*down[:-1]) if down else nn.Conv3d(cin, cfg.cond_channels, 1)

    def forward(self, item: dict, grid: LiftGrid) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One sample -> (condition (1, cond, X', Y', Z'), depth probabilities (N, D, h, w), their
        ground-truth bins (N, h, w), -1 where there is none: sky, padding, beyond the range)."""
        images = item.get("input_images", item["images"])
        check_inputs(item, images)
        out = self.head(self.encoder(images))
        n, _, h, w = out.shape
        c = self.cfg.feature_channels
        feats, probs = out[:, :c], out[:, c:].softmax(1)
        stride = self.encoder.stride
        pts, valid, target = [], [], []
        for i in range(n):
            pts.append(frustum_points(feature_intrinsics(item["intrinsics"][i], stride), item["distortion"][i],
                                      item["cam_to_chunk"][i].double(), h, w, self.bin_centres))
            rows = torch.clamp(torch.arange(h) * stride + stride // 2, max=images.shape[2] - 1)
            cols = torch.clamp(torch.arange(w) * stride + stride // 2, max=images.shape[3] - 1)
            valid.append(item["valid"][i][rows][:, cols])
            target.append(depth_to_bin(item["depth"][i][rows][:, cols], self.bin_edges))
        valid_t, target_t = torch.stack(valid), torch.stack(target)
        target_t = torch.where(valid_t, target_t, torch.full_like(target_t, -1))
        vol, hits = lift(feats, None if self.cfg.lifting == "broadcast" else probs, torch.stack(pts), grid, valid_t)
        x = torch.cat([vol, torch.log1p(hits)[None].to(vol.dtype)], 0)[None]
        return self.down(x), probs, target_t


def check_inputs(item: dict, images: torch.Tensor) -> None:
    """Clear errors for inputs the lifting cannot use: no images, an image whose size or
    intrinsics disagree (principal point outside the image, non-positive or non-finite focal
    lengths), a non-finite or non-rigid pose."""
    where = item.get("sample", "sample")
    if not isinstance(images, torch.Tensor) or images.ndim != 4 or images.shape[0] == 0 or images.shape[1] != 3:
        shape = tuple(images.shape) if isinstance(images, torch.Tensor) else type(images).__name__
        raise InputError(f"{where}: images: expected (N >= 1, 3, H, W), got {shape}")
    n, _, h, w = images.shape
    names = item.get("camera_names") or [str(i) for i in range(n)]
    for key, shape in (("intrinsics", (n, 3, 3)), ("cam_to_chunk", (n, 4, 4)), ("image_size", (n, 2))):
        if key not in item or tuple(item[key].shape) != shape:
            got = tuple(item[key].shape) if key in item else "nothing"
            raise InputError(f"{where}: {key}: expected {shape} for {n} images, got {got}")
    for i in range(n):
        k, pose = item["intrinsics"][i].double(), item["cam_to_chunk"][i].double()
        hh, ww = (int(v) for v in item["image_size"][i])
        if not (0 < hh <= h and 0 < ww <= w):
            raise InputError(f"{where}: camera {names[i]}: image_size {hh} x {ww} does not fit the {h} x {w} images")
        fx, fy, cx, cy = float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
        if not (math.isfinite(fx) and math.isfinite(fy) and fx > 0 and fy > 0 and 0 <= cx <= ww and 0 <= cy <= hh):
            raise InputError(f"{where}: camera {names[i]}: intrinsics (fx {fx:g}, fy {fy:g}, cx {cx:g}, cy {cy:g}) "
                             f"do not fit its {ww} x {hh} image (the principal point must lie inside it: "
                             f"were the images resized without scaling K?)")
        r = pose[:3, :3]
        if not bool(torch.isfinite(pose).all()) or float((r @ r.T - torch.eye(3, dtype=r.dtype)).abs().max()) > 1e-3:
            raise InputError(f"{where}: camera {names[i]}: cam_to_chunk must be a finite rigid transform, got "
                             f"{pose.tolist()}")


class GeometryNet(nn.Module):
    """The conditional model of one level with its frozen structure VAE (module docstring)."""

    def __init__(self, cfg: GeometryModelConfig, grid: LiftGrid | None = None):
        super().__init__()
        self.cfg = cfg
        self.vae = StructureVAE(cfg.vae)
        self.vae_loaded = False
        if cfg.vae_checkpoint is not None:
            self._load_vae(cfg.vae_checkpoint)
        for p in self.vae.parameters():
            p.requires_grad_(False)
        self.conditioner = ImageConditioner(cfg, self.vae.stride)
        self.denoiser = Denoiser3d(cfg.vae.latent_channels, cfg.cond_channels, cfg.widths, cfg.blocks, cfg.groups,
                                   attention_levels=cfg.attention_levels, heads=cfg.heads)
        self.schedule = NoiseSchedule(cfg.train_steps, cfg.beta_start, cfg.beta_end)

    def _load_vae(self, name: str) -> None:
        from .checkpoint import CheckpointError, resolve_checkpoint
        from .trainer import load_model

        try:
            path = resolve_checkpoint(name)
        except CheckpointError:
            return  # a checkpoint of this model holds the VAE's weights; training checks `vae_loaded`
        vae_net, run = load_model("geometry-vae", path)
        got = VAEConfig(**run.model.get("vae", {}))
        if got != self.cfg.vae:
            raise InputError(f"vae_checkpoint {name}: its VAE is {got.model_dump()}, the config's model.vae is "
                             f"{self.cfg.vae.model_dump()}")
        self.vae.load_state_dict(vae_net.vae.state_dict())
        self.vae_loaded = True

    def train(self, mode: bool = True):
        super().train(mode)
        self.vae.eval()  # frozen: no running statistics move, no posterior sampling
        return self

    def latent_target(self, item: dict, grid: LiftGrid) -> torch.Tensor:
        """The ground-truth grid's posterior mean / latent_std: (1, Cz, X', Y', Z')."""
        occ, lab = dense_target(item["gt_ijk"], item["gt_labels"], grid.dims)
        with torch.no_grad():
            mu, _ = self.vae.encode(occ[None], lab[None])
        return mu / self.vae.latent_std

    def predict_latent(self, cond: torch.Tensor, steps: int | None = None, seed: int = 0) -> torch.Tensor:
        """x_0 (1, Cz, ...) scaled latent: DDIM from seeded noise (diffusion) or one pass (predictor)."""
        shape = (cond.shape[0], self.cfg.vae.latent_channels, *cond.shape[2:])
        last = self.schedule.steps - 1
        if self.cfg.mode == "predictor":
            return self.denoiser(cond.new_zeros(shape), cond, torch.full((shape[0],), last))
        noise = torch.randn(shape, generator=torch.Generator().manual_seed(int(seed)), dtype=cond.dtype)

        def v_fn(x, t):
            return self.denoiser(x, cond, torch.full((x.shape[0],), t))

        return ddim_sample(v_fn, noise, self.schedule, steps or self.cfg.sample_steps)

    def decode(self, z_scaled: torch.Tensor):
        """Scaled latent -> per sample (ijk (V, 3), labels (V,)) in the box's voxels."""
        occ_levels, occ_final, lab = self.vae.decode(z_scaled * self.vae.latent_std)
        return prune_decode(occ_levels, occ_final, lab)

    def loss(self, item: dict, grid: LiftGrid) -> tuple[torch.Tensor, dict]:
        if not self.vae_loaded:
            raise InputError(f"model.vae_checkpoint {self.cfg.vae_checkpoint!r}: not found; train the level's "
                             f"structure VAE first (scube-sim train geometry-vae ...) and name its best.pt")
        cond, probs, target = self.conditioner(item, grid)
        x0 = self.latent_target(item, grid)
        last = self.schedule.steps - 1
        if self.cfg.mode == "predictor":
            pred = self.denoiser(torch.zeros_like(x0), cond, torch.full((1,), last))
            main = F.mse_loss(pred, x0)
        else:
            t = torch.randint(0, self.schedule.steps, (x0.shape[0],))
            noise = torch.randn_like(x0)
            v = self.denoiser(self.schedule.q_sample(x0, t, noise), cond, t)
            main = F.mse_loss(v, self.schedule.v_target(x0, t, noise))
        depth = depth_focal_loss(probs, target)
        return main + self.cfg.depth_weight * depth, {"latent": float(main.detach()), "depth": float(depth.detach())}


# ---------------------------------------------------------------------------- stages
def _grid_metrics(pred: list[tuple[torch.Tensor, torch.Tensor]], items: list[dict], split: bool) -> dict[str, float]:
    """`geometry_metrics.summarise` of predicted against ground-truth voxels: IoU (mean over
    samples), mIoU (semantic scene completion convention, over the summed confusion), voxel Chamfer
    quantiles; with `split`, each also over the voxels visible / invisible from the item's input
    cameras (`visible_voxels`, applied to both grids alike)."""
    samples = []
    for (ijk, lab), item in zip(pred, items):
        gt_ijk = item["gt_ijk"]
        if split:
            grid = item["lift_grid"]

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
        net.vae = StructureVAE(model_cfg.vae)
        return net

    def dataset(self, data_dir: Path, data_cfg: GeometryDataConfig, split: str, seed: int) -> Dataset:
        return _VoxelsOnly(GeometryDataset(Path(data_dir), split, data_cfg, seed))

    def collate(self, samples: list) -> list:
        return list(samples)

    def loss(self, model: nn.Module, batch: list) -> tuple[torch.Tensor, dict[str, float]]:
        occ, lab = _dense_batch(batch)
        return model.vae.loss(occ, lab)

    def evaluate(self, model: nn.Module, batches: Iterable[list]) -> dict[str, float]:
        preds, items = [], []
        for batch in batches:
            occ, lab = _dense_batch(batch)
            _, _, occ_levels, occ_final, logits = model.vae(occ, lab, sample=False)
            ijks, labs = prune_decode(occ_levels, occ_final, logits)
            preds += list(zip(ijks, labs))
            items += batch
        return _grid_metrics(preds, items, split=False)


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
        return {k: item[k] for k in ("gt_ijk", "gt_labels", "gt_visible", "sample")} | {"dims": self.ds.grid.dims}


def _dense_batch(batch: list[dict]) -> tuple[torch.Tensor, torch.Tensor]:
    occ, lab = zip(*(dense_target(it["gt_ijk"], it["gt_labels"], it["dims"]) for it in batch))
    return torch.stack(occ), torch.stack(lab)


class GeometryStage(Stage):
    name = "geometry"
    model_config = GeometryModelConfig
    data_config = GeometryDataConfig
    primary_metric = "iou"
    higher_is_better = True

    def build_model(self, model_cfg: GeometryModelConfig) -> nn.Module:
        return GeometryNet(model_cfg)

    def dataset(self, data_dir: Path, data_cfg: GeometryDataConfig, split: str, seed: int) -> Dataset:
        return GeometryDataset(Path(data_dir), split, data_cfg, seed)

    def collate(self, samples: list) -> list:
        return list(samples)

    def loss(self, model: nn.Module, batch: list) -> tuple[torch.Tensor, dict[str, float]]:
        total, logs = 0.0, {}
        for item in batch:
            loss, lg = model.loss(item, _item_grid(item))
            total = total + loss
            for k, v in lg.items():
                logs[k] = logs.get(k, 0.0) + v / len(batch)
        return total / len(batch), logs

    def evaluate(self, model: nn.Module, batches: Iterable[list]) -> dict[str, float]:
        preds, items = [], []
        for batch in batches:
            for item in batch:
                grid = _item_grid(item)
                cond, _, _ = model.conditioner(item, grid)
                z = model.predict_latent(cond, seed=_sample_seed(item))
                ijks, labs = model.decode(z)
                preds.append((ijks[0], labs[0]))
                items.append(item)
        return _grid_metrics(preds, items, split=True)


def _item_grid(item: dict) -> LiftGrid:
    return item["lift_grid"]


def _sample_seed(item: dict) -> int:
    """The sampler's seed of an item: from its sample name, so the same input gives the same grid."""
    return int.from_bytes(str(item.get("sample", "")).encode()[-8:].rjust(8, b"\0"), "big") % (2 ** 31)


register_stage(GeometryVAEStage())
register_stage(GeometryStage())
