"""The geometry stage's networks (`geometry.py` wires them to data and the trainer): the dense
structure VAE of a level and the dense denoiser U-Net, with their building blocks and losses.

Tensors are dense boxes (B, C, X, Y, Z) of one level's voxels (chunk frame axes: x forward, y
left, z up). A structure VAE halves the box L = len(widths) times to its latent and decodes it
back level by level, predicting occupancy at each: a voxel exists where it and every ancestor is
occupied (subdivide and prune). The last level's 8 children per voxel come from a per-parent
linear head (occupancy and label logits), so no convolution runs at the finest resolution.
Optionally (`VAEConfig`) a stem at the grid's own resolution precedes the first halving and the
decoder has its own block count (the XCube VAE's layout: its first level runs at the input
resolution, and its decoder weighs about 1.7 times its encoder).

The denoiser (`Denoiser3d`) is a 3D U-Net with a timestep embedding in one of two layouts:
``plain`` (the original: `blocks` residual blocks per level on both sides, strided / transposed
2x2x2 convolutions between levels, one middle block) and ``ldm`` (the latent-diffusion /
XCube UNet: `blocks` per encoder level and `blocks` + 1 per decoder level, residual blocks that
average-pool / nearest-upsample between levels, scale-shift (FiLM) timestep conditioning, a
middle of two residual blocks). Either can add multi-head self-attention over the voxels of
chosen levels (`SelfAttention3d`).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from pydantic import Field
from torch import nn

from ...config import StrictModel
from ...labels import NUM_LABELS
from ..nn.dense import ResBlock3d, group_norm

DENOISER_LAYOUTS = ("plain", "ldm")


class VAEConfig(StrictModel):
    """Structure VAE: widths per level below the grid (L = len(widths) halvings), residual blocks
    per level, latent channels (paper: 8), the KL weight, group-norm groups.

    Optional layout (None everywhere: the original layout, and the original state-dict keys):
    `input_width`: channels of a stem at the grid's own resolution (a 3x3x3 convolution and
    `blocks` residual blocks) before the first halving, as the paper's (XCube's) VAE whose first
    level runs at the input resolution: "base 64, multipliers 1, 2, 4" over a 256^3 grid with a
    64^3 latent is input_width 64, widths (128, 256). `decoder_blocks`: residual blocks per
    decoder level (None: max(1, blocks)). The defaults are None, not 0, so that a resolved
    config of the original layout compares equal, key by key, to one written before these
    fields existed (a run started then still resumes; its VAE checkpoint still matches)."""

    widths: tuple[int, ...] = Field(default=(32, 64), min_length=1, max_length=4)
    blocks: int = Field(default=1, ge=0)
    latent_channels: int = Field(default=8, ge=1)
    kl_weight: float = Field(default=1e-4, ge=0)
    groups: int = Field(default=8, ge=1)
    input_width: int | None = Field(default=None, ge=1)
    decoder_blocks: int | None = Field(default=None, ge=1)
    # The last level's children: None, one 1x1x1 head for the 8 children's occupancy and labels of
    # each voxel; 3, their occupancy from a 3x3x3 convolution (a surface's neighbours say which
    # children it passes through) and their labels from a 1x1x1 one.
    child_kernel: int | None = Field(default=None, ge=1, le=3)


class SelfAttention3d(nn.Module):
    """Multi-head self-attention over all voxels of a box (LDM's AttentionBlock): (B, C, X, Y, Z)
    -> x + proj(attention(qkv(norm(x)))), the same shape. No positional encoding: the block is
    equivariant to any permutation of the voxels (the convolutions around it know the layout).
    The output projection starts at zero, so a new block begins as the identity."""

    def __init__(self, channels: int, heads: int, groups: int):
        super().__init__()
        if heads < 1 or channels % heads:
            raise ValueError(f"attention: {channels} channels do not split into {heads} heads")
        self.heads = heads
        self.norm = group_norm(channels, groups)
        self.qkv = nn.Conv3d(channels, 3 * channels, 1)
        self.proj = nn.Conv3d(channels, channels, 1)
        nn.init.zeros_(self.proj.weight)
        nn.init.zeros_(self.proj.bias)

    def forward(self, x):
        b, c, *size = x.shape
        n = math.prod(size)
        qkv = self.qkv(self.norm(x)).reshape(b, 3, self.heads, c // self.heads, n).transpose(3, 4)
        q, k, v = qkv.unbind(1)  # each (B, heads, N, C / heads)
        out = F.scaled_dot_product_attention(q, k, v)
        return x + self.proj(out.transpose(2, 3).reshape(b, c, *size))


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """(B,) steps -> (B, dim) sinusoidal embedding (Transformer / DDPM)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32) / half)
    a = t.float()[:, None] * freqs[None]
    return torch.cat([torch.sin(a), torch.cos(a)], 1)


