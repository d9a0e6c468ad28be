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

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field
from torch import nn

from ...config import StrictModel
from ...labels import reflectance_from_labels
from ...voxsplat import VoxSplat
from ...worlds.groundtruth import CHUNK_CORNER
from ..nn.activations import activate
from ..nn.encoding import positional_encoding
from ..nn.lpips import LPIPS, LPIPSConfig, load_lpips
from ..nn.sky import SkyDecoder, build_panorama, camera_ray_directions, panorama_directions, sample_panorama
from ..nn.sparse import SparseTensor, SparseUNet, voxel_keys
from ..nn.splat_render import rasterization
from ..nn.voxel_rays import VoxelRayCaster, deposit_mean

NUM_RAW = 14


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


