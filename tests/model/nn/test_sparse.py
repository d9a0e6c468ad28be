"""Sparse tensors and convolutions against torch's dense conv3d / conv_transpose3d on small
densified grids (values and gradients, random shapes), and the structure operations against
their definitions."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from scube_sim.errors import InputError
from scube_sim.model.nn.sparse import (
    Grid,
    SparseBatchNorm,
    SparseConv3d,
    SparseConvTranspose3d,
    SparseGroupNorm,
    SparseTensor,
    SparseUNet,
    SubmanifoldConv3d,
    keys_to_ijk,
    prune,
    subdivide,
    unique_coords,
    voxel_keys,
)
from scube_sim.voxsplat import unique_voxels
from scube_sim.voxsplat import voxel_keys as np_voxel_keys

SIDE = 7  # sites lie in [lo, lo + SIDE)^3: the dense grids stay tiny
LO = 4


def random_sparse(seed: int, n: int, channels: int, batch: int, side: int = SIDE, lo: int = 0) -> SparseTensor:
    g = torch.Generator().manual_seed(seed)
    c = torch.cat([torch.randint(0, batch, (n, 1), generator=g), torch.randint(lo, lo + side, (n, 3), generator=g)], 1)
    c = unique_coords(c)
    perm = torch.randperm(len(c), generator=g)  # from_coords must sort whatever order it gets
    feats = torch.randn(len(c), channels, generator=g, dtype=torch.float64)
    return SparseTensor.from_coords(c[perm], feats[perm], batch_size=batch)


def dense_weight(w: torch.Tensor, k: int, transposed: bool = False) -> torch.Tensor:
    """(k^3, C_in, C_out) sparse weight -> conv3d (C_out, C_in, k, k, k) or conv_transpose3d
    (C_in, C_out, k, k, k) weight; the offsets run (i, j, k) row-major like the dense axes."""
    _, ci, co = w.shape
    if transposed:
        return w.permute(1, 2, 0).reshape(ci, co, k, k, k)
    return w.permute(2, 1, 0).reshape(co, ci, k, k, k)


def at_sites(dense: torch.Tensor, coords: torch.Tensor, origin) -> torch.Tensor:
    d = coords[:, 1:] - torch.as_tensor(origin)
    return dense[coords[:, 0], :, d[:, 0], d[:, 1], d[:, 2]]


def leaf(x: SparseTensor) -> SparseTensor:
    return x.replace(x.feats.clone().requires_grad_(True))


# --- keys --------------------------------------------------------------------------------------


def test_keys_are_the_voxsplat_packing_and_order():
    rng = np.random.default_rng(0)
    ijk = rng.integers(-(1 << 20) + 1, 1 << 20, (500, 3))
    np.testing.assert_array_equal(voxel_keys(torch.from_numpy(ijk)).numpy(), np_voxel_keys(ijk))
    np.testing.assert_array_equal(keys_to_ijk(voxel_keys(torch.from_numpy(ijk))).numpy(), ijk)
    small = rng.integers(-5, 5, (300, 3))
    x = SparseTensor.from_coords(unique_coords(torch.cat([torch.zeros(300, 1, dtype=torch.long),
                                                          torch.from_numpy(small)], 1)),
                                 torch.zeros(len(np.unique(small, axis=0)), 1))
    uniq, _, _ = unique_voxels(small)
    np.testing.assert_array_equal(x.coords[:, 1:].numpy(), uniq)  # VoxSplat's voxel order


def test_lookup_finds_sites_and_misses_others():
    x = random_sparse(1, 80, 1, 2)
    g = x.grid
    assert torch.equal(g.lookup(g.coords), torch.arange(len(g)))
    miss = g.coords.clone()
    miss[:, 1] += 100
    far = torch.tensor([[0, 1 << 21, 0, 0], [5, 0, 0, 0], [-1, 0, 0, 0]])
    assert bool((g.lookup(miss) == -1).all()) and bool((g.lookup(far) == -1).all())


def test_bad_grids_are_refused():
    with pytest.raises(InputError, match="duplicate"):
        Grid(torch.tensor([[0, 1, 2, 3], [0, 1, 2, 3]]), 1)
    with pytest.raises(InputError, match="2\\^20"):
        Grid(torch.tensor([[0, 1 << 20, 0, 0]]), 1)
    with pytest.raises(InputError, match="batch"):
        Grid(torch.tensor([[2, 0, 0, 0]]), 2)
    with pytest.raises(InputError, match="shape"):
        SparseTensor(torch.zeros(3, 2), Grid(torch.tensor([[0, 0, 0, 0]]), 1))


# --- convolutions against dense ones -----------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 120), cin=st.integers(1, 5), cout=st.integers(1, 5),
       batch=st.integers(1, 3), kernel=st.sampled_from([1, 3, 5]), dilation=st.sampled_from([1, 2]))
def test_submanifold_matches_dense_conv3d(seed, n, cin, cout, batch, kernel, dilation):
    x = leaf(random_sparse(seed, n, cin, batch))
    conv = SubmanifoldConv3d(cin, cout, kernel, dilation=dilation).double()
    y = conv(x)
    assert torch.equal(y.coords, x.coords)
    dense, origin = x.to_dense(torch.zeros(3, dtype=torch.long), (SIDE,) * 3)
    dense = dense.detach().requires_grad_(True)
    yd = F.conv3d(dense, dense_weight(conv.weight, kernel), conv.bias, padding=dilation * (kernel - 1) // 2,
                  dilation=dilation)
    ref = at_sites(yd, x.coords, origin)
    torch.testing.assert_close(y.feats, ref, atol=1e-12, rtol=1e-12)
    r = torch.randn_like(ref)
    gw, gb, gx = torch.autograd.grad((y.feats * r).sum(), [conv.weight, conv.bias, x.feats])
    gwd, gbd, gxd = torch.autograd.grad((ref * r).sum(), [conv.weight, conv.bias, dense])
    torch.testing.assert_close(gw, gwd, atol=1e-11, rtol=1e-11)
    torch.testing.assert_close(gb, gbd, atol=1e-11, rtol=1e-11)
    torch.testing.assert_close(gx, at_sites(gxd, x.coords, origin), atol=1e-11, rtol=1e-11)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 120), cin=st.integers(1, 4), cout=st.integers(1, 4),
       batch=st.integers(1, 2), kps=st.sampled_from([(2, 2, 0), (3, 2, 1), (3, 2, 0), (2, 1, 0), (3, 3, 1)]))
def test_strided_conv_matches_dense_conv3d(seed, n, cin, cout, batch, kps):
    k, s, p = kps
    # Sparse sites have no boundary: every coarse site the kernel reaches is an output. The sites
    # start at LO >= k inside a dense grid whose origin is a multiple of s, so that the dense
    # result (which stops at the zero padding) holds all of them.
    x = leaf(random_sparse(seed, n, cin, batch, lo=LO))
    conv = SparseConv3d(cin, cout, k, s, p, bias=False).double()
    y = conv(x)
    assert y.stride == s
    side = LO + SIDE + 2 * s
    dense, origin = x.to_dense(torch.zeros(3, dtype=torch.long), (side,) * 3)
    dense = dense.detach().requires_grad_(True)
    yd = F.conv3d(dense, dense_weight(conv.weight, k), stride=s, padding=p)
    inside = ((y.coords[:, 1:] >= 0) & (y.coords[:, 1:] < torch.tensor(yd.shape[2:]))).all(1)
    assert bool(inside.all())
    ref = at_sites(yd, y.coords, (0, 0, 0))
    torch.testing.assert_close(y.feats, ref, atol=1e-12, rtol=1e-12)
    mask = torch.ones_like(yd, dtype=torch.bool)
    c = y.coords
    mask[c[:, 0], :, c[:, 1], c[:, 2], c[:, 3]] = False
    assert float(yd.detach()[mask].abs().sum()) == 0.0  # and no site is missing
    r = torch.randn_like(ref)
    gw, gx = torch.autograd.grad((y.feats * r).sum(), [conv.weight, x.feats])
    gwd, gxd = torch.autograd.grad((ref * r).sum(), [conv.weight, dense])
    torch.testing.assert_close(gw, gwd, atol=1e-11, rtol=1e-11)
    torch.testing.assert_close(gx, at_sites(gxd, x.coords, origin), atol=1e-11, rtol=1e-11)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 120), cin=st.integers(1, 4), cout=st.integers(1, 4),
       batch=st.integers(1, 2), kps=st.sampled_from([(2, 2, 0), (3, 2, 1), (3, 2, 0)]), onto_target=st.booleans())
def test_transposed_conv_matches_dense_conv_transpose3d(seed, n, cin, cout, batch, kps, onto_target):
    k, s, p = kps
    fine = random_sparse(seed, n, 1, batch, lo=LO)
    coarse_grid, _ = fine.grid.downsample(k, s, p)
    g = torch.Generator().manual_seed(seed + 1)
    x = SparseTensor(torch.randn(len(coarse_grid), cin, generator=g, dtype=torch.float64), coarse_grid)
    x = leaf(x)
    up = SparseConvTranspose3d(cin, cout, k, s, p).double()
    y = up(x, fine) if onto_target else up(x)
    if onto_target:
        assert y.grid is fine.grid
    side = (LO + SIDE + 2 * s) // s + 1
    dense, origin = x.to_dense(torch.zeros(3, dtype=torch.long), (side,) * 3)
    dense = dense.detach().requires_grad_(True)
    yd = F.conv_transpose3d(dense, dense_weight(up.weight, k, transposed=True), up.bias, stride=s, padding=p)
    # the dense output crops p sites at each end (its padding); the sparse one has no ends
    keep = ((y.coords[:, 1:] >= 0) & (y.coords[:, 1:] < torch.tensor(yd.shape[2:]))).all(1)
    assert bool(keep.all()) if onto_target else int(keep.sum()) > 0
    ref = at_sites(yd, y.coords[keep], (0, 0, 0))
    torch.testing.assert_close(y.feats[keep], ref, atol=1e-12, rtol=1e-12)
    r = torch.randn_like(ref)
    gw, gx = torch.autograd.grad((y.feats[keep] * r).sum(), [up.weight, x.feats])
    gwd, gxd = torch.autograd.grad((ref * r).sum(), [up.weight, dense])
    torch.testing.assert_close(gw, gwd, atol=1e-11, rtol=1e-11)
    torch.testing.assert_close(gx, at_sites(gxd, x.coords, origin), atol=1e-11, rtol=1e-11)


def test_kernel_maps_are_built_once_per_grid_and_reused():
    x = random_sparse(3, 100, 2, 1)
    a, b = SubmanifoldConv3d(2, 2).double(), SubmanifoldConv3d(2, 2).double()
    a(x), b(x.replace(x.feats * 2))
    assert len(x.grid._maps) == 1
    m = x.grid.submanifold_map(3)
    assert x.grid.submanifold_map(3) is m
    d1, d2 = SparseConv3d(2, 3).double(), SparseConv3d(2, 3).double()
    assert d1(x).grid is d2(x).grid  # the same coarse grid object, so its maps are shared too
    # pair counts against a brute force neighbour count
    c = x.coords[:, 1:].numpy()
    diff = np.abs(c[:, None, :] - c[None, :, :]).max(-1)
    assert m.num_pairs == int((diff <= 1).sum())


# --- structure -----------------------------------------------------------------------------------


def test_subdivide_and_prune():
    x = random_sparse(4, 50, 3, 2)
    x = SparseTensor(x.feats, Grid(x.coords, 2, stride=4, _sorted=True))
    child, parent = subdivide(x)
    assert len(child) == 8 * len(x) and child.stride == 2
    assert torch.equal(child.coords, unique_coords(child.coords))  # unique and sorted
    pc = x.coords[parent]
    assert torch.equal(pc[:, 0], child.coords[:, 0])
    assert torch.equal(torch.div(child.coords[:, 1:], 2, rounding_mode="floor"), pc[:, 1:])
    assert torch.equal(child.feats, x.feats[parent])
    keep = child.feats[:, 0] > 0
    pr = prune(child, keep)
    assert len(pr) == int(keep.sum()) and torch.equal(pr.coords, child.coords[keep])
    assert torch.equal(pr.feats, child.feats[keep])
    # a transposed convolution back onto the children sees exactly one parent per child (k = s = 2)
    up = SparseConvTranspose3d(3, 1, 2, 2, bias=False).double()
    assert up(x, child).grid.upsample_map(x.grid, 2, 2).num_pairs == len(child)


def test_group_norm_matches_torch_per_batch_element():
    x = random_sparse(5, 150, 8, 3)
    gn = SparseGroupNorm(4, 8).double()
    with torch.no_grad():
        gn.weight.uniform_(0.5, 2), gn.bias.uniform_(-1, 1)
    y = gn(x)
    for b in range(3):
        sel = x.coords[:, 0] == b
        ref = F.group_norm(x.feats[sel].T[None], 4, gn.weight, gn.bias, eps=gn.eps)[0].T
        torch.testing.assert_close(y.feats[sel], ref)
    bn = SparseBatchNorm(8).double()
    torch.testing.assert_close(bn(x).feats, F.batch_norm(x.feats, None, None, training=True))


@pytest.mark.parametrize("norm", ["batch", "group"])
def test_unet_is_shift_equivariant_and_trains(norm):
    """Shifting every site by a multiple of the coarsest stride shifts the output with it (the
    grids and kernel maps are the same up to translation), and a few Adam steps fit a target."""
    torch.manual_seed(0)
    x = random_sparse(6, 300, 2, 2, side=10)
    net = SparseUNet(2, 3, widths=(4, 8, 16), blocks=1, norm=norm).double()
    y = net(x)
    assert torch.equal(y.coords, x.coords) and y.feats.shape == (len(x), 3)
    shift = torch.tensor([0, 8, -16, 4])
    xs = SparseTensor.from_coords(x.coords + shift, x.feats, batch_size=2)
    torch.testing.assert_close(net(xs).feats, y.feats, atol=1e-10, rtol=1e-10)
    target = torch.sin(x.coords[:, 1:].double()).sum(1, keepdim=True).repeat(1, 3)
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    first = None
    for _ in range(30):
        loss = F.mse_loss(net(x).feats, target)
        first = float(loss.detach()) if first is None else first
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.5 * first
