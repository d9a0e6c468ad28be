"""The geometry stage's conditional model (paper section 3.1, appendix A-C): posed camera images to
a semantic voxel grid, through a structure VAE and an image-conditioned latent diffusion (XCube).

One level of the hierarchy at a time (`level: coarse | fine` in the data config; this module
holds the dense coarse level, whose box is small enough to be dense on a CPU: 128 x 128 x 32 cells
of 0.8 m, 0.5 M cells, most of them empty).

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
the trade, and the baseline the diffusion has to beat). With `refine`, an `OccupancyRefiner`
reads the lifted volume again at the voxels' own size after the decoder and corrects its final
occupancy and label logits.

Frames: chunk (x forward, y left, z up, metres; `CHUNK_CORNER`); voxel (i, j, k) of the level's
box spans region[:3] + [ijk, ijk + 1) * voxel_size.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F
from pydantic import Field, model_validator
from torch import nn

from ...config import StrictModel
from ...errors import InputError
from ...labels import NUM_LABELS
from ..nn.diffusion import NoiseSchedule, ddim_sample
from ..nn.encoding import positional_encoding
from ..nn.image_encoder import ImageEncoderConfig, build_image_encoder
from ..nn.lifting import (
    LiftGrid,
    depth_bin_centres,
    depth_bin_edges,
    depth_focal_loss,
    depth_to_bin,
    feature_intrinsics,
    frustum_points,
    lift,
)
from ..nn.sky import camera_ray_directions
from ..nn.sparse import SparseTensor
from ..nn.voxel_rays import VoxelRayCaster
from .data import dense_target
from .dense_nets import Denoiser3d, OccupancyRefiner, StructureVAE, VAEConfig, label_ce, prune_decode, structure_bce
from .sparse_nets import SparseDenoiser, SparseStructureVAE, decoded_voxels, row_ids

SITE_PE_FREQUENCIES = 6


# lift_norm mean: voxels whose summed depth weight is far below this hold ~0 instead of a mean of
# features that no pixel puts there with any confidence.
MASS_EPS = 1e-2


class GeometryVAEModelConfig(StrictModel):
    """The structure VAE of one level: dense (coarse) or sparse with its latent on the coarse
    grid's sites (fine)."""

    level: str = Field(default="coarse", pattern="^(coarse|fine)$")
    vae: VAEConfig = Field(default_factory=VAEConfig)


