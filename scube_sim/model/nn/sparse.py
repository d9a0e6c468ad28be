"""Sparse voxel tensors and convolutions in pure PyTorch: they train on CPU and GPU alike.

A `SparseTensor` is features (N, C) on the active sites of a `Grid`: coords (N, 4) int64
[batch, i, j, k], sorted by batch, then by the VoxSplat key of (i, j, k) (the same packing as
`voxsplat.voxel_keys`, so a batch element's sites come in VoxSplat voxel order). Coordinates are
in the grid's own index space: a grid at stride s indexes voxels s times the finest size, and a
down-sampled voxel o covers the finer voxels s * o + [0, s).

Convolutions gather -> matmul -> scatter along kernel maps: for each kernel offset, the pairs
(input row, output row) it connects. A map is built once per pair of grids (hashed coordinates,
sorted keys and `searchsorted`) and cached on the grid, so every layer of a network that runs on
the same grids reuses it, and a transposed convolution back onto a grid reuses nothing it must
not: its map is looked up on its target.

Semantics (dense equivalents, cross-correlation as torch's conv3d; offsets delta in [0, k)^3 in
(i, j, k) order, weight (k^3, C_in, C_out)):

    submanifold   out[o] = sum_delta in[o + (delta - (k - 1) / 2) * dilation] W[delta],  o in the input sites
    strided       out[o] = sum_delta in[s * o + delta - p] W[delta],   o: every site reached
    transposed    out[s * i + delta - p] += in[i] W[delta],            at the target's sites (or every site reached)

Grids hold at most |i|, |j|, |k| < 2^20 (the key packing).
"""

from __future__ import annotations

import itertools
import math

import torch
import torch.nn.functional as F
from torch import nn

from ...errors import InputError

_BITS = 21
_BIAS = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def voxel_keys(ijk: torch.Tensor) -> torch.Tensor:
    """(N, 3) int64 voxel indices -> (N,) int64 keys that sort like (i, j, k); the packing of
    `scube_sim.voxsplat.voxel_keys`. |index| < 2^20."""
    b = ijk.long() + _BIAS
    return (b[:, 0] << (2 * _BITS)) | (b[:, 1] << _BITS) | b[:, 2]


def keys_to_ijk(keys: torch.Tensor) -> torch.Tensor:
    """(N,) keys -> (N, 3) int64 voxel indices (inverse of `voxel_keys`)."""
    return torch.stack([(keys >> (2 * _BITS)) & _MASK, (keys >> _BITS) & _MASK, keys & _MASK], 1) - _BIAS


def _in_range(ijk: torch.Tensor) -> torch.Tensor:
    return (ijk.abs() < _BIAS).all(dim=1)


def kernel_offsets(kernel: int, device=None) -> torch.Tensor:
    """(k^3, 3) int64 offsets delta in [0, k)^3, in (i, j, k) row-major order (the weight order)."""
    return torch.tensor(list(itertools.product(range(kernel), repeat=3)), dtype=torch.int64, device=device)


class KernelMap:
    """Pairs (input row, output row) per kernel offset: in_idx[k], out_idx[k] (P_k,) int64."""

    def __init__(self, in_idx: list[torch.Tensor], out_idx: list[torch.Tensor]):
        self.in_idx, self.out_idx = in_idx, out_idx

    def transposed(self) -> KernelMap:
        return KernelMap(self.out_idx, self.in_idx)

    @property
    def num_pairs(self) -> int:
        return sum(int(i.numel()) for i in self.in_idx)