# ---------------------------------------------------------------------------- structure VAE
class StructureVAE(nn.Module):
    """Dense structure VAE of one level (module docstring). Input occupancy (B, X, Y, Z) and labels
    (B, X, Y, Z) (-1 empty); X, Y, Z divisible by 2^L."""

    def __init__(self, cfg: VAEConfig):
        super().__init__()
        self.cfg = cfg
        w, g, lat = cfg.widths, cfg.groups, cfg.latent_channels
        self.levels = len(w)
        cin = 1 + NUM_LABELS
        self.stem = None
        if cfg.input_width is not None:  # the first level, at the grid's own resolution
            self.stem = nn.ModuleList([nn.Conv3d(cin, cfg.input_width, 3, padding=1)] +
                                      [ResBlock3d(cfg.input_width, cfg.input_width, g) for _ in range(cfg.blocks)])
            cin = cfg.input_width
        down = []
        for c in w:
            down.append(nn.ModuleList([nn.Conv3d(cin, c, 2, stride=2)] + [ResBlock3d(c, c, g) for _ in range(cfg.blocks)]))
            cin = c
        self.down = nn.ModuleList(down)
        self.to_latent = nn.Sequential(group_norm(w[-1], g), nn.SiLU(), nn.Conv3d(w[-1], 2 * lat, 1))
        self.from_latent = nn.Conv3d(lat, w[-1], 3, padding=1)
        dec_blocks = cfg.decoder_blocks if cfg.decoder_blocks is not None else max(1, cfg.blocks)
        self.dec_blocks = nn.ModuleList()
        self.occ_heads = nn.ModuleList()
        self.up = nn.ModuleList()
        for i in range(self.levels - 1, -1, -1):  # decoder levels at stride 2^(i+1), coarsest first
            self.dec_blocks.append(nn.ModuleList([ResBlock3d(w[i], w[i], g) for _ in range(dec_blocks)]))
            self.occ_heads.append(nn.Conv3d(w[i], 1, 1))
            if i > 0:
                self.up.append(nn.ConvTranspose3d(w[i], w[i - 1], 2, stride=2))
        if cfg.child_kernel is None:
            self.child_head = nn.Sequential(group_norm(w[0], g), nn.SiLU(), nn.Conv3d(w[0], 8 * (1 + NUM_LABELS), 1))
            self.child_labels = None
        else:
            k = cfg.child_kernel
            self.child_head = nn.Sequential(group_norm(w[0], g), nn.SiLU(), nn.Conv3d(w[0], 8, k, padding=k // 2))
            self.child_labels = nn.Conv3d(w[0], 8 * NUM_LABELS, 1)
        # running RMS of the posterior means: the diffusion works on latents / latent_std
        self.register_buffer("latent_std", torch.ones(()))
        self.register_buffer("_latent_sq", torch.zeros(()))
        self.register_buffer("_latent_n", torch.zeros((), dtype=torch.float64))

    @property
    def stride(self) -> int:
        return 2 ** self.levels

    def encode(self, occ: torch.Tensor, labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (mu, logvar) (B, latent, X / 2^L, Y / 2^L, Z / 2^L)."""
        onehot = F.one_hot(labels.clamp_min(0), NUM_LABELS).permute(0, 4, 1, 2, 3).to(occ.dtype) * occ[:, None]
        x = torch.cat([occ[:, None], onehot], 1)
        x = run_encoder(x, self.stem, self.down)
        mu, logvar = self.to_latent(x).chunk(2, 1)
        return mu, logvar.clamp(-30.0, 20.0)

    def decode(self, z: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
        """Latent (B, latent, ...) -> (occupancy logits per level, coarsest first, each (B, X / s,
        Y / s, Z / s) for s = 2^L .. 2; final occupancy logits (B, X, Y, Z); label logits (B, L,
        X, Y, Z))."""
        x = self.from_latent(z)
        occ = []
        for i, blocks in enumerate(self.dec_blocks):
            for b in blocks:
                x = b(x)
            occ.append(self.occ_heads[i](x)[:, 0])
            if i < len(self.up):
                x = self.up[i](x)
        if self.child_labels is None:
            y = self.child_head(x)  # (B, 8 (1 + L), X/2, Y/2, Z/2): 8 children per voxel
            b, _, X, Y, Z = y.shape
            y = y.reshape(b, 2, 2, 2, 1 + NUM_LABELS, X, Y, Z)
        else:
            occ_c = self.child_head(x)
            b, _, X, Y, Z = occ_c.shape
            lab_c = self.child_labels(F.silu(self.child_head[0](x)))
            y = torch.cat([occ_c.reshape(b, 2, 2, 2, 1, X, Y, Z), lab_c.reshape(b, 2, 2, 2, NUM_LABELS, X, Y, Z)], 4)
        y = y.permute(0, 4, 5, 1, 6, 2, 7, 3)
        y = y.reshape(b, 1 + NUM_LABELS, 2 * X, 2 * Y, 2 * Z)
        return occ, y[:, 0], y[:, 1:]

    def forward(self, occ, labels, sample: bool = True):
        mu, logvar = self.encode(occ, labels)
        if self.training:
            with torch.no_grad():  # running RMS of the posterior means over training
                track_latent_rms(self, mu)
        z = mu + torch.randn_like(mu) * (0.5 * logvar).exp() if sample else mu
        return (mu, logvar) + self.decode(z)

    def loss(self, occ, labels) -> tuple[torch.Tensor, dict]:
        """Structure BCE at every level (targets: max-pooled occupancy) + label cross-entropy on the
        occupied voxels + kl_weight KL; the mean over the batch."""
        mu, logvar, occ_levels, occ_final, lab_logits = self(occ, labels)
        bce = structure_bce(occ_levels, occ_final, occ)
        ce = label_ce(lab_logits, labels)
        kl = 0.5 * (mu.pow(2) + logvar.exp() - 1 - logvar).mean()
        loss = bce + ce + self.cfg.kl_weight * kl
        return loss, {"bce": float(bce.detach()), "ce": float(ce.detach()), "kl": float(kl.detach())}


def structure_bce(occ_levels: list[torch.Tensor], occ_final: torch.Tensor, occ: torch.Tensor) -> torch.Tensor:
    """Mean BCE of the final occupancy plus each coarser level against the max-pooled target."""
    total = F.binary_cross_entropy_with_logits(occ_final, occ)
    for logits in occ_levels:
        s = occ.shape[-1] // logits.shape[-1]
        target = F.max_pool3d(occ[:, None], s)[:, 0]
        total = total + F.binary_cross_entropy_with_logits(logits, target)
    return total


def label_ce(lab_logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of the label logits (B, L, X, Y, Z) on the occupied voxels (labels >= 0)."""
    ok = labels >= 0
    if not bool(ok.any()):
        return lab_logits.sum() * 0.0
    return F.cross_entropy(lab_logits.permute(0, 2, 3, 4, 1)[ok], labels[ok])


def prune_decode(occ_levels: list[torch.Tensor], occ_final: torch.Tensor, lab_logits: torch.Tensor,
                 threshold: float = 0.0) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Per sample: (ijk (V, 3) int64, labels (V,) int64) of the voxels predicted occupied (logit >
    threshold) whose every ancestor is predicted occupied too (the hierarchy's pruning)."""
    keep = occ_final > threshold
    for logits in occ_levels:
        s = occ_final.shape[-1] // logits.shape[-1]
        up = (logits > threshold)
        for d in (1, 2, 3):
            up = up.repeat_interleave(s, dim=d)
        keep = keep & up
    ijks, labs = [], []
    for b in range(keep.shape[0]):
        ijk = torch.nonzero(keep[b])
        ijks.append(ijk)
        labs.append(lab_logits[b].argmax(0)[ijk[:, 0], ijk[:, 1], ijk[:, 2]])
    return ijks, labs


class OccupancyRefiner(nn.Module):
    """The coarse level's last step at the voxels' own resolution: the frozen decoder's logits and
    the lifted image volume in, corrections to the final occupancy and label logits out.

    The latent sits 2^L voxels apart (3.2 m against 0.8 m in the cpu configs), so whatever the
    lifted features say about where inside a latent cell a surface lies reaches the output only
    through the decoder's learnt code. Here it enters directly: a 1x1x1 projection of [lifted
    volume, final occupancy logit, every coarser level's logit repeated to the voxels, label
    logits] to `width` channels, a residual pair of 3x3x3 convolutions, a 1x1x1 head. The head
    starts at zero, so an untrained refiner returns the decoder's logits unchanged."""

    def __init__(self, lifted: int, levels: int, width: int):
        super().__init__()
        self.proj = nn.Conv3d(lifted + 1 + levels + NUM_LABELS, width, 1)
        self.body = nn.Sequential(nn.SiLU(), nn.Conv3d(width, width, 3, padding=1), nn.SiLU(),
                                  nn.Conv3d(width, width, 3, padding=1))
        self.head = nn.Conv3d(width, 1 + NUM_LABELS, 1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, lifted: torch.Tensor, occ_levels: list[torch.Tensor], occ_final: torch.Tensor,
                lab_logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """lifted (B, C, X, Y, Z) on the final level's voxels; the decoder's outputs (`StructureVAE.decode`)
        -> refined (final occupancy logits (B, X, Y, Z), label logits (B, L, X, Y, Z))."""
        if lifted.shape[2:] != occ_final.shape[1:]:
            raise ValueError(f"refiner: lifted volume {tuple(lifted.shape[2:])} and decoded grid "
                             f"{tuple(occ_final.shape[1:])} differ in size")
        ups = [F.interpolate(logits[:, None], size=occ_final.shape[1:], mode="nearest") for logits in occ_levels]
        h = self.proj(torch.cat([lifted, occ_final[:, None], *ups, lab_logits], 1))
        d = self.head(F.silu(h + self.body(h)))
        return occ_final + d[:, 0], lab_logits + d[:, 1:]


class Denoiser3d(nn.Module):
    """Dense 3D U-Net: (latent (B, Cz, ...) noisy, condition (B, Cc, ...), t (B,)) -> (B, Cz, ...).

    `widths` per level (level 0: the latent's resolution, halving between levels; the box's sides
    must divide by 2^(len(widths) - 1)), `blocks` residual blocks per level, `layout` ``plain`` or
    ``ldm`` (module docstring). `attention_levels`: levels with multi-head self-attention
    (`heads` heads; the level's width must divide by it) after each of their residual blocks, in
    the encoder and the decoder, and in the middle (between its blocks in ``ldm``) when the
    deepest level is listed. Self-attention over a level of N voxels costs O(N^2): list only
    small levels. With no attention the modules and the computation are the original ones."""

    def __init__(self, latent: int, cond: int, widths: tuple[int, ...], blocks: int, groups: int,
                 attention_levels: tuple[int, ...] = (), heads: int = 8, layout: str = "plain"):
        super().__init__()
        levels = len(widths)
        attn = check_unet_options(widths, attention_levels, layout)
        ldm = layout == "ldm"
        emb = 4 * widths[0]
        self.emb_dim = widths[0]

        def res(cin: int, cout: int, resample: str | None = None) -> ResBlock3d:
            return ResBlock3d(cin, cout, groups, emb, scale_shift=ldm, resample=resample)

        def att(channels: int, level: int) -> nn.Module:
            return SelfAttention3d(channels, heads, groups) if level in attn else nn.Identity()

        self.time = nn.Sequential(nn.Linear(widths[0], emb), nn.SiLU(), nn.Linear(emb, emb))
        self.inp = nn.Conv3d(latent + cond, widths[0], 3, padding=1)
        self.enc = nn.ModuleList()
        self.enc_attn = nn.ModuleList()  # one per `enc` block (Identity where a level has none)
        self.downs = nn.ModuleList()
        c = widths[0]
        skips = [c] if ldm else []  # ldm: the input convolution's output is a skip too
        for i, wd in enumerate(widths):
            for _ in range(blocks):
                self.enc.append(res(c, wd))
                c = wd
                self.enc_attn.append(att(c, i))
                skips.append(c)
            if i + 1 < levels:
                self.downs.append(res(c, c, "down") if ldm else nn.Conv3d(c, c, 2, stride=2))
                if ldm:
                    skips.append(c)
        self.mid = res(c, c)
        self.mid_attn = att(c, levels - 1)
        self.mid2 = res(c, c) if ldm else None
        self.dec = nn.ModuleList()
        self.dec_attn = nn.ModuleList()  # one per `dec` block
        self.ups = nn.ModuleList()
        self.dec_per_level = blocks + 1 if ldm else blocks
        for i, wd in reversed(list(enumerate(widths))):
            for _ in range(self.dec_per_level):
                self.dec.append(res(c + skips.pop(), wd))
                c = wd
                self.dec_attn.append(att(c, i))
            if i > 0:
                self.ups.append(res(c, c, "up") if ldm else nn.ConvTranspose3d(c, c, 2, stride=2))
        self.out = nn.Sequential(group_norm(c, groups), nn.SiLU(), nn.Conv3d(c, latent, 3, padding=1))
        nn.init.zeros_(self.out[-1].weight)
        nn.init.zeros_(self.out[-1].bias)
        if ldm:  # LDM zero-initialises every residual branch's last convolution
            for m in self.modules():
                if isinstance(m, ResBlock3d):
                    nn.init.zeros_(m.c2.weight)
                    nn.init.zeros_(m.c2.bias)
        self.widths, self.blocks, self.layout = widths, blocks, layout
        self.attention_levels = tuple(sorted(attn))

    def forward(self, z, cond, t):
        e = self.time(timestep_embedding(t, self.emb_dim))
        x = self.inp(torch.cat([z, cond], 1))
        ldm = self.layout == "ldm"
        hs, k = ([x] if ldm else []), 0
        for i in range(len(self.widths)):
            for _ in range(self.blocks):
                x = self.enc_attn[k](self.enc[k](x, e))
                k += 1
                hs.append(x)
            if i < len(self.downs):
                x = self.downs[i](x, e) if ldm else self.downs[i](x)
                if ldm:
                    hs.append(x)
        x = self.mid_attn(self.mid(x, e))
        if self.mid2 is not None:
            x = self.mid2(x, e)
        k = 0
        for j in range(len(self.widths)):
            for _ in range(self.dec_per_level):
                x = self.dec_attn[k](self.dec[k](torch.cat([x, hs.pop()], 1), e))
                k += 1
            if j < len(self.ups):
                x = self.ups[j](x, e) if ldm else self.ups[j](x)
        return self.out(x)


def track_latent_rms(vae: nn.Module, mu: torch.Tensor) -> None:
    """Fold one training batch's posterior means into a VAE's `latent_std`: the RMS of mu over
    every batch so far (buffers `_latent_sq` the running sum of mean(mu^2), `_latent_n` the count).
    `geometry.calibrate_latent_std` replaces it by the final encoder's RMS over a dataset."""
    vae._latent_sq += mu.detach().pow(2).mean()
    vae._latent_n += 1
    vae.latent_std.copy_((vae._latent_sq / vae._latent_n).sqrt().clamp_min(1e-3))


def check_unet_options(widths, attention_levels, layout: str) -> set[int]:
    """The denoisers' (dense and sparse) layout and attention levels, checked: -> the set of levels."""
    if layout not in DENOISER_LAYOUTS:
        raise ValueError(f"layout: expected one of {', '.join(DENOISER_LAYOUTS)}, got {layout!r}")
    levels = len(widths)
    attn = set(attention_levels)
    bad = sorted(a for a in attn if not 0 <= a < levels)
    if bad:
        raise ValueError(f"attention_levels {bad}: a U-Net of {levels} widths has levels 0 to {levels - 1}")
    return attn


def run_encoder(x, stem, down):
    """A structure VAE's encoder, dense or sparse: the optional stem (its first module, then its
    blocks), then each level's strided convolution and blocks."""
    if stem is not None:
        for m in stem:
            x = m(x)
    for conv, *blocks in down:
        x = conv(x)
        for b in blocks:
            x = b(x)
    return x