class GeometryModelConfig(StrictModel):
    """The conditional model of one level. mode: diffusion | predictor. vae_checkpoint: the
    trained `geometry-vae` run of this level (path or shipped name), frozen; `vae` must be its
    architecture. encoder: the image backbone; feature_channels C and depth_bins D of the conv
    head (paper: 32, 64; bins from near to far metres); lifting: depth (Eq. 1) | broadcast (the
    ablation) | oracle (each pixel's features put in its depth map's bin alone, in training and
    at inference: an upper bound that isolates the 3D prior from the depth estimate; needs depth
    maps, so worlds only); lift_norm: sum (Eq. 1 as written: each voxel holds the weighted sum of
    its features and log(1 + frustum points)) | mean (the weighted mean feature, log(1 + the
    summed weight) and log(1 + frustum points): the sum spans orders of magnitude between a voxel
    next to a camera and one 60 m out, which the unnormalised convolutions after it do not undo);
    depth_weight: lambda of the focal depth loss (paper 1). Denoiser: a 3D U-Net of
    `widths` (one level each, halving between) with `blocks` residual blocks per level,
    condition channels `cond_channels`. predictor_loss (mode predictor): latent (MSE to the
    ground truth's latent) | decoded (the predicted latent decoded by the frozen VAE and scored as
    the VAE is trained: structure BCE at every level + label cross-entropy against the
    ground-truth grid, the fine level's decoder kept to the ground truth's candidates as in its
    VAE's training; the latent is a learnt, non-linear code of the grid, and regressing it drifts
    to the mean scene). refine (coarse predictor, decoded loss): an `OccupancyRefiner` of
    `refine_width` channels corrects the decoded final occupancy and label logits from the lifted
    volume at the voxels' own resolution, and the grid is the refined final logit > 0 (its input
    holds every coarser level's logit, so it does the pruning). Diffusion: `train_steps` linear
    steps from beta_start to beta_end, `sample_steps` DDIM steps at inference (validation uses them
    too)."""

    level: str = Field(default="coarse", pattern="^(coarse|fine)$")
    mode: str = Field(default="diffusion", pattern="^(diffusion|predictor)$")
    predictor_loss: str = Field(default="latent", pattern="^(latent|decoded)$")
    refine: bool = False
    refine_width: int = Field(default=16, ge=1)
    vae_checkpoint: str | None = None
    vae: VAEConfig = Field(default_factory=VAEConfig)
    encoder: ImageEncoderConfig = Field(default_factory=ImageEncoderConfig)
    feature_channels: int = Field(default=32, ge=1)
    depth_bins: int = Field(default=64, ge=2)
    near: float = Field(default=0.1, gt=0)
    far: float = Field(default=90.0, gt=0)
    lifting: str = Field(default="depth", pattern="^(depth|broadcast|oracle)$")
    lift_norm: str = Field(default="sum", pattern="^(sum|mean)$")
    depth_weight: float = Field(default=1.0, ge=0)
    cond_channels: int = Field(default=64, ge=1)
    widths: tuple[int, ...] = Field(default=(64, 128, 256), min_length=1, max_length=5)
    blocks: int = Field(default=2, ge=1)
    groups: int = Field(default=8, ge=1)
    attention_levels: tuple[int, ...] = ()  # U-Net levels (0: the latent's resolution) with self-attention
    heads: int = Field(default=8, ge=1)
    layout: str = Field(default="plain", pattern="^(plain|ldm)$")  # Denoiser3d's layouts (geometry_nets)
    train_steps: int = Field(default=1000, ge=1)
    beta_start: float = Field(default=1e-4, gt=0)
    beta_end: float = Field(default=2e-2, gt=0)
    sample_steps: int = Field(default=10, ge=1)

    @model_validator(mode="after")
    def _check(self):
        if self.far <= self.near:
            raise ValueError(f"far ({self.far}) must exceed near ({self.near})")
        if self.predictor_loss == "decoded" and self.mode != "predictor":
            raise ValueError("predictor_loss 'decoded' is the single-step predictor's (mode: predictor)")
        if self.refine and (self.level != "coarse" or self.predictor_loss != "decoded"):
            raise ValueError("refine: the coarse level's single-step predictor with predictor_loss 'decoded' only "
                             f"(got level {self.level!r}, mode {self.mode!r}, predictor_loss {self.predictor_loss!r})")
        if self.sample_steps > self.train_steps:
            raise ValueError(f"sample_steps ({self.sample_steps}) cannot exceed train_steps ({self.train_steps})")
        return self