class Grid:
    """The active sites of a batch at one stride, with the kernel maps that start or end here.

    coords (N, 4) int64 [batch, i, j, k], unique, sorted by (batch, key); stride: this grid's
    voxel size in finest voxels; batch_size: number of batch elements (some may be empty)."""

    def __init__(self, coords: torch.Tensor, batch_size: int, stride: int = 1, *, _sorted: bool = False):
        coords = torch.as_tensor(coords).long()
        if coords.ndim != 2 or coords.shape[1] != 4:
            raise InputError(f"coords: expected shape (N, 4) [batch, i, j, k], got {tuple(coords.shape)}")
        if coords.numel() and not bool(_in_range(coords[:, 1:]).all()):
            raise InputError("coords: voxel indices beyond +-2^20 (the key packing's range)")
        if coords.numel() and (int(coords[:, 0].min()) < 0 or int(coords[:, 0].max()) >= batch_size):
            raise InputError(f"coords: batch indices must lie in [0, {batch_size})")
        self.batch_size, self.stride = int(batch_size), int(stride)
        keys = voxel_keys(coords[:, 1:])
        if not _sorted:
            order = torch.argsort(keys, stable=True)
            order = order[torch.argsort(coords[order, 0], stable=True)]
            coords, keys = coords[order], keys[order]
        if coords.shape[0] > 1:
            same = (coords[1:, 0] == coords[:-1, 0]) & (keys[1:] == keys[:-1])
            if bool(same.any()):
                raise InputError("coords: duplicate sites (use unique_coords first)")
        self.coords, self.keys = coords, keys
        counts = torch.bincount(coords[:, 0], minlength=self.batch_size) if coords.numel() else \
            torch.zeros(self.batch_size, dtype=torch.int64, device=coords.device)
        self.starts = torch.cumsum(counts, 0) - counts
        self.counts = counts
        self._maps: dict = {}

    def __len__(self) -> int:
        return int(self.coords.shape[0])

    @property
    def device(self) -> torch.device:
        return self.coords.device

    @property
    def batch(self) -> torch.Tensor:
        """(N,) int64 batch index of each site."""
        return self.coords[:, 0]

    def lookup(self, query: torch.Tensor) -> torch.Tensor:
        """(Q, 4) [batch, i, j, k] -> (Q,) int64 row of each query site in this grid, -1 if absent."""
        out = torch.full((query.shape[0],), -1, dtype=torch.int64, device=query.device)
        if not len(self) or not query.shape[0]:
            return out
        ok = _in_range(query[:, 1:]) & (query[:, 0] >= 0) & (query[:, 0] < self.batch_size)
        qkeys = torch.where(ok, voxel_keys(torch.where(ok[:, None], query[:, 1:], 0)), 0)
        for b in range(self.batch_size):
            n = int(self.counts[b])
            if n == 0:
                continue
            s = int(self.starts[b])
            sel = torch.nonzero(ok & (query[:, 0] == b)).squeeze(1)
            if not sel.numel():
                continue
            seg = self.keys[s:s + n]
            pos = torch.searchsorted(seg, qkeys[sel]).clamp_max(n - 1)
            hit = seg[pos] == qkeys[sel]
            out[sel[hit]] = s + pos[hit]
        return out

    def cached(self, key, build):
        """The value cached under `key`, built by `build()` on first use."""
        if key not in self._maps:
            self._maps[key] = build()
        return self._maps[key]

    # --- kernel maps -------------------------------------------------------------------------
    def _search_own_rows(self, qkeys: torch.Tensor) -> torch.Tensor:
        """(N,) keys, one per row of this grid and in the same batch -> (N,) row of each key in
        this grid, -1 if absent (queries aligned with the rows need no batch selection)."""
        out = torch.full_like(qkeys, -1)
        for b in range(self.batch_size):
            n, s = int(self.counts[b]), int(self.starts[b])
            if n == 0:
                continue
            seg, q = self.keys[s:s + n], qkeys[s:s + n]
            pos = torch.searchsorted(seg, q).clamp_max(n - 1)
            out[s:s + n] = torch.where(seg[pos] == q, s + pos, -1)
        return out

    def submanifold_map(self, kernel: int, dilation: int = 1) -> KernelMap:
        """Map of a submanifold convolution on this grid (odd kernel)."""
        def build():
            c = (kernel - 1) // 2
            ins, outs = [], []
            rows = torch.arange(len(self), device=self.device)
            reach = c * dilation
            # A shift of every index by d moves every key by key(d) - key(0) while no index leaves
            # its 21-bit field: then the neighbour keys are one addition away.
            fast = not len(self) or int(self.coords[:, 1:].abs().max()) + reach < _BIAS
            for d in kernel_offsets(kernel, self.device):
                shift = (d - c) * dilation
                if not bool(shift.any()):
                    ins.append(rows), outs.append(rows)
                    continue
                if fast:
                    dk = (int(shift[0]) << (2 * _BITS)) + (int(shift[1]) << _BITS) + int(shift[2])
                    idx = self._search_own_rows(self.keys + dk)
                else:
                    q = self.coords.clone()
                    q[:, 1:] += shift
                    idx = self.lookup(q)
                hit = idx >= 0
                ins.append(idx[hit]), outs.append(rows[hit])
            return KernelMap(ins, outs)
        return self.cached(("subm", kernel, dilation), build)

    def downsample(self, kernel: int, stride: int, padding: int = 0) -> tuple[Grid, KernelMap]:
        """The grid and map of a strided convolution from this grid: output sites are every o
        with s * o + delta - p active for some delta (cached: the same grid object each time)."""
        def build():
            offs = kernel_offsets(kernel, self.device)
            outs_c, valid = [], []
            for d in offs:
                num = self.coords[:, 1:] - d + padding
                ok = (num % stride == 0).all(dim=1)
                o = torch.cat([self.coords[:, :1], torch.div(num, stride, rounding_mode="floor")], 1)
                outs_c.append(o), valid.append(ok)
            allc = torch.cat([o[v] for o, v in zip(outs_c, valid)])
            out_grid = Grid(unique_coords(allc), self.batch_size, self.stride * stride, _sorted=True)
            rows = torch.arange(len(self), device=self.device)
            ins, outs = [], []
            for o, v in zip(outs_c, valid):
                ins.append(rows[v]), outs.append(out_grid.lookup(o[v]))
            return out_grid, KernelMap(ins, outs)
        return self.cached(("down", kernel, stride, padding), build)

    def upsample_map(self, coarse: Grid, kernel: int, stride: int, padding: int = 0) -> KernelMap:
        """Map of a transposed convolution from `coarse` onto this grid's sites:
        out[s * i + delta - p] += in[i] W[delta] (cached on this grid, the target)."""
        def build():
            rows = torch.arange(len(self), device=self.device)
            ins, outs = [], []
            for d in kernel_offsets(kernel, self.device):
                num = self.coords[:, 1:] + padding - d
                ok = (num % stride == 0).all(dim=1)
                q = torch.cat([self.coords[:, :1], torch.div(num, stride, rounding_mode="floor")], 1)
                idx = torch.where(ok, coarse.lookup(q), -1)
                hit = idx >= 0
                ins.append(idx[hit]), outs.append(rows[hit])
            return KernelMap(ins, outs)
        return self.cached(("up", kernel, stride, padding, coarse), build)

    def upsample(self, kernel: int, stride: int, padding: int = 0) -> tuple[Grid, KernelMap]:
        """Every site a transposed convolution from this grid reaches, and its map."""
        def build():
            offs = kernel_offsets(kernel, self.device)
            cand = [torch.cat([self.coords[:, :1], self.coords[:, 1:] * stride + d - padding], 1) for d in offs]
            fine = Grid(unique_coords(torch.cat(cand)), self.batch_size, max(self.stride // stride, 1), _sorted=True)
            return fine, fine.upsample_map(self, kernel, stride, padding)
        return self.cached(("up-all", kernel, stride, padding), build)


def site_order(coords: torch.Tensor) -> torch.Tensor:
    """(N,) permutation that sorts (N, 4) [batch, i, j, k] sites by (batch, key): a grid's order."""
    coords = torch.as_tensor(coords).long()
    if not coords.shape[0]:
        return torch.zeros(0, dtype=torch.int64, device=coords.device)
    order = torch.argsort(voxel_keys(coords[:, 1:]), stable=True)
    return order[torch.argsort(coords[order, 0], stable=True)]


def unique_coords(coords: torch.Tensor) -> torch.Tensor:
    """(N, 4) [batch, i, j, k] -> the unique rows, sorted by (batch, key)."""
    coords = coords.long()
    if not coords.shape[0]:
        return coords.reshape(0, 4)
    parts = []
    for b in torch.unique(coords[:, 0]).tolist():
        k = torch.unique(voxel_keys(coords[coords[:, 0] == b, 1:]))  # sorted
        parts.append(torch.cat([torch.full((k.shape[0], 1), b, dtype=torch.int64, device=coords.device),
                                keys_to_ijk(k)], 1))
    return torch.cat(parts)


class SparseTensor:
    """Features on a grid's active sites: feats (N, C) float, row n at grid.coords[n]."""

    def __init__(self, feats: torch.Tensor, grid: Grid):
        if feats.ndim != 2 or feats.shape[0] != len(grid):
            raise InputError(f"feats: expected shape ({len(grid)}, C) for a grid of {len(grid)} sites, "
                             f"got {tuple(feats.shape)}")
        self.feats, self.grid = feats, grid

    @classmethod
    def from_coords(cls, coords: torch.Tensor, feats: torch.Tensor, batch_size: int | None = None,
                    stride: int = 1) -> SparseTensor:
        """Unsorted (N, 4) [batch, i, j, k] sites with their (N, C) features (no duplicates)."""
        coords = torch.as_tensor(coords).long()
        if coords.shape[0] != feats.shape[0]:
            raise InputError(f"coords and feats: {coords.shape[0]} sites but {feats.shape[0]} feature rows")
        b = int(coords[:, 0].max()) + 1 if batch_size is None and coords.numel() else (batch_size or 1)
        order = site_order(coords)
        return cls(feats[order], Grid(coords[order], b, stride, _sorted=True))

    @property
    def coords(self) -> torch.Tensor:
        return self.grid.coords

    @property
    def stride(self) -> int:
        return self.grid.stride

    @property
    def batch_size(self) -> int:
        return self.grid.batch_size

    @property
    def num_channels(self) -> int:
        return int(self.feats.shape[1])

    def __len__(self) -> int:
        return len(self.grid)

    def replace(self, feats: torch.Tensor) -> SparseTensor:
        """Same sites (and cached maps), new features."""
        return SparseTensor(feats, self.grid)

    def to_dense(self, origin: torch.Tensor | None = None, shape: tuple[int, int, int] | None = None) -> tuple:
        """(B, C, D, H, W) dense tensor with zeros off the sites, and its origin (3,): dense index
        = ijk - origin. Default: the bounding box of the sites."""
        ijk = self.coords[:, 1:]
        if origin is None:
            origin = ijk.min(0).values if len(self) else torch.zeros(3, dtype=torch.int64)
        if shape is None:
            shape = tuple((ijk.max(0).values - origin + 1).tolist()) if len(self) else (1, 1, 1)
        d = ijk - origin
        if len(self) and (bool((d < 0).any()) or any(int(d[:, a].max()) >= shape[a] for a in range(3))):
            raise InputError("to_dense: sites outside the requested box")
        dense = self.feats.new_zeros((self.batch_size, self.num_channels) + tuple(shape))
        dense[self.coords[:, 0], :, d[:, 0], d[:, 1], d[:, 2]] = self.feats
        return dense, origin


def cat_features(*tensors: SparseTensor) -> SparseTensor:
    """Concatenate the channels of tensors on the same grid."""
    g = tensors[0].grid
    if any(t.grid is not g for t in tensors):
        raise InputError("cat_features: the tensors lie on different grids")
    return SparseTensor(torch.cat([t.feats for t in tensors], 1), g)


class _KernelMapConv(torch.autograd.Function):
    """Gather -> matmul -> scatter along a kernel map, with a backward that recomputes the
    gathers instead of keeping one gathered copy of the input per kernel offset."""

    @staticmethod
    def forward(ctx, feats, weight, kmap: KernelMap, num_out: int):
        out = feats.new_zeros((num_out, weight.shape[2]))
        for k, (i_idx, o_idx) in enumerate(zip(kmap.in_idx, kmap.out_idx)):
            if not i_idx.numel():
                continue
            if o_idx is i_idx:  # the identity offset of a submanifold map: no gather, no scatter
                out.addmm_(feats, weight[k])
            else:
                out.index_add_(0, o_idx, feats.index_select(0, i_idx) @ weight[k])
        ctx.save_for_backward(feats, weight)
        ctx.kmap = kmap
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        feats, weight = ctx.saved_tensors
        grad_out = grad_out.contiguous()
        need_x, need_w = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        gx = torch.zeros_like(feats) if need_x else None
        gw = torch.zeros_like(weight) if need_w else None
        for k, (i_idx, o_idx) in enumerate(zip(ctx.kmap.in_idx, ctx.kmap.out_idx)):
            if not i_idx.numel():
                continue
            same = o_idx is i_idx
            g = grad_out if same else grad_out.index_select(0, o_idx)
            if need_w:
                x = feats if same else feats.index_select(0, i_idx)
                gw[k] = x.T @ g
            if need_x:
                if same:
                    gx.addmm_(g, weight[k].T)
                else:
                    gx.index_add_(0, i_idx, g @ weight[k].T)
        return gx, gw, None, None


def apply_kernel_map(feats: torch.Tensor, weight: torch.Tensor, kmap: KernelMap, num_out: int) -> torch.Tensor:
    """Gather -> matmul -> scatter: (N_in, C_in) features, (K, C_in, C_out) weight -> (num_out, C_out)."""
    if feats.dtype != weight.dtype:
        raise InputError(f"sparse convolution: features are {feats.dtype} but the weight is {weight.dtype}")
    return _KernelMapConv.apply(feats, weight, kmap, num_out)


class _SparseConvBase(nn.Module):
    def __init__(self, in_channels: int, out_channels: int, kernel: int, bias: bool):
        super().__init__()
        self.in_channels, self.out_channels, self.kernel = in_channels, out_channels, kernel
        self.weight = nn.Parameter(torch.empty(kernel ** 3, in_channels, out_channels))
        self.bias = nn.Parameter(torch.zeros(out_channels)) if bias else None
        bound = 1.0 / math.sqrt(in_channels * kernel ** 3)  # torch's conv default (kaiming, a = sqrt 5)
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            nn.init.uniform_(self.bias, -bound, bound)

    def _run(self, x: SparseTensor, kmap: KernelMap, grid: Grid) -> SparseTensor:
        if x.num_channels != self.in_channels:
            raise InputError(f"{type(self).__name__}: expected {self.in_channels} input channels, got {x.num_channels}")
        out = apply_kernel_map(x.feats, self.weight, kmap, len(grid))
        if self.bias is not None:
            out = out + self.bias
        return SparseTensor(out, grid)

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, kernel={self.kernel}, bias={self.bias is not None}"


class SubmanifoldConv3d(_SparseConvBase):
    """Convolution that keeps the active sites (odd kernel, 'same' padding)."""

    def __init__(self, in_channels: int, out_channels: int, kernel: int = 3, dilation: int = 1, bias: bool = True):
        if kernel % 2 == 0:
            raise InputError(f"SubmanifoldConv3d: kernel must be odd, got {kernel}")
        super().__init__(in_channels, out_channels, kernel, bias)
        self.dilation = dilation

    def forward(self, x: SparseTensor) -> SparseTensor:
        return self._run(x, x.grid.submanifold_map(self.kernel, self.dilation), x.grid)


class SparseConv3d(_SparseConvBase):
    """Strided convolution: the output grid is every coarse site the kernel reaches."""

    def __init__(self, in_channels: int, out_channels: int, kernel: int = 2, stride: int = 2, padding: int = 0,
                 bias: bool = True):
        super().__init__(in_channels, out_channels, kernel, bias)
        self.stride, self.padding = stride, padding

    def forward(self, x: SparseTensor) -> SparseTensor:
        grid, kmap = x.grid.downsample(self.kernel, self.stride, self.padding)
        return self._run(x, kmap, grid)


class SparseConvTranspose3d(_SparseConvBase):
    """Transposed convolution (up-sampling) onto `target`'s sites (typically the finer grid an
    encoder came from), or onto every site it reaches when no target is given."""

    def __init__(self, in_channels: int, out_channels: int, kernel: int = 2, stride: int = 2, padding: int = 0,
                 bias: bool = True):
        super().__init__(in_channels, out_channels, kernel, bias)
        self.stride, self.padding = stride, padding

    def forward(self, x: SparseTensor, target: Grid | SparseTensor | None = None) -> SparseTensor:
        if target is None:
            grid, kmap = x.grid.upsample(self.kernel, self.stride, self.padding)
        else:
            grid = target.grid if isinstance(target, SparseTensor) else target
            kmap = grid.upsample_map(x.grid, self.kernel, self.stride, self.padding)
        return self._run(x, kmap, grid)


# --- structure: subdivide and prune --------------------------------------------------------------

def subdivide(x: SparseTensor) -> tuple[SparseTensor, torch.Tensor]:
    """Each site -> its 2 x 2 x 2 children at half the stride (coords 2 * ijk + [0, 1]^3), with
    the parent's features. Returns the children and (8N,) int64 parent row of each child."""
    offs = kernel_offsets(2, x.grid.device)
    n = len(x)
    child = (x.coords[:, None, 1:] * 2 + offs[None]).reshape(-1, 3)
    batch = x.coords[:, 0].repeat_interleave(8)
    parent = torch.arange(n, device=x.grid.device).repeat_interleave(8)
    # Sorting by (batch, key) keeps a batch element's children in key order; parents are unique,
    # so children are too.
    keys = voxel_keys(child)
    order = torch.argsort(keys, stable=True)
    order = order[torch.argsort(batch[order], stable=True)]
    coords = torch.cat([batch[order, None], child[order]], 1)
    grid = Grid(coords, x.batch_size, max(x.stride // 2, 1), _sorted=True)
    return SparseTensor(x.feats[parent[order]], grid), parent[order]


def prune(x: SparseTensor, keep: torch.Tensor) -> SparseTensor:
    """The sites where keep (N,) bool is true (order kept, so still sorted)."""
    if keep.shape != (len(x),):
        raise InputError(f"prune: keep must have shape ({len(x)},), got {tuple(keep.shape)}")
    idx = torch.nonzero(keep).squeeze(1)
    return SparseTensor(x.feats[idx], Grid(x.coords[idx], x.batch_size, x.stride, _sorted=True))


# --- normalisation over active sites --------------------------------------------------------------

class SparseBatchNorm(nn.BatchNorm1d):
    """Batch norm with statistics over every active site of the batch."""

    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        return x.replace(super().forward(x.feats))


class SparseGroupNorm(nn.Module):
    """Group norm per batch element over its active sites (empty sites do not count)."""

    def __init__(self, num_groups: int, num_channels: int, eps: float = 1e-5, affine: bool = True):
        super().__init__()
        if num_channels % num_groups:
            raise InputError(f"SparseGroupNorm: {num_channels} channels do not split into {num_groups} groups")
        self.num_groups, self.num_channels, self.eps = num_groups, num_channels, eps
        self.weight = nn.Parameter(torch.ones(num_channels)) if affine else None
        self.bias = nn.Parameter(torch.zeros(num_channels)) if affine else None

    def forward(self, x: SparseTensor) -> SparseTensor:
        n, c = x.feats.shape
        g = self.num_groups
        f = x.feats.reshape(n, g, c // g)
        b = x.grid.batch
        count = (x.grid.counts.clamp_min(1) * (c // g)).to(f.dtype)[:, None]  # (B, 1)
        mean = f.new_zeros(x.batch_size, g).index_add(0, b, f.sum(2)) / count
        cen = f - mean[b][:, :, None]
        var = f.new_zeros(x.batch_size, g).index_add(0, b, (cen * cen).sum(2)) / count
        out = (cen / torch.sqrt(var[b][:, :, None] + self.eps)).reshape(n, c)
        if self.weight is not None:
            out = out * self.weight + self.bias
        return x.replace(out)


def make_norm(kind: str, channels: int, groups: int = 8) -> nn.Module:
    """'batch' | 'group' (groups capped to divide the channels) | 'none'."""
    if kind == "batch":
        return SparseBatchNorm(channels)
    if kind == "group":
        return SparseGroupNorm(math.gcd(groups, channels), channels)
    if kind == "none":
        return SparseIdentity()
    raise InputError(f"norm: expected 'batch', 'group' or 'none', got {kind!r}")


class SparseIdentity(nn.Module):
    def forward(self, x: SparseTensor) -> SparseTensor:
        return x


class SparseReLU(nn.Module):
    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.replace(F.relu(x.feats))


class SparseLinear(nn.Linear):
    """A per-site linear layer (a 1 x 1 x 1 convolution)."""

    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        return x.replace(super().forward(x.feats))


# --- the U-Net ------------------------------------------------------------------------------------

class SparseResBlock(nn.Module):
    """conv-norm-relu-conv-norm plus the input (projected when the width changes), then relu."""

    def __init__(self, in_channels: int, out_channels: int, norm: str = "batch", kernel: int = 3):
        super().__init__()
        self.conv1 = SubmanifoldConv3d(in_channels, out_channels, kernel, bias=False)
        self.norm1 = make_norm(norm, out_channels)
        self.conv2 = SubmanifoldConv3d(out_channels, out_channels, kernel, bias=False)
        self.norm2 = make_norm(norm, out_channels)
        self.skip = SparseLinear(in_channels, out_channels, bias=False) if in_channels != out_channels else None

    def forward(self, x: SparseTensor) -> SparseTensor:
        h = SparseReLU()(self.norm1(self.conv1(x)))
        h = self.norm2(self.conv2(h))
        s = self.skip(x) if self.skip is not None else x
        return h.replace(F.relu(h.feats + s.feats))


class SparseUNet(nn.Module):
    """Sparse U-Net: widths[l] channels at stride 2^l, `blocks` residual blocks per level on each
    side, strided (k = 2, s = 2) down-sampling and transposed up-sampling back onto the encoder's
    own grids, skip connections by concatenation. Output: out_channels on the input's sites.

    Depth = len(widths); SCube's appearance network is base 32 with multipliers 1, 2, 4."""

    def __init__(self, in_channels: int, out_channels: int, widths: tuple[int, ...] = (32, 64, 128), blocks: int = 1,
                 norm: str = "batch", kernel: int = 3):
        super().__init__()
        if not widths:
            raise InputError("SparseUNet: widths must name at least one level")
        self.widths = tuple(int(w) for w in widths)
        self.stem = SubmanifoldConv3d(in_channels, self.widths[0], kernel)
        self.enc = nn.ModuleList()
        self.down = nn.ModuleList()
        self.up = nn.ModuleList()
        self.dec = nn.ModuleList()
        for lvl, w in enumerate(self.widths):
            self.enc.append(nn.Sequential(*[SparseResBlock(w, w, norm, kernel) for _ in range(blocks)]))
            if lvl + 1 < len(self.widths):
                self.down.append(nn.Sequential(SparseConv3d(w, self.widths[lvl + 1], 2, 2, bias=False),
                                               make_norm(norm, self.widths[lvl + 1]), SparseReLU()))
        for lvl in range(len(self.widths) - 2, -1, -1):
            w = self.widths[lvl]
            self.up.append(SparseConvTranspose3d(self.widths[lvl + 1], w, 2, 2, bias=False))
            self.dec.append(nn.Sequential(SparseResBlock(2 * w, w, norm, kernel),
                                          *[SparseResBlock(w, w, norm, kernel) for _ in range(blocks - 1)]))
        self.up_norm = nn.ModuleList([make_norm(norm, self.widths[lvl])
                                      for lvl in range(len(self.widths) - 2, -1, -1)])
        self.head = SparseLinear(self.widths[0], out_channels)

    def forward(self, x: SparseTensor) -> SparseTensor:
        h = self.stem(x)
        skips = []
        for lvl, block in enumerate(self.enc):
            h = block(h)
            if lvl < len(self.down):
                skips.append(h)
                h = self.down[lvl](h)
        for up, norm, dec in zip(self.up, self.up_norm, self.dec):
            skip = skips.pop()
            h = SparseReLU()(norm(up(h, skip)))
            h = dec(cat_features(h, skip))
        return self.head(h)
