"""Stage `appearance` (paper section 3.2, appendix B): M Gaussians in every voxel of a grid and a
sky panorama, from the posed input images; trained on ground-truth voxels.

Per sample (chunk frame: x forward, y left, z up, metres):

1. An image CNN (3 -> 16 -> 32 -> 32, kernel 3, strides 1, 1, 2, residual on the last two) gives
   each input camera a feature map at half its resolution.
2. Each feature pixel's ray deposits its feature in the first voxel it enters (`voxel_rays`,
   cast through the grid; the rays are fixed per sample, so the dataset casts them); a voxel
   takes the mean of its rays, plus a flag for "seen" and a positional encoding of its centre.
3. A sparse U-Net (widths 32, 64, 128 by default: base 32, multipliers 1, 2, 4) maps that to
   M x 14 raw values per voxel, activated by the shared definition (`activations.activate`).
4. The same features, where the sky mask says sky, fill the sky panorama (`sky`); a novel view
   samples it along its rays and decodes it to RGB. Image = Gaussians (`splat_render`) + the
   transmittance left after them x sky.

Loss per view: 0.9 L1(image) + 1.0 L1(alpha, non-sky mask) + 0.1 (1 - SSIM), + 0.6 LPIPS where the
model config names a user's local LPIPS weight files (`model.lpips`; none can be downloaded here,
`lpips`). Metrics: PSNR and SSIM of the rendered views, PSNR on the sky pixels alone, and LPIPS
where it is configured.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field, field_validator
from torch import nn
from torch.utils.data import Dataset

from ..config import StrictModel
from ..errors import InputError
from ..labels import NUM_LABELS, reflectance_from_labels
from ..voxsplat import VoxSplat
from ..worlds.groundtruth import CHUNK_CORNER
from .activations import OFFSET, OPACITY, QUAT, RGB, SCALE, activate
from .augment import AugmentConfig, photometric
from .data import DataConfig, WorldsTorchDataset, item_generator
from .image_metrics import psnr, ssim
from .lpips import LPIPS, LPIPSConfig, load_lpips
from .sky import SkyDecoder, build_panorama, camera_ray_directions, panorama_directions, sample_panorama
from .sparse import SparseTensor, SparseUNet, voxel_keys
from .splat_render import rasterization
from .stages import Stage, register_stage
from .voxel_rays import VoxelRayCaster, deposit_mean

NUM_RAW = 14
NO_AUGMENT = AugmentConfig(**{k: {"p": 0.0} for k in ("color_jitter", "exposure", "blur", "noise", "jpeg")})
LOSS_WEIGHTS = {"l1": 0.9, "alpha": 1.0, "ssim": 0.1}
EVAL_OFFSETS = (5, 10)  # the paper's novel-view instants T+5, T+10: never in the loss
# The test-time fit (`fit_input_views`): Adam rates per kind of raw value, in the raw layout's order, and
# for the panorama's features. Offsets are r * tanh(raw) with r one voxel, so 0.02 is about 3DGS's
# position rate for a 100 m scene (1.6e-4 x extent) at 0.4 m; colours are SH degree 0 (x 0.28).
FIT_RATES = {"offset": 0.02, "opacity": 0.05, "scale": 0.01, "quat": 0.005, "rgb": 0.02, "pano": 0.01}
_RAW_SLOTS = {"offset": OFFSET, "opacity": OPACITY, "scale": SCALE, "quat": QUAT, "rgb": RGB}


class AppearanceModelConfig(StrictModel):
    """The network: Gaussians per voxel M, image feature channels, U-Net widths (depth = count),
    residual blocks, norm, positional-encoding frequencies, the training panorama's size (paper:
    768 x 1536; sized down for CPU), where the raw values start (opacity, scale in voxels), and
    the optional LPIPS loss term from a user's local weight files (`lpips.LPIPSConfig`)."""

    gaussians_per_voxel: int = Field(default=4, ge=1, le=16)
    image_channels: int = Field(default=32, ge=4)
    widths: tuple[int, ...] = Field(default=(32, 64, 128), min_length=1)
    blocks: int = Field(default=1, ge=1)
    norm: str = Field(default="group", pattern="^(batch|group|none)$")
    pe_frequencies: int = Field(default=6, ge=0, le=16)
    panorama: tuple[int, int] = (64, 128)
    offset_range: float = Field(default=1.0, gt=0)
    init_opacity: float = Field(default=0.5, gt=0, lt=1)
    init_scale_voxels: float = Field(default=0.5, gt=0)
    lpips: LPIPSConfig | None = None


