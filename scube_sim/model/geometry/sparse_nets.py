"""The geometry stage's fine-level networks, sparse (`sparse.py`): the fine structure VAE, whose
latent lives on the sites of the coarse grid, and the sparse denoiser U-Net on those sites.

Coordinates are the fine level's voxel indices; a site at stride s covers fine voxels s * o +
[0, s) (the sparse module's convention). With L = len(widths) halvings the latent grid is at
stride 2^L: the cpu profile's 0.2 m fine grid has its latent on the 0.8 m coarse sites, as the
official code uses the coarse output grid as the fine latent grid.

Decoding from the latent sites (stride 2^L) down: each site's 8 children are candidates whose
occupancy a per-site head predicts; the occupied ones (the ground truth's in training, the
prediction's at inference) get features by a transposed convolution onto them, and so on down to
stride 1, where the last head gives each child's occupancy and label logits directly (no
convolution runs on the finest grid). Optionally (`VAEConfig`) a stem at the fine grid's own
resolution precedes the first halving (`input_width`) and each decoder level has its own block
count (`decoder_blocks`), as `geometry_nets.StructureVAE` (`SparseStructureVAE` lists the
differences that remain).

The denoiser (`SparseDenoiser`) has the dense `Denoiser3d`'s two layouts: ``plain`` (the
original sparse U-Net) and ``ldm`` (XCube's / LDM's UNet, block for block the dense one's, with
sparse average pooling and nearest up-sampling onto the encoder's own grids between levels), and
optional multi-head self-attention over the active sites of each batch element
(`SparseSelfAttention`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ...errors import InputError
from ...labels import NUM_LABELS
from ..nn.sparse import (
    Grid,
    SparseConv3d,
    SparseConvTranspose3d,
    SparseLinear,
    SparseTensor,
    SubmanifoldConv3d,
    cat_features,
    kernel_offsets,
    make_norm,
    site_order,
)
from .dense_nets import VAEConfig, check_unet_options, run_encoder, timestep_embedding, track_latent_rms

_OFFS = kernel_offsets(2)  # (8, 3): child m of site o is 2 o + _OFFS[m]


def parent_rows(fine: Grid, coarse: Grid) -> torch.Tensor:
    """(len(fine),) int64: the row in `coarse` (twice the stride) of each fine site's parent
    (fine ijk // 2), cached on `fine`. Every parent must be a site of `coarse`."""
    def build():
        q = torch.cat([fine.coords[:, :1], torch.div(fine.coords[:, 1:], 2, rounding_mode="floor")], 1)
        rows = coarse.lookup(q)
        if bool((rows < 0).any()):
            raise InputError("sparse resampling: a site's parent is not on the coarser grid")
        return rows
    return fine.cached(("parent", coarse), build)


def avg_pool2(x: SparseTensor) -> SparseTensor:
    """2x2x2 average pooling onto the strided grid (`Grid.downsample(2, 2)`, the grid a strided
    2x2x2 convolution of `x` lands on): each parent gets the mean of its active children (dense
    `avg_pool3d` would count the empty children as zeros)."""
    coarse, _ = x.grid.downsample(2, 2)
    parent = parent_rows(x.grid, coarse)
    count = torch.bincount(parent, minlength=len(coarse)).clamp_min(1).to(x.feats.dtype)
    out = x.feats.new_zeros(len(coarse), x.num_channels).index_add(0, parent, x.feats)
    return SparseTensor(out / count[:, None], coarse)


def upsample_nearest2(x: SparseTensor, target: Grid) -> SparseTensor:
    """Nearest up-sampling onto `target`'s sites (half x's stride): each site takes its parent's
    features."""
    return SparseTensor(x.feats[parent_rows(target, x.grid)], target)


class SparseSiLU(nn.Module):
    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.replace(F.silu(x.feats))


class TimeResBlock(nn.Module):
    """Sparse pre-norm residual block (group norm, SiLU, 3^3 submanifold convolutions), adding a
    per-sample embedding (B, E) after the first convolution when `emb` > 0 (the sparse
    `model.nn.dense.ResBlock3d`, with the same modules and parameters). scale_shift: the
    embedding gives a scale and a shift of the second normalisation instead (FiLM). resample
    ``down`` / ``up``: the block moves both branches, after the first normalisation, to the
    2x2x2-pooled grid (`avg_pool2`) / onto `target`'s sites (`upsample_nearest2`)."""

    def __init__(self, cin: int, cout: int, groups: int, emb: int = 0, scale_shift: bool = False,
                 resample: str | None = None):
        super().__init__()
        if scale_shift and not emb:
            raise ValueError("scale_shift needs an embedding (emb > 0)")
        if resample not in (None, "down", "up"):
            raise ValueError(f"resample: expected None, 'down' or 'up', got {resample!r}")
        self.n1, self.c1 = make_norm("group", cin, groups), SubmanifoldConv3d(cin, cout, 3)
        self.n2, self.c2 = make_norm("group", cout, groups), SubmanifoldConv3d(cout, cout, 3)
        self.emb = nn.Linear(emb, (2 if scale_shift else 1) * cout) if emb else None
        self.skip = SparseLinear(cin, cout) if cin != cout else None
        self.scale_shift, self.resample = scale_shift, resample

    def forward(self, x: SparseTensor, emb: torch.Tensor | None = None, target: Grid | None = None) -> SparseTensor:
        h = x.replace(F.silu(self.n1(x).feats))
        if self.resample == "down":
            h, x = avg_pool2(h), avg_pool2(x)
        elif self.resample == "up":
            if target is None:
                raise ValueError("an up-sampling block needs the target grid")
            h, x = upsample_nearest2(h, target), upsample_nearest2(x, target)
        h = self.c1(h)
        if self.scale_shift:
            scale, shift = self.emb(emb)[h.grid.batch].chunk(2, 1)
            h = self.c2(h.replace(F.silu(self.n2(h).feats * (1 + scale) + shift)))
        else:
            if self.emb is not None:
                h = h.replace(h.feats + self.emb(emb)[x.grid.batch])
            h = self.c2(h.replace(F.silu(self.n2(h).feats)))
        s = self.skip(x).feats if self.skip is not None else x.feats
        return h.replace(h.feats + s)


class SparseSelfAttention(nn.Module):
    """Multi-head self-attention over the active sites of each batch element separately (the
    sparse `geometry_nets.SelfAttention3d`, the same parameters): x + proj(attention(qkv(norm(x)))).
    No positional encoding; the output projection starts at zero (a new block is the identity).
    One `scaled_dot_product_attention` per batch element (its sites are one contiguous run of
    rows, the grid's order): O(N_b^2) work, and O(N_b) memory where a fused kernel runs."""

    def __init__(self, channels: int, heads: int, groups: int):
        super().__init__()
        if heads < 1 or channels % heads:
            raise ValueError(f"attention: {channels} channels do not split into {heads} heads")
        self.heads = heads
        self.norm = make_norm("group", channels, groups)
        self.qkv = SparseLinear(channels, 3 * channels)
        self.proj = SparseLinear(channels, channels)
        nn.init.zeros_(self.proj.weight)
        nn.init.zeros_(self.proj.bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        n, c = x.feats.shape
        qkv = self.qkv(self.norm(x)).feats.reshape(n, 3, self.heads, c // self.heads)
        # group the rows by batch element: a grid's rows are sorted by batch, so each element's
        # are one contiguous run of grid.counts[b] rows
        runs = torch.bincount(x.grid.batch, minlength=x.batch_size).tolist()
        out = []
        for part in qkv.split(runs):
            if not len(part):
                continue
            q, k, v = part.permute(1, 2, 0, 3).unbind(0)  # each (heads, N_b, C / heads)
            out.append(F.scaled_dot_product_attention(q, k, v).transpose(0, 1).reshape(len(part), c))
        out = torch.cat(out) if out else x.feats.new_zeros(0, c)
        return x.replace(x.feats + self.proj(x.replace(out)).feats)


def child_coords(coords: torch.Tensor) -> torch.Tensor:
    """(N, 4) [b, i, j, k] sites -> (N, 8, 4) their children's, child m at 2 ijk + _OFFS[m]."""
    c = coords[:, None, 1:] * 2 + _OFFS[None]
    return torch.cat([coords[:, None, :1].expand(-1, 8, 1), c], 2)


def grid_of(coords: torch.Tensor, batch_size: int, stride: int) -> Grid:
    """A Grid of unsorted unique (N, 4) sites."""
    return Grid(coords[site_order(coords)], batch_size, stride, _sorted=True)


def row_ids(*arrays: torch.Tensor) -> list[torch.Tensor]:
    """One id per distinct row over all the (N_i, 4) int arrays: equal rows, equal ids, in the
    rows' lexicographic order (as torch.unique(dim=0) numbers them)."""
    rows = torch.cat(arrays)
    if len(rows):
        lo = rows.min(0).values
        span = rows.max(0).values - lo + 1
        bits = [int(v).bit_length() for v in span.tolist()]
        if sum(bits) <= 62:
            # Each column shifted to start at 0 and packed, the first most significant: one int64
            # per row in the same order, and a 1-D unique (torch.unique(dim=0) sorts rows
            # generically, a large share of a fine-VAE training step).
            key = torch.zeros(len(rows), dtype=torch.int64)
            for c, b in enumerate(bits):
                key = (key << b) | (rows[:, c].to(torch.int64) - lo[c])
            _, inv = torch.unique(key, return_inverse=True)
            return list(inv.split([len(a) for a in arrays]))
    _, inv = torch.unique(rows, dim=0, return_inverse=True)
    return list(inv.split([len(a) for a in arrays]))


def member(coords: torch.Tensor, of: torch.Tensor) -> torch.Tensor:
    """(N,) bool: each [b, i, j, k] row of `coords` is among the rows of `of`."""
    a, b = row_ids(coords, of)
    return torch.isin(a, b)


class SparseStructureVAE(nn.Module):
    """Fine structure VAE (module docstring). `encode` takes the fine voxels (N, 4) [b, i, j, k]
    with labels; the latent sites are their ancestors at stride 2^L.

    The optional layout of `VAEConfig`, as the dense `StructureVAE`'s: `input_width` adds a stem
    on the fine voxels themselves (a 3^3 submanifold convolution to input_width channels and
    `blocks` residual blocks) before the first halving; `decoder_blocks` gives each decoder level
    that many residual blocks (`dec` holds each level's first, `dec_more` the rest). Differences
    from the dense layout, all of the sparse decoding or kept for the original state-dict keys:
    decoder_blocks None is one block per level (dense: max(1, blocks)); the latent projections
    are per-site linear layers (dense: a norm and SiLU before `to_latent`, a 3^3 convolution for
    `from_latent`); each level's occupancy head predicts its 8 children's occupancy (the sites
    themselves are given), so the coarsest level has none of its own and the finest is the final
    head's; the final head has no norm before it. With input_width and decoder_blocks None the
    modules and the state-dict keys are the original ones."""

    def __init__(self, cfg: VAEConfig):
        super().__init__()
        self.cfg = cfg
        w, g, lat = cfg.widths, cfg.groups, cfg.latent_channels
        self.levels = len(w)
        cin = 1 + NUM_LABELS
        self.stem = None
        if cfg.input_width is not None:  # at the fine grid's own resolution (stride 1)
            self.stem = nn.ModuleList([SubmanifoldConv3d(cin, cfg.input_width, 3)] +
                                      [TimeResBlock(cfg.input_width, cfg.input_width, g) for _ in range(cfg.blocks)])
            cin = cfg.input_width
        self.down = nn.ModuleList()
        for c in w:
            self.down.append(nn.ModuleList([SparseConv3d(cin, c, 2, 2)] +
                                           [TimeResBlock(c, c, g) for _ in range(cfg.blocks)]))
            cin = c
        self.to_latent = SparseLinear(w[-1], 2 * lat)
        self.from_latent = SparseLinear(lat, w[-1])
        dec_levels = range(self.levels - 1, -1, -1)  # decoder levels at stride 2^(i+1), coarsest first
        more = (cfg.decoder_blocks if cfg.decoder_blocks is not None else 1) - 1
        self.dec = nn.ModuleList([TimeResBlock(w[i], w[i], g) for i in dec_levels])
        self.dec_more = nn.ModuleList([nn.ModuleList([TimeResBlock(w[i], w[i], g) for _ in range(more)])
                                       for i in dec_levels])
        # level i (stride 2^(i+1)) -> its children at stride 2^i: occupancy per child, and for i > 0
        # the kept children's features
        self.occ = nn.ModuleList([SparseLinear(w[i], 8) for i in range(self.levels - 1, 0, -1)])
        self.up = nn.ModuleList([SparseConvTranspose3d(w[i], w[i - 1], 2, 2) for i in range(self.levels - 1, 0, -1)])
        self.final = SparseLinear(w[0], 8 * (1 + NUM_LABELS))
        self.register_buffer("latent_std", torch.ones(()))
        self.register_buffer("_latent_sq", torch.zeros(()))
        self.register_buffer("_latent_n", torch.zeros((), dtype=torch.float64))

    @property
    def stride(self) -> int:
        return 2 ** self.levels

    def encode(self, coords: torch.Tensor, labels: torch.Tensor, batch_size: int) -> tuple[SparseTensor, torch.Tensor]:
        """Fine voxels -> (mu on the latent sites (stride 2^L), logvar (N, latent))."""
        feats = torch.cat([torch.ones(len(coords), 1), F.one_hot(labels, NUM_LABELS).float()], 1)
        x = SparseTensor.from_coords(coords, feats, batch_size=batch_size)
        x = run_encoder(x, self.stem, self.down)
        mu, logvar = self.to_latent(x).feats.chunk(2, 1)
        return x.replace(mu), logvar.clamp(-30.0, 20.0)

    def _dec_level(self, i: int, x: SparseTensor) -> SparseTensor:
        x = self.dec[i](x)
        for b in self.dec_more[i]:
            x = b(x)
        return x

    def decode(self, z: SparseTensor, target: torch.Tensor | None = None, threshold: float = 0.0):
        """Latent on its sites -> (candidate occupancy per level [(coords (M, 4), logits (M,))],
        coarsest first, the last at stride 1 with (M, L) label logits as a third element).
        target: the fine voxels (N, 4) to keep at every level (teacher forcing), else the
        prediction's (logit > threshold)."""
        x = self._dec_level(0, z.replace(self.from_latent(z).feats))
        out = []
        for i in range(self.levels - 1):
            logits = self.occ[i](x).feats.reshape(-1)  # (8 N,) in child order of each site
            cand = child_coords(x.coords).reshape(-1, 4)
            out.append((cand, logits))
            if target is not None:
                s = 2 ** (self.levels - 1 - i)  # stride of the candidates
                keep = member(cand, torch.cat([target[:, :1], target[:, 1:] // s], 1))
            else:
                keep = logits > threshold
            kept = grid_of(cand[keep], x.batch_size, x.stride // 2)
            x = self._dec_level(i + 1, self.up[i](x, kept))
        y = self.final(x).feats.reshape(len(x), 8, 1 + NUM_LABELS)
        cand = child_coords(x.coords).reshape(-1, 4)
        out.append((cand, y[..., 0].reshape(-1), y[..., 1:].reshape(-1, NUM_LABELS)))
        return out

    def forward(self, coords, labels, batch_size: int, sample: bool = True):
        mu, logvar = self.encode(coords, labels, batch_size)
        if self.training:
            with torch.no_grad():
                track_latent_rms(self, mu.feats)
        z = mu.feats + torch.randn_like(mu.feats) * (0.5 * logvar).exp() if sample else mu.feats
        return mu, logvar, self.decode(mu.replace(z), target=coords if self.training else None)

    def loss(self, coords, labels, batch_size: int) -> tuple[torch.Tensor, dict]:
        """BCE of every level's candidates against the ground truth's occupancy there, label
        cross-entropy on the occupied fine voxels, kl_weight KL; means over candidates."""
        mu, logvar, levels = self(coords, labels, batch_size)
        bce, ce = self.reconstruction_loss(levels, coords, labels)
        kl = 0.5 * (mu.feats.pow(2) + logvar.exp() - 1 - logvar).mean()
        loss = bce + ce + self.cfg.kl_weight * kl
        return loss, {"bce": float(bce.detach()), "ce": float(ce.detach()), "kl": float(kl.detach())}

    def reconstruction_loss(self, levels, coords: torch.Tensor, labels: torch.Tensor):
        """(structure BCE summed over the levels, label cross-entropy) of `decode`'s output
        against the fine voxels coords (N, 4) with labels (N,): each level's candidates scored
        against the ground truth's occupancy there (mean over candidates), labels on the
        candidates that are ground-truth voxels."""
        bce = 0.0
        for i, lv in enumerate(levels):
            cand, logits = lv[0], lv[1]
            s = 2 ** (self.levels - 1 - i)
            occ = member(cand, torch.cat([coords[:, :1], coords[:, 1:] // s], 1)).float()
            bce = bce + F.binary_cross_entropy_with_logits(logits, occ)
        cand, _, lab_logits = levels[-1]
        # labels of the candidates that are ground-truth voxels
        key, gkey = row_ids(cand, coords)
        order = torch.argsort(gkey)
        pos = torch.searchsorted(gkey[order], key).clamp_max(len(gkey) - 1)
        hit = gkey[order][pos] == key
        ce = F.cross_entropy(lab_logits[hit], labels[order][pos[hit]]) if bool(hit.any()) else lab_logits.sum() * 0
        return bce, ce


def decoded_voxels(levels, threshold: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The last level of `SparseStructureVAE.decode` -> (coords (V, 4) of the children predicted
    occupied, labels (V,))."""
    cand, logits, lab = levels[-1]
    keep = logits > threshold
    return cand[keep], lab[keep].argmax(1)


class SparseDenoiser(nn.Module):
    """Sparse U-Net with a timestep embedding: (latent + condition on the latent sites, t (B,)) ->
    v (N, latent). widths per level (halving between), `blocks` residual blocks per level.

    `layout` ``plain`` (the original: `stem`, per level `blocks` encoder blocks, a strided 2x2x2
    convolution changing the width between levels, a transposed one back onto the encoder's grid
    and `blocks` decoder blocks, no middle, a linear `head`) or ``ldm``: the dense `Denoiser3d`'s
    ldm layout block for block, with the same modules, names and parameter counts (XCube's /
    LDM's UNet: `blocks` per encoder level and `blocks` + 1 per decoder level, residual blocks
    that average-pool onto the strided grid / nearest-up-sample onto the encoder's grid between
    levels, scale-shift timestep conditioning, a middle of two blocks, zero-initialised residual
    branches). `attention_levels`: levels with multi-head self-attention over each batch
    element's sites (`heads` heads) after each of their residual blocks, in the encoder and the
    decoder, and (ldm) between the middle blocks when the deepest level is listed; the plain
    layout has no middle, and no decoder blocks at the deepest level. Self-attention over a level
    of N sites per element costs O(N^2): list only small levels. With layout plain and no
    attention the modules and the state-dict keys are the original ones."""

    def __init__(self, latent: int, cond: int, widths: tuple[int, ...], blocks: int, groups: int,
                 attention_levels: tuple[int, ...] = (), heads: int = 8, layout: str = "plain"):
        super().__init__()
        attn = check_unet_options(widths, attention_levels, layout)
        self.widths, self.blocks, self.layout = tuple(widths), blocks, layout
        self.attention_levels = tuple(sorted(attn))
        self.emb_dim = widths[0]
        emb = 4 * widths[0]

        def att(channels: int, level: int) -> nn.Module:
            return SparseSelfAttention(channels, heads, groups) if level in attn else nn.Identity()

        self.time = nn.Sequential(nn.Linear(widths[0], emb), nn.SiLU(), nn.Linear(emb, emb))
        if layout == "ldm":
            self._build_ldm(latent, cond, widths, blocks, groups, emb, att)
            return
        self.stem = SubmanifoldConv3d(latent + cond, widths[0], 3)
        self.enc, self.down, self.up, self.dec = nn.ModuleList(), nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        # one attention module per residual block (Identity where its level has none: no keys)
        self.enc_attn, self.dec_attn = nn.ModuleList(), nn.ModuleList()
        for i, w in enumerate(widths):
            self.enc.append(nn.ModuleList([TimeResBlock(w, w, groups, emb) for _ in range(blocks)]))
            self.enc_attn.append(nn.ModuleList([att(w, i) for _ in range(blocks)]))
            if i + 1 < len(widths):
                self.down.append(SparseConv3d(w, widths[i + 1], 2, 2))
        for i in range(len(widths) - 2, -1, -1):
            self.up.append(SparseConvTranspose3d(widths[i + 1], widths[i], 2, 2))
            self.dec.append(nn.ModuleList([TimeResBlock(2 * widths[i], widths[i], groups, emb)] +
                                          [TimeResBlock(widths[i], widths[i], groups, emb) for _ in range(blocks - 1)]))
            self.dec_attn.append(nn.ModuleList([att(widths[i], i) for _ in range(max(blocks, 1))]))
        self.head = SparseLinear(widths[0], latent)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def _build_ldm(self, latent, cond, widths, blocks, groups, emb, att) -> None:
        """The modules of `Denoiser3d`'s ldm layout (the same names), sparse."""
        levels = len(widths)

        def res(cin: int, cout: int, resample: str | None = None) -> TimeResBlock:
            return TimeResBlock(cin, cout, groups, emb, scale_shift=True, resample=resample)

        self.inp = SubmanifoldConv3d(latent + cond, widths[0], 3)
        self.enc, self.enc_attn, self.downs = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        c = widths[0]
        skips = [c]  # the input convolution's output is a skip too
        for i, wd in enumerate(widths):
            for _ in range(blocks):
                self.enc.append(res(c, wd))
                c = wd
                self.enc_attn.append(att(c, i))
                skips.append(c)
            if i + 1 < levels:
                self.downs.append(res(c, c, "down"))
                skips.append(c)
        self.mid = res(c, c)
        self.mid_attn = att(c, levels - 1)
        self.mid2 = res(c, c)
        self.dec, self.dec_attn, self.ups = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        self.dec_per_level = blocks + 1
        for i, wd in reversed(list(enumerate(widths))):
            for _ in range(self.dec_per_level):
                self.dec.append(res(c + skips.pop(), wd))
                c = wd
                self.dec_attn.append(att(c, i))
            if i > 0:
                self.ups.append(res(c, c, "up"))
        self.out = nn.Sequential(make_norm("group", c, groups), SparseSiLU(), SubmanifoldConv3d(c, latent, 3))
        nn.init.zeros_(self.out[-1].weight)
        nn.init.zeros_(self.out[-1].bias)
        for m in self.modules():  # LDM zero-initialises every residual branch's last convolution
            if isinstance(m, TimeResBlock):
                nn.init.zeros_(m.c2.weight)
                nn.init.zeros_(m.c2.bias)

    def forward(self, x: SparseTensor, t: torch.Tensor) -> SparseTensor:
        e = self.time(timestep_embedding(t, self.emb_dim))
        if self.layout == "ldm":
            return self._forward_ldm(x, e)
        h = self.stem(x)
        skips = []
        for i, (blocks, attns) in enumerate(zip(self.enc, self.enc_attn)):
            for b, a in zip(blocks, attns):
                h = a(b(h, e))
            if i < len(self.down):
                skips.append(h)
                h = self.down[i](h)
        for up, blocks, attns in zip(self.up, self.dec, self.dec_attn):
            skip = skips.pop()
            h = cat_features(up(h, skip), skip)
            for b, a in zip(blocks, attns):
                h = a(b(h, e))
        return self.head(h)

    def _forward_ldm(self, x: SparseTensor, e: torch.Tensor) -> SparseTensor:
        x = self.inp(x)
        hs, k = [x], 0
        for i in range(len(self.widths)):
            for _ in range(self.blocks):
                x = self.enc_attn[k](self.enc[k](x, e))
                k += 1
                hs.append(x)
            if i < len(self.downs):
                x = self.downs[i](x, e)  # onto x.grid.downsample(2, 2): the grid a strided conv makes
                hs.append(x)
        x = self.mid2(self.mid_attn(self.mid(x, e)), e)
        k = 0
        for j in range(len(self.widths)):
            for _ in range(self.dec_per_level):
                x = self.dec_attn[k](self.dec[k](cat_features(x, hs.pop()), e))
                k += 1
            if j < len(self.ups):
                x = self.ups[j](x, e, target=hs[-1].grid)  # back onto the encoder's grid of that level
        return self.out(x)


__all__ = ["SparseDenoiser", "SparseSelfAttention", "SparseStructureVAE", "TimeResBlock", "avg_pool2", "child_coords",
           "decoded_voxels", "member", "upsample_nearest2"]