# ---------------------------------------------------------------------------- conditional model
class ImageConditioner(nn.Module):
    """Images -> per-pixel features (C) and depth distributions (D) -> Eq. 1 into the level's box
    -> strided convolutions to the latent's resolution (module docstring)."""

    def __init__(self, cfg: GeometryModelConfig, latent_stride: int | None):
        """latent_stride: the dense latent's size in lifting voxels; None: the sparse (fine) level,
        whose condition is gathered per latent site (`site_condition`)."""
        super().__init__()
        self.cfg = cfg
        self.encoder = build_image_encoder(cfg.encoder)
        e = self.encoder.out_channels
        self.head = nn.Sequential(nn.Conv2d(e, e, 3, padding=1), nn.ReLU(inplace=True),
                                  nn.Conv2d(e, cfg.feature_channels + cfg.depth_bins, 1))
        self.register_buffer("bin_edges", depth_bin_edges(cfg.depth_bins, cfg.near, cfg.far), persistent=False)
        self.register_buffer("bin_centres", depth_bin_centres(cfg.depth_bins, cfg.near, cfg.far), persistent=False)
        self.site_proj = None
        if latent_stride is None:  # lifted features + the coarse label of each site
            self.site_proj = nn.Linear(self.lifted_channels + NUM_LABELS + 6 * SITE_PE_FREQUENCIES,
                                       cfg.cond_channels)
            self.down = None
            return
        levels = int(round(math.log2(latent_stride)))
        down, cin = [], self.lifted_channels
        for i in range(levels):
            cout = cfg.cond_channels if i == levels - 1 else max(cfg.feature_channels, cfg.cond_channels // 2)
            down += [nn.Conv3d(cin, cout, 2, stride=2), nn.SiLU()]
            cin = cout
        self.down = nn.Sequential(*down[:-1]) if down else nn.Conv3d(cin, cfg.cond_channels, 1)

    @property
    def lifted_channels(self) -> int:
        """Channels per voxel of the lifted volume: C features, then log(1 + summed weight) with
        lift_norm mean, then log(1 + frustum points)."""
        return self.cfg.feature_channels + (2 if self.cfg.lift_norm == "mean" else 1)

    def forward(self, item: dict, grid: LiftGrid) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One sample -> (condition (1, cond, X', Y', Z'), depth probabilities (N, D, h, w), their
        ground-truth bins (N, h, w), -1 where there is none: sky, padding, beyond the range)."""
        x, probs, target = self.lift_volume(item, grid)
        return (x if self.down is None else self.down(x)), probs, target

    def lift_volume(self, item: dict, grid: LiftGrid) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """`forward` before the strided convolutions: the lifted volume (1, lifted_channels, X, Y, Z)
        on `grid`, the depth probabilities and their ground-truth bins."""
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
            if "depth" in item:
                target.append(depth_to_bin(item["depth"][i][rows][:, cols], self.bin_edges))
            else:  # real frames at inference: no depth map, no depth target
                target.append(torch.full((h, w), -1, dtype=torch.int64))
        valid_t, target_t = torch.stack(valid), torch.stack(target)
        target_t = torch.where(valid_t, target_t, torch.full_like(target_t, -1))
        weights = {"depth": probs, "broadcast": None}.get(self.cfg.lifting)
        if self.cfg.lifting == "oracle" and "depth" not in item:
            raise InputError(f"{item.get('sample', 'sample')}: lifting 'oracle' needs depth maps (worlds data); "
                             f"these frames have none")
        if self.cfg.lifting == "oracle":  # one-hot at the depth map's bin; nothing where it has none
            weights = F.one_hot(target_t.clamp(min=0), probs.shape[1]).permute(0, 3, 1, 2).to(feats.dtype)
            weights = weights * (target_t >= 0)[:, None].to(feats.dtype)
        if self.cfg.lift_norm == "mean":  # a channel of ones lifts the summed weight beside the features
            vol, hits = lift(torch.cat([feats, feats.new_ones(n, 1, h, w)], 1), weights, torch.stack(pts), grid,
                             valid_t)
            mass = vol[c:]
            vol = torch.cat([vol[:c] / (mass + MASS_EPS), torch.log1p(mass)], 0)
        else:
            vol, hits = lift(feats, weights, torch.stack(pts), grid, valid_t)
        return torch.cat([vol, torch.log1p(hits)[None].to(vol.dtype)], 0)[None], probs, target_t

    def site_condition(self, volume: torch.Tensor, sites: torch.Tensor, labels: torch.Tensor,
                       grid: LiftGrid) -> torch.Tensor:
        """(1, lifted_channels, X, Y, Z) lifted volume on `grid`, (N, 3) site indices in it, (N,) their coarse
        labels -> (N, cond) per-site condition: the lifted features there, the label, and a
        positional encoding of the site's centre (sparse convolutions see no box edges, so
        absolute height comes from here)."""
        f = volume[0][:, sites[:, 0], sites[:, 1], sites[:, 2]].T
        centres = torch.tensor(grid.origin, dtype=f.dtype) + (sites.to(f.dtype) + 0.5) * grid.voxel_size
        return self.site_proj(torch.cat([f, F.one_hot(labels, NUM_LABELS).to(f.dtype),
                                         positional_encoding(centres, SITE_PE_FREQUENCIES)], 1))


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
    """The conditional model of one level with its frozen structure VAE (module docstring).

    Coarse: a dense latent over the box, a dense denoiser. Fine: the latent on the coarse grid's
    sites (the ground truth's in training, the coarse prediction's at inference), a sparse
    denoiser conditioned per site on the lifted features there and the site's coarse label."""

    def __init__(self, cfg: GeometryModelConfig, load_vae: Callable[[str], nn.Module | None] | None = None):
        """load_vae: cfg.vae_checkpoint -> the trained structure VAE of this level (None: no such
        file; a checkpoint of this model holds the VAE's weights, and training checks
        `vae_loaded`); the geometry stage passes its checkpoint loader. Called after this VAE is
        made and before the rest, which keeps the random initialisation's order."""
        super().__init__()
        self.cfg = cfg
        self.fine = cfg.level == "fine"
        self.vae = SparseStructureVAE(cfg.vae) if self.fine else StructureVAE(cfg.vae)
        self.vae_loaded = False
        if cfg.vae_checkpoint is not None and load_vae is not None:
            trained = load_vae(cfg.vae_checkpoint)
            if trained is not None:
                self.vae.load_state_dict(trained.state_dict())
                self.vae_loaded = True
        for p in self.vae.parameters():
            p.requires_grad_(False)
        self.conditioner = ImageConditioner(cfg, None if self.fine else self.vae.stride)
        lat = cfg.vae.latent_channels
        if self.fine:
            self.denoiser = SparseDenoiser(lat, cfg.cond_channels, cfg.widths, cfg.blocks, cfg.groups,
                                           attention_levels=cfg.attention_levels, heads=cfg.heads, layout=cfg.layout)
        else:
            self.denoiser = Denoiser3d(lat, cfg.cond_channels, cfg.widths, cfg.blocks, cfg.groups,
                                       attention_levels=cfg.attention_levels, heads=cfg.heads, layout=cfg.layout)
        self.refiner = None
        if cfg.refine:
            self.refiner = OccupancyRefiner(self.conditioner.lifted_channels, len(self.vae.occ_heads), cfg.refine_width)
        self.schedule = NoiseSchedule(cfg.train_steps, cfg.beta_start, cfg.beta_end)
        self._latents: dict = {}  # (sample, box) -> its clean latent (coarse level; the VAE is frozen)

    def train(self, mode: bool = True):
        super().train(mode)
        self.vae.eval()  # frozen: no running statistics move, no posterior sampling
        return self

    def load_state_dict(self, *args, **kwargs):
        self._latents.clear()  # new VAE weights: the cached latents are stale
        return super().load_state_dict(*args, **kwargs)

    def _check_level(self, item: dict) -> None:
        if item.get("level", "coarse") != self.cfg.level:
            raise InputError(f"{item.get('sample', 'sample')}: a {item.get('level')} level item for the "
                             f"{self.cfg.level} level's model (data.level and model.level must agree)")

    # -- the clean latent and the condition, per level
    def latent_target(self, item: dict):
        """The ground-truth grid's posterior mean / latent_std: coarse (1, Cz, X', Y', Z'); fine a
        SparseTensor on the coarse sites (stride 2^L, batch 1)."""
        with torch.no_grad():
            if self.fine:
                coords = torch.cat([torch.zeros(len(item["gt_ijk"]), 1, dtype=torch.int64), item["gt_ijk"]], 1)
                mu, _ = self.vae.encode(coords, item["gt_labels"], 1)
                return mu.replace(mu.feats / self.vae.latent_std)
            # the VAE is frozen: a sample's (whole-box) latent is the same every epoch, so keep it
            key = (str(item.get("sample")), item["gt_grid"])
            if key not in self._latents:
                occ, lab = dense_target(item["gt_ijk"], item["gt_labels"], item["gt_grid"].dims)
                mu, _ = self.vae.encode(occ[None], lab[None])
                self._latents[key] = mu / self.vae.latent_std
            return self._latents[key]

    def _site_labels(self, sites: torch.Tensor, ijk: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """The labels of `sites` (N, 3) from a grid (ijk, labels) that holds them (0 where not)."""
        a, b = row_ids(sites, ijk)
        order = torch.argsort(b)
        pos = torch.searchsorted(b[order], a).clamp_max(max(len(b) - 1, 0))
        hit = (b[order][pos] == a) if len(b) else torch.zeros(len(a), dtype=torch.bool)
        return torch.where(hit, labels[order][pos] if len(b) else 0, torch.zeros_like(a))

    def _v(self, x_t, cond, t: torch.Tensor):
        if self.fine:
            return self.denoiser(cond[0].replace(torch.cat([x_t, cond[1]], 1)), t).feats
        return self.denoiser(x_t, cond, t)

    def loss(self, item: dict, grid: LiftGrid | None = None) -> tuple[torch.Tensor, dict]:
        self._check_level(item)
        if not self.vae_loaded:
            raise InputError(f"model.vae_checkpoint {self.cfg.vae_checkpoint!r}: not found; train the level's "
                             f"structure VAE first (scube-sim train geometry-vae ...) and name its best.pt")
        vol, lifted, probs, target = self._condition(item, grid or item["lift_grid"])
        x0 = self.latent_target(item)
        if self.fine:
            sites = x0.coords[:, 1:]
            labels = self._site_labels(sites, item["coarse_gt_ijk"], item["coarse_gt_labels"])
            cond = (x0, self.conditioner.site_condition(vol, sites, labels, item["lift_grid"]))
            x0 = x0.feats
        else:
            cond = vol
        last = self.schedule.steps - 1
        if self.cfg.mode == "predictor":
            pred = self._v(torch.zeros_like(x0), cond, torch.full((1,), last))
            if self.cfg.predictor_loss == "decoded" and self.fine:
                coords = torch.cat([torch.zeros(len(item["gt_ijk"]), 1, dtype=torch.int64), item["gt_ijk"]], 1)
                levels = self.vae.decode(cond[0].replace(pred * self.vae.latent_std), target=coords)
                bce, ce = self.vae.reconstruction_loss(levels, coords, item["gt_labels"])
                main = bce + ce
            elif self.cfg.predictor_loss == "decoded":
                occ, lab = dense_target(item["gt_ijk"], item["gt_labels"], item["gt_grid"].dims)
                occ_levels, occ_final, lab_logits = self._decode(pred, lifted)
                main = structure_bce(occ_levels, occ_final, occ[None]) + label_ce(lab_logits, lab[None])
            else:
                main = F.mse_loss(pred, x0)
        else:
            t = torch.randint(0, self.schedule.steps, (1,))
            noise = torch.randn_like(x0)
            tt = t.expand(x0.shape[0])  # one sample: every row (site) at its step
            v = self._v(self.schedule.q_sample(x0, tt, noise), cond, t)
            main = F.mse_loss(v, self.schedule.v_target(x0, tt, noise))
        depth = depth_focal_loss(probs, target)
        return main + self.cfg.depth_weight * depth, {"latent": float(main.detach()), "depth": float(depth.detach())}

    def _condition(self, item: dict, grid: LiftGrid):
        """-> (the denoiser's condition, the lifted volume where the refiner needs it (else None),
        depth probabilities, their ground-truth bins)."""
        if self.refiner is None:
            cond, probs, target = self.conditioner(item, grid)
            return cond, None, probs, target
        lifted, probs, target = self.conditioner.lift_volume(item, grid)
        return self.conditioner.down(lifted), lifted, probs, target

    def _decode(self, z: torch.Tensor, lifted: torch.Tensor | None):
        """Scaled latent (1, Cz, X', Y', Z') -> the coarse decoder's (occupancy logits per level, final
        occupancy logits, label logits), the last two refined where the model has a refiner."""
        occ_levels, occ_final, lab = self.vae.decode(z * self.vae.latent_std)
        if self.refiner is not None:
            occ_final, lab = self.refiner(lifted, occ_levels, occ_final, lab)
        return occ_levels, occ_final, lab

    # -- inference
    def sample_latent(self, cond, shape: tuple[int, ...], steps: int | None = None, seed: int = 0) -> torch.Tensor:
        """x_0 of `shape` (scaled latent): DDIM from seeded noise (diffusion) or one pass (predictor)."""
        last = self.schedule.steps - 1
        if self.cfg.mode == "predictor":
            return self._v(torch.zeros(shape), cond, torch.full((1,), last))
        noise = torch.randn(shape, generator=torch.Generator().manual_seed(int(seed)))
        return ddim_sample(lambda x, t: self._v(x, cond, torch.full((1,), t)), noise, self.schedule,
                           steps or self.cfg.sample_steps)

    def predict_from_depth(self, item: dict):
        """The 2D-prior baseline: each valid feature pixel's most likely depth bin (this network's
        own depth head) unprojected to its bin centre, and the level's voxels those points fall in;
        no 3D prior, no semantics (label 0). -> (ijk (V, 3), labels (V,))."""
        self._check_level(item)
        _, probs, _ = self.conditioner(item, item["lift_grid"])
        stride = self.conditioner.encoder.stride
        n, d, h, w = probs.shape
        grid = item["gt_grid"]
        best = probs.argmax(1)  # (N, h, w)
        flat = []
        for i in range(n):
            pts = frustum_points(feature_intrinsics(item["intrinsics"][i], stride), item["distortion"][i],
                                 item["cam_to_chunk"][i].double(), h, w, self.conditioner.bin_centres)
            p = pts.gather(0, best[i][None, :, :, None].expand(1, h, w, 3))[0]  # (h, w, 3)
            rows = torch.clamp(torch.arange(h) * stride + stride // 2, max=item["valid"].shape[1] - 1)
            cols = torch.clamp(torch.arange(w) * stride + stride // 2, max=item["valid"].shape[2] - 1)
            index, inside = grid.voxel_index(p)
            flat.append(index[inside & item["valid"][i][rows][:, cols]])
        keys = torch.unique(torch.cat(flat)) if flat else torch.zeros(0, dtype=torch.int64)
        _, y, z = grid.dims
        ijk = torch.stack([keys // (y * z), (keys // z) % y, keys % z], 1)
        return ijk, torch.zeros(len(ijk), dtype=torch.int64)

    def predict_with_confidence(self, item: dict, k: int = 1, steps: int | None = None, seed: int = 0,
                                coarse=None, observed: bool = True):
        """`predict` with seed `seed` -> (ijk (V, 3), labels (V,), confidence (V,) float32 the share
        of the k samples drawn with seeds seed .. seed + k - 1 that hold the voxel (1 when k = 1:
        only the first sample is drawn), observed (V,) bool whether an input camera sees the voxel
        first along one of its rays, traced through the predicted grid itself, `observed_voxels`).
        The coarse single-step predictor draws no samples (each would be the same grid): its
        confidence is the decoder's occupancy probability of the voxel, the product over the
        voxel and its ancestors (each level's sigmoid; with a refiner, the refined voxel's sigmoid
        alone), whatever k is. observed False: None instead
        of the trace (a caller that refines the grid traces its own)."""
        if k < 1:
            raise InputError(f"k: expected at least one sample, got {k}")
        if self.cfg.mode == "predictor" and not self.fine:
            ijk, labels, prob = self._predict_coarse(item, steps, seed)
            return ijk, labels, prob.float(), observed_voxels(ijk, item["gt_grid"], item) if observed else None
        ijk, labels = self.predict(item, steps, seed, coarse)
        count = torch.ones(len(ijk), dtype=torch.int64)
        keys = flat_keys(ijk, item["gt_grid"].dims)
        for extra in range(1, k):
            other, _ = self.predict(item, steps, seed + extra, coarse)
            count += torch.isin(keys, flat_keys(other, item["gt_grid"].dims)).to(torch.int64)
        seen = observed_voxels(ijk, item["gt_grid"], item) if observed else None
        return ijk, labels, (count.double() / k).float(), seen

    def _predict_coarse(self, item: dict, steps: int | None, seed: int):
        """The coarse level: (ijk (V, 3), labels (V,), occupancy probability (V,) of each voxel and
        all its ancestors, the product of their sigmoids)."""
        vol, lifted, _, _ = self._condition(item, item["lift_grid"])
        z = self.sample_latent(vol, (1, self.cfg.vae.latent_channels, *vol.shape[2:]), steps, seed)
        occ_levels, occ_final, lab = self._decode(z, lifted)
        if self.refiner is not None:  # the refined logit decides alone: it saw every ancestor's
            occ_levels = []
        ijks, labs = prune_decode(occ_levels, occ_final, lab)
        ijk = ijks[0]
        logp = F.logsigmoid(occ_final[0])[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
        for logits in occ_levels:
            s = occ_final.shape[-1] // logits.shape[-1]
            p = ijk // s
            logp = logp + F.logsigmoid(logits[0])[p[:, 0], p[:, 1], p[:, 2]]
        return ijk, labs[0], logp.exp()

    def predict(self, item: dict, steps: int | None = None, seed: int = 0, coarse=None):
        """One sample -> (ijk (V, 3) int64 in the level's box voxels, labels (V,)). coarse: the
        fine level's latent grid (ijk, labels) at the coarse voxel size (default: the item's
        ground truth, which evaluates the fine level alone)."""
        self._check_level(item)
        if not self.fine:
            ijk, labels, _ = self._predict_coarse(item, steps, seed)
            return ijk, labels
        vol, _, _ = self.conditioner(item, item["lift_grid"])
        lat = self.cfg.vae.latent_channels
        sites, site_labels = coarse if coarse is not None else (item["coarse_gt_ijk"], item["coarse_gt_labels"])
        if not len(sites):
            return torch.zeros(0, 3, dtype=torch.int64), torch.zeros(0, dtype=torch.int64)
        st = SparseTensor.from_coords(torch.cat([torch.zeros(len(sites), 1, dtype=torch.int64), sites], 1),
                                      torch.zeros(len(sites), lat), batch_size=1, stride=self.vae.stride)
        st_sites = st.coords[:, 1:]
        cond = (st, self.conditioner.site_condition(vol, st_sites, self._site_labels(st_sites, sites, site_labels),
                                                    item["lift_grid"]))
        z = self.sample_latent(cond, (len(st), lat), steps, seed)
        coords, labels = decoded_voxels(self.vae.decode(st.replace(z * self.vae.latent_std)))
        return coords[:, 1:], labels


# ---------------------------------------------------------------------------- stages
def flat_keys(ijk: torch.Tensor, dims) -> torch.Tensor:
    """(V, 3) box voxel indices -> (V,) int64 i * Y * Z + j * Z + k."""
    _, y, z = (int(d) for d in dims)
    return (ijk[:, 0] * y + ijk[:, 1]) * z + ijk[:, 2]


def observed_voxels(ijk: torch.Tensor, grid: LiftGrid, item: dict, stride: int = 4) -> torch.Tensor:
    """(V,) bool: whether voxel ijk[v] of `grid` is the first voxel of the grid itself along a ray
    of an input camera (rays through the centres of each image's stride x stride pixel blocks,
    distortion included). Needs no depth map: the grid's own voxels occlude, so it applies to a
    prediction from real photographs as to a worlds sample."""
    out = torch.zeros(len(ijk), dtype=torch.bool)
    if not len(ijk):
        return out
    caster = VoxelRayCaster(ijk, grid.voxel_size, grid.origin)
    for i in range(len(item["intrinsics"])):
        h, w = (-(-int(v) // stride) for v in item["image_size"][i])
        dirs = camera_ray_directions(feature_intrinsics(item["intrinsics"][i], stride), item["distortion"][i],
                                     item["cam_to_chunk"][i], h, w).reshape(-1, 3).double()
        origin = torch.as_tensor(item["cam_to_chunk"][i])[:3, 3].double().expand_as(dirs)
        hit, _ = caster.first_hit(origin, dirs)
        out[hit[hit >= 0]] = True
    return out


