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
convolution runs on the finest grid).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..labels import LABEL_NAMES
from .geometry_nets import VAEConfig, timestep_embedding, track_latent_rms
from .sparse import (Grid, SparseConv3d, SparseConvTranspose3d, SparseLinear, SparseTensor, SubmanifoldConv3d,
                     cat_features, kernel_offsets, make_norm, site_order)

NUM_LABELS = len(LABEL_NAMES)
_OFFS = kernel_offsets(2)  # (8, 3): child m of site o is 2 o + _OFFS[m]


class TimeResBlock(nn.Module):
    """Sparse pre-norm residual block (group norm, SiLU, 3^3 submanifold convolutions), adding a
    per-sample embedding (B, E) after the first convolution when `emb` > 0."""

    def __init__(self, cin: int, cout: int, groups: int, emb: int = 0):
        super().__init__()
        self.n1, self.c1 = make_norm("group", cin, groups), SubmanifoldConv3d(cin, cout, 3)
        self.n2, self.c2 = make_norm("group", cout, groups), SubmanifoldConv3d(cout, cout, 3)
        self.emb = nn.Linear(emb, cout) if emb else None
        self.skip = SparseLinear(cin, cout) if cin != cout else None

    def forward(self, x: SparseTensor, emb: torch.Tensor | None = None) -> SparseTensor:
        h = self.c1(x.replace(F.silu(self.n1(x).feats)))
        if self.emb is not None:
            h = h.replace(h.feats + self.emb(emb)[x.grid.batch])
        h = self.c2(h.replace(F.silu(self.n2(h).feats)))
        s = self.skip(x).feats if self.skip is not None else x.feats
        return h.replace(h.feats + s)


def child_coords(coords: torch.Tensor) -> torch.Tensor:
    """(N, 4) [b, i, j, k] sites -> (N, 8, 4) their children's, child m at 2 ijk + _OFFS[m]."""
    c = coords[:, None, 1:] * 2 + _OFFS[None]
    return torch.cat([coords[:, None, :1].expand(-1, 8, 1), c], 2)


def grid_of(coords: torch.Tensor, batch_size: int, stride: int) -> Grid:
    """A Grid of unsorted unique (N, 4) sites."""
    return Grid(coords[site_order(coords)], batch_size, stride, _sorted=True)


def row_ids(*arrays: torch.Tensor) -> list[torch.Tensor]:
    """One id per distinct row over all the (N_i, 4) int arrays: equal rows, equal ids."""
    _, inv = torch.unique(torch.cat(arrays), dim=0, return_inverse=True)
    return list(inv.split([len(a) for a in arrays]))


def member(coords: torch.Tensor, of: torch.Tensor) -> torch.Tensor:
    """(N,) bool: each [b, i, j, k] row of `coords` is among the rows of `of`."""
    a, b = row_ids(coords, of)
    return torch.isin(a, b)


class SparseStructureVAE(nn.Module):
    """Fine structure VAE (module docstring). `encode` takes the fine voxels (N, 4) [b, i, j, k]
    with labels; the latent sites are their ancestors at stride 2^L."""

    def __init__(self, cfg: VAEConfig):
        super().__init__()
        if cfg.input_width is not None or cfg.decoder_blocks is not None:
            raise ValueError("vae: the sparse (fine) structure VAE does not implement input_width / decoder_blocks")
        self.cfg = cfg
        w, g, lat = cfg.widths, cfg.groups, cfg.latent_channels
        self.levels = len(w)
        self.down = nn.ModuleList()
        cin = 1 + NUM_LABELS
        for c in w:
            self.down.append(nn.ModuleList([SparseConv3d(cin, c, 2, 2)] +
                                           [TimeResBlock(c, c, g) for _ in range(cfg.blocks)]))
            cin = c
        self.to_latent = SparseLinear(w[-1], 2 * lat)
        self.from_latent = SparseLinear(lat, w[-1])
        self.dec = nn.ModuleList([TimeResBlock(w[i], w[i], g) for i in range(self.levels - 1, -1, -1)])
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
        for conv, *blocks in self.down:
            x = conv(x)
            for b in blocks:
                x = b(x)
        mu, logvar = self.to_latent(x).feats.chunk(2, 1)
        return x.replace(mu), logvar.clamp(-30.0, 20.0)

    def decode(self, z: SparseTensor, target: torch.Tensor | None = None, threshold: float = 0.0):
        """Latent on its sites -> (candidate occupancy per level [(coords (M, 4), logits (M,))],
        coarsest first, the last at stride 1 with (M, L) label logits as a third element).
        target: the fine voxels (N, 4) to keep at every level (teacher forcing), else the
        prediction's (logit > threshold)."""
        x = self.dec[0](z.replace(self.from_latent(z).feats))
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
            x = self.dec[i + 1](self.up[i](x, kept))
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
        kl = 0.5 * (mu.feats.pow(2) + logvar.exp() - 1 - logvar).mean()
        loss = bce + ce + self.cfg.kl_weight * kl
        return loss, {"bce": float(bce.detach()), "ce": float(ce.detach()), "kl": float(kl.detach())}


def decoded_voxels(levels, threshold: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The last level of `SparseStructureVAE.decode` -> (coords (V, 4) of the children predicted
    occupied, labels (V,))."""
    cand, logits, lab = levels[-1]
    keep = logits > threshold
    return cand[keep], lab[keep].argmax(1)


class SparseDenoiser(nn.Module):
    """Sparse U-Net with a timestep embedding: (latent + condition on the latent sites, t (B,)) ->
    v (N, latent). widths per level (halving between), `blocks` residual blocks per level."""

    def __init__(self, latent: int, cond: int, widths: tuple[int, ...], blocks: int, groups: int):
        super().__init__()
        self.emb_dim = widths[0]
        emb = 4 * widths[0]
        self.time = nn.Sequential(nn.Linear(widths[0], emb), nn.SiLU(), nn.Linear(emb, emb))
        self.stem = SubmanifoldConv3d(latent + cond, widths[0], 3)
        self.enc, self.down, self.up, self.dec = nn.ModuleList(), nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        for i, w in enumerate(widths):
            self.enc.append(nn.ModuleList([TimeResBlock(w, w, groups, emb) for _ in range(blocks)]))
            if i + 1 < len(widths):
                self.down.append(SparseConv3d(w, widths[i + 1], 2, 2))
        for i in range(len(widths) - 2, -1, -1):
            self.up.append(SparseConvTranspose3d(widths[i + 1], widths[i], 2, 2))
            self.dec.append(nn.ModuleList([TimeResBlock(2 * widths[i], widths[i], groups, emb)] +
                                          [TimeResBlock(widths[i], widths[i], groups, emb) for _ in range(blocks - 1)]))
        self.head = SparseLinear(widths[0], latent)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, x: SparseTensor, t: torch.Tensor) -> SparseTensor:
        e = self.time(timestep_embedding(t, self.emb_dim))
        h = self.stem(x)
        skips = []
        for i, blocks in enumerate(self.enc):
            for b in blocks:
                h = b(h, e)
            if i < len(self.down):
                skips.append(h)
                h = self.down[i](h)
        for up, blocks in zip(self.up, self.dec):
            skip = skips.pop()
            h = cat_features(up(h, skip), skip)
            for b in blocks:
                h = b(h, e)
        return self.head(h)


__all__ = ["SparseDenoiser", "SparseStructureVAE", "TimeResBlock", "child_coords", "decoded_voxels", "member"]