class AppearanceDataConfig(StrictModel):
    """Which ground-truth grid (level fine | coarse, optionally coarsened by `coarsen`: fine x 2
    is 0.2 m in the worlds), the part of the chunk kept (x_min, y_min, z_min, x_max, y_max, z_max,
    chunk frame metres; None: all), the image scale of the stored images, and the views rendered
    for the loss: the cameras at the stored instants `loss_offsets` (frames after T; 0 is the
    input instant; never the evaluation's T+5 and T+10, so a dataset for it is generated with
    e.g. ``--frame-offsets 0,2,7``), all of them or `train_views` drawn per item (seeded by seed,
    epoch and index: rendering is most of a step's time on a CPU). Moving actors are masked out
    of the loss at the instants after T (the grid holds them where they were at T).
    `augment`: the photometric augmentation of the network's *input* images in training (the
    rendered views are compared with the clean images). `eval_cameras`: the cameras evaluated,
    ``front`` (the three forward-facing ones, the paper's protocol) or ``all``."""

    level: str = Field(default="coarse", pattern="^(fine|coarse)$")
    coarsen: int = Field(default=1, ge=1, le=8)
    region: tuple[float, float, float, float, float, float] | None = None
    image_scale: float = Field(default=0.5, gt=0, le=1)
    eval_frames: bool = False
    loss_offsets: list[int] = Field(default_factory=lambda: [0], min_length=1)
    train_views: int | None = Field(default=None, ge=1)  # views rendered per training item (None: all)
    augment: AugmentConfig = Field(default_factory=AugmentConfig)  # of the network's input images only
    eval_cameras: str = Field(default="front", pattern="^(front|all)$")

    @field_validator("loss_offsets")
    @classmethod
    def _not_the_evaluation(cls, v: list[int]) -> list[int]:
        bad = sorted(set(v) & set(EVAL_OFFSETS))
        if bad or any(k < 0 for k in v) or len(set(v)) != len(v):
            raise ValueError(f"expected distinct frame offsets >= 0 other than the evaluation's "
                             f"{list(EVAL_OFFSETS)}, got {v}")
        return sorted(v)


# ---------------------------------------------------------------------------- data
class AppearanceDataset(Dataset):
    """Worlds samples with a ground-truth grid and each input camera's first-hit voxels.

    Item: the `WorldsTorchDataset` item (images at `image_scale`, cameras, sky masks, ...) plus
    ``ijk`` (V, 3) int64 voxels (chunk frame, origin CHUNK_CORNER), ``voxel_size``, and ``hits``
    (N, h, w) int64, the row of ``ijk`` each half-resolution feature pixel's ray enters first (-1:
    none), ``loss_views`` the (frame offset, camera index) pairs the loss renders, ``eval_cameras``
    the config's choice, and in training ``input_images``, the
    network's augmented inputs (``images`` stay clean: the loss's targets). Pinhole and OpenCV
    cameras."""

    def __init__(self, root: Path, split: str, cfg: AppearanceDataConfig, seed: int = 0):
        self.cfg = cfg
        self.seed = seed
        self.train = split == "train"
        # clean images from the base (they are the loss's targets); inputs are augmented here
        later = self.train and any(k != 0 for k in cfg.loss_offsets)
        self.base = WorldsTorchDataset(root, split=split, train=split == "train",
                                       config=DataConfig(image_scale=cfg.image_scale,
                                                         eval_frames=cfg.eval_frames or later,
                                                         seed=seed, augment=NO_AUGMENT))

    def __len__(self) -> int:
        return len(self.base)

    def set_epoch(self, epoch: int) -> None:
        self.base.set_epoch(epoch)

    def __getitem__(self, index: int) -> dict:
        item = self.base[index]
        ijk = item[f"{self.cfg.level}_ijk"]
        labels = item[f"{self.cfg.level}_labels"].to(torch.int64)
        vs = float(item[f"{self.cfg.level}_voxel_size"])
        if self.cfg.coarsen > 1:
            ijk, inv = torch.unique(ijk // self.cfg.coarsen, dim=0, return_inverse=True)
            labels = majority_labels(inv, labels, len(ijk))
            vs *= self.cfg.coarsen
        if self.cfg.region is not None:
            centres = torch.as_tensor(CHUNK_CORNER) + (ijk.double() + 0.5) * vs
            lo, hi = torch.tensor(self.cfg.region[:3]), torch.tensor(self.cfg.region[3:])
            inside = ((centres >= lo) & (centres < hi)).all(1)
            ijk, labels = ijk[inside], labels[inside]
        item["ijk"], item["labels"], item["voxel_size"] = ijk, labels, vs
        item["hits"] = first_hit_voxels(item, ijk, vs)
        offsets = self.cfg.loss_offsets if self.train else [0]
        views = [(k, i) for k in offsets for i in range(frame_at(item, k)["images"].shape[0])]
        if self.train and self.cfg.train_views is not None and self.cfg.train_views < len(views):
            gen = item_generator(self.seed + 1, self.base.epoch, index % len(self))  # not the augmentation's stream
            views = [views[j] for j in sorted(torch.randperm(len(views), generator=gen)[: self.cfg.train_views].tolist())]
        item["loss_views"] = views
        item["eval_cameras"] = self.cfg.eval_cameras
        if self.train:
            gen = item_generator(self.seed + 2, self.base.epoch, index % len(self))
            item["input_images"] = torch.stack([photometric(im, gen, self.cfg.augment) for im in item["images"]])
        return item


def first_hit_voxels(item: dict, ijk: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """(N, h, w) int64: for each half-resolution feature pixel of the item's N cameras, the row
    of `ijk` (V, 3) (chunk voxels of `voxel_size` from CHUNK_CORNER) its ray enters first; -1
    where it enters none (sky, or beyond the grid) and in the padding."""
    caster = VoxelRayCaster(ijk, voxel_size, CHUNK_CORNER)
    n, _, h, w = item["images"].shape
    hits = []
    for i in range(n):
        hh, ww = _half(int(item["image_size"][i, 0])), _half(int(item["image_size"][i, 1]))
        dirs = camera_ray_directions(_half_k(item["intrinsics"][i]), item["distortion"][i],
                                     item["cam_to_chunk"][i], hh, ww).reshape(-1, 3).double()
        origin = item["cam_to_chunk"][i][:3, 3].double().expand_as(dirs)
        idx, _ = caster.first_hit(origin, dirs)
        full = torch.full((_half(h), _half(w)), -1, dtype=torch.int64)
        full[:hh, :ww] = idx.reshape(hh, ww)
        hits.append(full)
    return torch.stack(hits)


def frame_at(item: dict, offset: int) -> dict:
    """The item's cameras at frame offset `offset` (0: the item itself, else its ``eval_frames``
    entry); an error naming the sample and the stored offsets when it has none there."""
    if offset == 0:
        return item
    for f in item.get("eval_frames", []):
        if f["offset"] == offset:
            return f
    have = [0] + [f["offset"] for f in item.get("eval_frames", [])]
    raise InputError(f"sample {item.get('sample')}: no frame at offset {offset} (stored: {have}); generate the "
                     f"training split with `scube-sim worlds generate --frame-offsets ...` that include it")


def static_mask(frame: dict, i: int, moving: torch.Tensor) -> torch.Tensor:
    """(H, W) bool of camera i of `frame`: inside the image and not on a moving actor."""
    hh, ww = (int(s) for s in frame["image_size"][i])
    inst = frame["instance"][i, :hh, :ww]
    return frame["valid"][i, :hh, :ww] & ~torch.isin(inst, moving)


def is_front_camera(name: str) -> bool:
    """The forward-facing cameras of the shipped rigs: waymo-5 FRONT, FRONT_LEFT, FRONT_RIGHT;
    nuscenes-6 CAM_FRONT, CAM_FRONT_LEFT, CAM_FRONT_RIGHT."""
    return "FRONT" in name.upper()


def _half(n: int) -> int:
    return (n + 1) // 2  # a stride-2, padding-1, kernel-3 convolution's output size


def _half_k(K: torch.Tensor) -> torch.Tensor:
    """K of the half-resolution feature map (its pixel i covers image pixels 2i, 2i + 1)."""
    k = K.double().clone()
    k[:2] /= 2.0
    return k


# ---------------------------------------------------------------------------- network
class _ResBlock2d(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 3, stride, 1)
        self.skip = nn.Identity() if cin == cout and stride == 1 else nn.Conv2d(cin, cout, 1, stride)

    def forward(self, x):
        return F.relu(self.conv(x) + self.skip(x))


class ImageEncoder(nn.Module):
    """(N, 3, H, W) -> (N, C, ceil(H/2), ceil(W/2)): conv 3 -> 16 -> 32 -> C, strides 1, 1, 2,
    residual on the last two (appendix B)."""

    def __init__(self, channels: int = 32):
        super().__init__()
        self.net = nn.Sequential(nn.Conv2d(3, 16, 3, 1, 1), nn.ReLU(inplace=True), _ResBlock2d(16, 32, 1),
                                 _ResBlock2d(32, channels, 2))

    def forward(self, images):
        return self.net(images)


def majority_labels(inverse: torch.Tensor, labels: torch.Tensor, n: int) -> torch.Tensor:
    """(n,) int64 the most frequent of the `labels` (M,) that `inverse` (M,) maps to each of n
    coarse voxels (ties to the lower id): a coarsened grid's labels."""
    counts = torch.zeros(n, NUM_LABELS, dtype=torch.int64).index_put_(
        (inverse, labels.to(torch.int64)), torch.ones_like(inverse), accumulate=True)
    return counts.argmax(1)


def positional_encoding(x: torch.Tensor, frequencies: int) -> torch.Tensor:
    """(V, 3) chunk-frame centres, metres -> (V, 6 F): sin and cos of pi 2^f x / 51.2 m."""
    if frequencies == 0:
        return x.new_zeros((x.shape[0], 0))
    u = (x / 51.2)[:, None, :] * (math.pi * 2.0 ** torch.arange(frequencies, dtype=x.dtype))[None, :, None]
    return torch.cat([torch.sin(u), torch.cos(u)], 1).reshape(x.shape[0], 6 * frequencies)


class AppearanceNet(nn.Module):
    def __init__(self, cfg: AppearanceModelConfig):
        super().__init__()
        self.cfg = cfg
        m = cfg.gaussians_per_voxel
        self.encoder = ImageEncoder(cfg.image_channels)
        self.unet = SparseUNet(cfg.image_channels + 1 + 6 * cfg.pe_frequencies, m * NUM_RAW, widths=cfg.widths,
                               blocks=cfg.blocks, norm=cfg.norm)
        self.sky = SkyDecoder(cfg.image_channels, 16)
        # where the raw values start: opacity init_opacity, scale init_scale_voxels (x voxel size)
        self.register_buffer("_opacity_bias", torch.tensor(math.log(cfg.init_opacity / (1 - cfg.init_opacity))))
        self.__dict__["_lpips"] = None  # not a submodule: the user's weights stay out of checkpoints

    def lpips(self) -> LPIPS | None:
        """The configured LPIPS network (None without `cfg.lpips`), loaded on first use."""
        if self.cfg.lpips is not None and self.__dict__["_lpips"] is None:
            self.__dict__["_lpips"] = load_lpips(self.cfg.lpips)
        return self.__dict__["_lpips"]

    def forward(self, item: dict, sky: bool = True) -> dict:
        """One sample (an `AppearanceDataset` item) -> the Gaussians (flat: means (G, 3), quats,
        scales, opacities, colors; chunk frame) and the sky panorama (C, Hp, Wp); with sky False
        (a LiDAR-only conversion) no panorama is built (``pano`` None)."""
        feats = self.encoder(item.get("input_images", item["images"]))  # (N, C, h, w)
        n, c, h, w = feats.shape
        hits = item["hits"][:, :h, :w]
        ijk, vs = item["ijk"], float(item["voxel_size"])
        v = ijk.shape[0]
        vox, count = deposit_mean(feats.permute(0, 2, 3, 1).reshape(-1, c), hits.reshape(-1), v)
        centres = torch.as_tensor(CHUNK_CORNER, dtype=feats.dtype) + (ijk.to(feats.dtype) + 0.5) * vs
        seen = (count > 0).to(feats.dtype)[:, None]
        x = torch.cat([vox, seen, positional_encoding(centres, self.cfg.pe_frequencies)], 1)
        coords = torch.cat([torch.zeros(v, 1, dtype=torch.int64), ijk], 1)
        st = SparseTensor.from_coords(coords, x, batch_size=1)
        raw = st.feats.new_zeros((v, self.cfg.gaussians_per_voxel * NUM_RAW))
        if v:
            out = self.unet(st)
            # back from the grid's site order to the item's voxel order
            pos = torch.searchsorted(voxel_keys(out.coords[:, 1:]), voxel_keys(ijk))
            raw = out.feats[pos]
        raw = raw.reshape(v, self.cfg.gaussians_per_voxel, NUM_RAW)
        bias = torch.zeros(NUM_RAW, dtype=raw.dtype)
        bias[3] = self._opacity_bias
        bias[4:7] = math.log(self.cfg.init_scale_voxels * vs)
        flat = self.splats(raw + bias, item)
        if not sky:
            return {**flat, "pano": None, "pano_weight": None}
        sky_small = F.interpolate((item["sky"] & item["valid"])[:, None].to(feats.dtype), size=(h, w),
                                  mode="area")[:, 0]  # the sky fraction of each feature pixel
        k_half = torch.stack([_half_k(k) for k in item["intrinsics"]])
        pano, weight = build_panorama(feats, sky_small, item["cam_to_chunk"].double(), k_half, item["distortion"],
                                      *self.cfg.panorama)
        return {**flat, "pano": pano, "pano_weight": weight}

    def splats(self, raw: torch.Tensor, item: dict) -> dict:
        """(V, M, 14) raw values of the item's voxels -> the flat Gaussians (chunk frame): means
        (V*M, 3), quats, scales, opacities, colors, and ``raw`` itself."""
        vs = float(item["voxel_size"])
        centres = torch.as_tensor(CHUNK_CORNER, dtype=raw.dtype) + (item["ijk"].to(raw.dtype) + 0.5) * vs
        g = activate(raw, centres, vs, self.cfg.offset_range)
        return {"means": g["means"].reshape(-1, 3), "quats": g["quats"].reshape(-1, 4),
                "scales": g["scales"].reshape(-1, 3), "opacities": g["opacities"].reshape(-1),
                "colors": g["colors"].reshape(-1, 3), "raw": raw}

    def sky_rgb(self, out: dict, height: int, width: int) -> torch.Tensor:
        """(height, width, 3) the decoded sky on the equirectangular grid of `sky` (chunk axes)."""
        feats = sample_panorama(out["pano"], panorama_directions(height, width, out["pano"].dtype))
        return self.sky(feats[None])[0].permute(1, 2, 0)

    def to_voxsplat(self, out: dict, item: dict, sky_size: tuple[int, int] | None = (128, 256)) -> VoxSplat:
        """The prediction for `item` as a VoxSplat in the chunk frame (origin CHUNK_CORNER, the
        item's grid; metadata ``frame: chunk``, ``chunk_to_world``, ``sample``) with its sky as the
        ``sky_panorama`` channel at `sky_size` (rows, columns; None or no panorama: none). Same activations, so the
        Gaussians are the ones `render` draws. The voxels carry the item's labels and each Gaussian
        its label's default reflectance (`labels.reflectance_from_labels`) as the ``reflectance``
        channel, so a LiDAR's intensity goes through its own response as on a built scene."""
        raw = out["raw"].detach().float().numpy()
        labels = item["labels"].numpy()
        vs = VoxSplat(ijk=item["ijk"].numpy(), params=raw, labels=labels,
                      voxel_size=float(item["voxel_size"]), origin=np.asarray(CHUNK_CORNER, np.float64),
                      offset_range=self.cfg.offset_range,
                      metadata={"frame": "chunk", "sample": str(item.get("sample", "")),
                                "chunk_to_world": np.asarray(item["chunk_to_world"], np.float64).tolist(),
                                "source": "scube_sim.model.appearance"})
        if sky_size is not None and out.get("pano") is not None:
            vs.set_channel("sky_panorama", self.sky_rgb(out, *sky_size).detach().float().numpy())
        vs.set_channel("reflectance", np.repeat(reflectance_from_labels(labels)[:, None], raw.shape[1], axis=1))
        return vs

    def render(self, out: dict, K: torch.Tensor, cam_to_chunk: torch.Tensor, height: int, width: int,
               distortion=None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One view: (image (3, H, W) in [0, 1], alpha (H, W) of the Gaussians, sky (3, H, W))."""
        dtype = out["means"].dtype
        viewmat = torch.linalg.inv(cam_to_chunk.double()).to(dtype)[None]
        dist = distortion if distortion is not None and bool(torch.as_tensor(distortion).abs().sum() > 0) else None
        img, alpha, _ = rasterization(out["means"], out["quats"], out["scales"], out["opacities"], out["colors"],
                                      viewmat, K.to(dtype)[None], width, height,
                                      camera_model="opencv" if dist is not None else "pinhole",
                                      dist_coeffs=None if dist is None else torch.as_tensor(dist)[None].double())
        dirs = camera_ray_directions(K, distortion, cam_to_chunk, height, width)
        sky = self.sky(sample_panorama(out["pano"], dirs.to(out["pano"].dtype))[None])[0]
        a = alpha[0, ..., 0]
        return img[0].permute(2, 0, 1) + (1 - a)[None] * sky, a, sky


# ---------------------------------------------------------------------------- stage
def view_losses(model: AppearanceNet, out: dict, item: dict, views=None) -> tuple[torch.Tensor, dict]:
    """The loss over views (frame offset, camera index) of an item (default: its cameras at T).
    After T the moving actors' pixels are left out (the grid holds them where they were at T)."""
    total = 0.0
    logs = {"l1": 0.0, "alpha": 0.0, "ssim": 0.0}
    lpips = model.lpips()
    if lpips is not None:
        logs["lpips"] = 0.0
    views = [(0, i) for i in range(item["images"].shape[0])] if views is None else views
    moving = item.get("moving_instances", torch.zeros(0, dtype=torch.int64))
    for k, i in views:
        frame = frame_at(item, k)
        hh, ww = (int(s) for s in frame["image_size"][i])
        img, alpha, _ = model.render(out, frame["intrinsics"][i], frame["cam_to_chunk"][i], hh, ww,
                                     frame["distortion"][i])
        gt = frame["images"][i, :, :hh, :ww]
        nonsky = (~frame["sky"][i, :hh, :ww]).to(img.dtype)
        keep = (static_mask(frame, i, moving) if k != 0 else frame["valid"][i, :hh, :ww]).to(img.dtype)
        n_keep = keep.sum().clamp_min(1.0)
        l1 = ((img - gt).abs() * keep).sum() / (3 * n_keep)
        la = ((alpha - nonsky).abs() * keep).sum() / n_keep
        ls = 1 - ssim(img[None], gt[None], keep[None])
        total = total + LOSS_WEIGHTS["l1"] * l1 + LOSS_WEIGHTS["alpha"] * la + LOSS_WEIGHTS["ssim"] * ls
        if lpips is not None:
            lp = lpips(img[None], gt[None], keep[None])[0]
            total = total + model.cfg.lpips.weight * lp
            logs["lpips"] += float(lp.detach()) / len(views)
        logs["l1"] += float(l1.detach()) / len(views)
        logs["alpha"] += float(la.detach()) / len(views)
        logs["ssim"] += float(1 - ls.detach()) / len(views)
    return total / len(views), logs


def fit_input_views(model: AppearanceNet, out: dict, item: dict, steps: int, on_step=None) -> dict:
    """Test-time fitting, after the network: its prediction `out` for `item` (made with the sky)
    optimised for `steps` Adam steps (`FIT_RATES`) on the item's own input views at T, one
    camera per step in order, with the training loss -> a prediction of the same form, without
    gradients. What moves is what the network outputs: every Gaussian's raw values and the
    panorama's features; the network (its sky decoder too) stays as it is. Not the paper's
    method (SCube is feed-forward): a speed/accuracy knob, off by default (0 steps).
    on_step(step, prediction) is called after each step (evaluation hooks)."""
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
        raise InputError(f"fit steps: expected an integer >= 0, got {steps!r}")
    if steps == 0:
        return out
    if out.get("pano") is None:
        raise InputError("fit_input_views: the prediction has no sky panorama (the loss composites the sky behind the "
                         "Gaussians); run the network with sky=True")
    parts = {k: out["raw"][..., s].detach().clone().requires_grad_(True) for k, s in _RAW_SLOTS.items()}
    pano = out["pano"].detach().clone().requires_grad_(True)
    leaves = [*parts.values(), pano]
    opt = torch.optim.Adam([{"params": [parts[k]], "lr": FIT_RATES[k]} for k in parts]
                           + [{"params": [pano], "lr": FIT_RATES["pano"]}])

    def current() -> dict:
        return {**model.splats(torch.cat(list(parts.values()), dim=-1), item), "pano": pano,
                "pano_weight": out.get("pano_weight")}

    n_views = item["images"].shape[0]
    for step in range(1, int(steps) + 1):
        with torch.enable_grad():
            loss, _ = view_losses(model, current(), item, views=[(0, (step - 1) % n_views)])
            # gradients for the prediction alone: the network's weights collect none
            for leaf, grad in zip(leaves, torch.autograd.grad(loss, leaves)):
                leaf.grad = grad
        opt.step()
        if on_step is not None:
            with torch.no_grad():
                on_step(step, current())
    with torch.no_grad():
        return {k: (v.detach() if torch.is_tensor(v) else v) for k, v in current().items()}


def evaluate_item(model: AppearanceNet, item: dict, cameras: str = "front", out: dict | None = None) -> dict:
    """Per-view metrics of one item at T and at each of its ``eval_frames``: ``{name: [values]}``
    with names psnr_t<k>, ssim_t<k> (moving actors and padding masked out), lpips_t<k> (the same
    pixels; where the model config names LPIPS weights) and psnr_sky_t<k> (sky pixels alone, where
    the view has any); k the frame offset. `cameras`: front | all."""
    out = model(item) if out is None else out
    lpips = model.lpips()
    moving = item.get("moving_instances", torch.zeros(0, dtype=torch.int64))
    res: dict[str, list[float]] = {}
    for frame in [item] + list(item.get("eval_frames", [])):
        k = int(frame.get("offset", 0)) if frame is not item else 0
        for i, name in enumerate(frame["camera_names"]):
            if cameras == "front" and not is_front_camera(name):
                continue
            hh, ww = (int(s) for s in frame["image_size"][i])
            img, _, _ = model.render(out, frame["intrinsics"][i], frame["cam_to_chunk"][i], hh, ww,
                                     frame["distortion"][i])
            gt = frame["images"][i, :, :hh, :ww]
            keep = static_mask(frame, i, moving)
            sky = frame["sky"][i, :hh, :ww] & keep
            res.setdefault(f"psnr_t{k}", []).append(psnr(img[None], gt[None], keep[None]))
            res.setdefault(f"ssim_t{k}", []).append(float(ssim(img[None], gt[None], keep[None])))
            if lpips is not None:
                res.setdefault(f"lpips_t{k}", []).append(float(lpips(img[None], gt[None], keep[None])[0]))
            if bool(sky.any()):
                res.setdefault(f"psnr_sky_t{k}", []).append(psnr(img[None], gt[None], sky[None]))
    return res


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
