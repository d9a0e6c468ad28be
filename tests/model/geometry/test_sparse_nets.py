"""The fine level's sparse networks (`geometry_sparse`): the original layouts keep their
state-dict keys, the ldm layout and the self-attention over each batch element's sites run and
have the dense networks' parameters (on a full box, their values too), and the sparse VAE's
optional stem and decoder blocks."""

from __future__ import annotations

import pytest
import torch

from scube_sim.labels import NUM_LABELS
from scube_sim.model.geometry.dense_nets import Denoiser3d, SelfAttention3d, StructureVAE, VAEConfig
from scube_sim.model.geometry.sparse_nets import (
    SparseDenoiser,
    SparseSelfAttention,
    SparseStructureVAE,
    avg_pool2,
    row_ids,
    upsample_nearest2,
)
from scube_sim.model.nn.sparse import SparseTensor, unique_coords

META = torch.device("meta")

# The state-dict keys and shapes of the original sparse networks, taken before the ldm layout,
# attention and the VAE's optional layout existed: SparseDenoiser(4, 3, (8, 16), 2, 4),
# SparseStructureVAE(VAEConfig(widths=(8, 16), blocks=1)) and blocks=0. Checkpoints of runs with
# them must still load.
DENOISER_KEYS = {
    'time.0.weight': (32, 8), 'time.0.bias': (32,), 'time.2.weight': (32, 32), 'time.2.bias': (32,), 'stem.weight':
    (27, 7, 8), 'stem.bias': (8,), 'enc.0.0.n1.weight': (8,), 'enc.0.0.n1.bias': (8,), 'enc.0.0.c1.weight': (27, 8,
    8), 'enc.0.0.c1.bias': (8,), 'enc.0.0.n2.weight': (8,), 'enc.0.0.n2.bias': (8,), 'enc.0.0.c2.weight': (27, 8,
    8), 'enc.0.0.c2.bias': (8,), 'enc.0.0.emb.weight': (8, 32), 'enc.0.0.emb.bias': (8,), 'enc.0.1.n1.weight': (8,),
    'enc.0.1.n1.bias': (8,), 'enc.0.1.c1.weight': (27, 8, 8), 'enc.0.1.c1.bias': (8,), 'enc.0.1.n2.weight': (8,),
    'enc.0.1.n2.bias': (8,), 'enc.0.1.c2.weight': (27, 8, 8), 'enc.0.1.c2.bias': (8,), 'enc.0.1.emb.weight': (8,
    32), 'enc.0.1.emb.bias': (8,), 'enc.1.0.n1.weight': (16,), 'enc.1.0.n1.bias': (16,), 'enc.1.0.c1.weight': (27,
    16, 16), 'enc.1.0.c1.bias': (16,), 'enc.1.0.n2.weight': (16,), 'enc.1.0.n2.bias': (16,), 'enc.1.0.c2.weight':
    (27, 16, 16), 'enc.1.0.c2.bias': (16,), 'enc.1.0.emb.weight': (16, 32), 'enc.1.0.emb.bias': (16,),
    'enc.1.1.n1.weight': (16,), 'enc.1.1.n1.bias': (16,), 'enc.1.1.c1.weight': (27, 16, 16), 'enc.1.1.c1.bias':
    (16,), 'enc.1.1.n2.weight': (16,), 'enc.1.1.n2.bias': (16,), 'enc.1.1.c2.weight': (27, 16, 16),
    'enc.1.1.c2.bias': (16,), 'enc.1.1.emb.weight': (16, 32), 'enc.1.1.emb.bias': (16,), 'down.0.weight': (8, 8,
    16), 'down.0.bias': (16,), 'up.0.weight': (8, 16, 8), 'up.0.bias': (8,), 'dec.0.0.n1.weight': (16,),
    'dec.0.0.n1.bias': (16,), 'dec.0.0.c1.weight': (27, 16, 8), 'dec.0.0.c1.bias': (8,), 'dec.0.0.n2.weight': (8,),
    'dec.0.0.n2.bias': (8,), 'dec.0.0.c2.weight': (27, 8, 8), 'dec.0.0.c2.bias': (8,), 'dec.0.0.emb.weight': (8,
    32), 'dec.0.0.emb.bias': (8,), 'dec.0.0.skip.weight': (8, 16), 'dec.0.0.skip.bias': (8,), 'dec.0.1.n1.weight':
    (8,), 'dec.0.1.n1.bias': (8,), 'dec.0.1.c1.weight': (27, 8, 8), 'dec.0.1.c1.bias': (8,), 'dec.0.1.n2.weight':
    (8,), 'dec.0.1.n2.bias': (8,), 'dec.0.1.c2.weight': (27, 8, 8), 'dec.0.1.c2.bias': (8,), 'dec.0.1.emb.weight':
    (8, 32), 'dec.0.1.emb.bias': (8,), 'head.weight': (4, 8), 'head.bias': (4,),
}
VAE_KEYS = {
    'latent_std': (), '_latent_sq': (), '_latent_n': (), 'down.0.0.weight': (8, 27, 8), 'down.0.0.bias': (8,),
    'down.0.1.n1.weight': (8,), 'down.0.1.n1.bias': (8,), 'down.0.1.c1.weight': (27, 8, 8), 'down.0.1.c1.bias':
    (8,), 'down.0.1.n2.weight': (8,), 'down.0.1.n2.bias': (8,), 'down.0.1.c2.weight': (27, 8, 8),
    'down.0.1.c2.bias': (8,), 'down.1.0.weight': (8, 8, 16), 'down.1.0.bias': (16,), 'down.1.1.n1.weight': (16,),
    'down.1.1.n1.bias': (16,), 'down.1.1.c1.weight': (27, 16, 16), 'down.1.1.c1.bias': (16,), 'down.1.1.n2.weight':
    (16,), 'down.1.1.n2.bias': (16,), 'down.1.1.c2.weight': (27, 16, 16), 'down.1.1.c2.bias': (16,),
    'to_latent.weight': (16, 16), 'to_latent.bias': (16,), 'from_latent.weight': (16, 8), 'from_latent.bias': (16,),
    'dec.0.n1.weight': (16,), 'dec.0.n1.bias': (16,), 'dec.0.c1.weight': (27, 16, 16), 'dec.0.c1.bias': (16,),
    'dec.0.n2.weight': (16,), 'dec.0.n2.bias': (16,), 'dec.0.c2.weight': (27, 16, 16), 'dec.0.c2.bias': (16,),
    'dec.1.n1.weight': (8,), 'dec.1.n1.bias': (8,), 'dec.1.c1.weight': (27, 8, 8), 'dec.1.c1.bias': (8,),
    'dec.1.n2.weight': (8,), 'dec.1.n2.bias': (8,), 'dec.1.c2.weight': (27, 8, 8), 'dec.1.c2.bias': (8,),
    'occ.0.weight': (8, 16), 'occ.0.bias': (8,), 'up.0.weight': (8, 16, 8), 'up.0.bias': (8,), 'final.weight': (216,
    8), 'final.bias': (216,),
}
VAE0_KEYS = {
    'latent_std': (), '_latent_sq': (), '_latent_n': (), 'down.0.0.weight': (8, 27, 8), 'down.0.0.bias': (8,),
    'down.1.0.weight': (8, 8, 16), 'down.1.0.bias': (16,), 'to_latent.weight': (16, 16), 'to_latent.bias': (16,),
    'from_latent.weight': (16, 8), 'from_latent.bias': (16,), 'dec.0.n1.weight': (16,), 'dec.0.n1.bias': (16,),
    'dec.0.c1.weight': (27, 16, 16), 'dec.0.c1.bias': (16,), 'dec.0.n2.weight': (16,), 'dec.0.n2.bias': (16,),
    'dec.0.c2.weight': (27, 16, 16), 'dec.0.c2.bias': (16,), 'dec.1.n1.weight': (8,), 'dec.1.n1.bias': (8,),
    'dec.1.c1.weight': (27, 8, 8), 'dec.1.c1.bias': (8,), 'dec.1.n2.weight': (8,), 'dec.1.n2.bias': (8,),
    'dec.1.c2.weight': (27, 8, 8), 'dec.1.c2.bias': (8,), 'occ.0.weight': (8, 16), 'occ.0.bias': (8,),
    'up.0.weight': (8, 16, 8), 'up.0.bias': (8,), 'final.weight': (216, 8), 'final.bias': (216,),
}


def _shapes(module: torch.nn.Module) -> dict:
    return {k: tuple(v.shape) for k, v in module.state_dict().items()}


def _params(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def _randomise(module: torch.nn.Module) -> None:
    """Every parameter random (the zero-initialised branches would hide a dead path)."""
    with torch.no_grad():
        for p in module.parameters():
            p.normal_(0.0, 0.2)


def _sparse_input(seed: int, channels: int, side: int = 6, n: int = 120, batch: int = 2) -> SparseTensor:
    g = torch.Generator().manual_seed(seed)
    c = torch.cat([torch.randint(0, batch, (n, 1), generator=g), torch.randint(0, side, (n, 3), generator=g)], 1)
    c = unique_coords(c)
    return SparseTensor.from_coords(c, torch.randn(len(c), channels, generator=g), batch_size=batch)


def _full_box(batch: int, side: int, channels: int, seed: int = 0) -> tuple[SparseTensor, torch.Tensor]:
    """Every voxel of a side^3 box active in each batch element: (sparse, dense (B, C, s, s, s))."""
    g = torch.Generator().manual_seed(seed)
    dense = torch.randn(batch, channels, side, side, side, generator=g)
    ijk = torch.stack(torch.meshgrid(*[torch.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    coords = torch.cat([torch.arange(batch).repeat_interleave(len(ijk))[:, None], ijk.repeat(batch, 1)], 1)
    feats = dense[coords[:, 0], :, coords[:, 1], coords[:, 2], coords[:, 3]]
    return SparseTensor.from_coords(coords, feats, batch_size=batch), dense


def _copy_dense_into_sparse(dense: torch.nn.Module, sparse: torch.nn.Module) -> None:
    """Load a dense network's weights into the sparse one of the same names: 3^3 / 2^3 conv
    (C_out, C_in, k, k, k) -> (k^3, C_in, C_out); 1^3 conv -> linear (C_out, C_in)."""
    src = dense.state_dict()
    out = {}
    for k, v in sparse.state_dict().items():
        w = src[k]
        if w.ndim == 5 and v.ndim == 3:
            w = w.reshape(w.shape[0], w.shape[1], -1).permute(2, 1, 0)
        elif w.ndim == 5 and v.ndim == 2:
            w = w[:, :, 0, 0, 0]
        assert w.shape == v.shape, k
        out[k] = w
    sparse.load_state_dict(out)


# ---------------------------------------------------------------------------- original keys
def test_row_ids_number_rows_as_torch_unique_does():
    """Packed int64 keys give the ids torch.unique(dim=0) gives (lexicographic), negative
    coordinates included; a range too wide to pack falls back to it."""
    g = torch.Generator().manual_seed(0)
    for _ in range(50):
        n1, n2 = torch.randint(0, 300, (2,), generator=g).tolist()
        lo = int(torch.randint(-1000, 10, (1,), generator=g))
        a = torch.randint(lo, lo + 200, (n1, 4), generator=g)
        b = torch.randint(lo, lo + 40, (n2, 4), generator=g)
        a[:, 0], b[:, 0] = a[:, 0] % 3, b[:, 0] % 3
        _, inv = torch.unique(torch.cat([a, b]), dim=0, return_inverse=True)
        got = row_ids(a, b)
        assert torch.equal(got[0], inv[:n1]) and torch.equal(got[1], inv[n1:])
    wide = torch.tensor([[0, -2**40, 0, 0], [1, 2**40, 5, 5], [0, -2**40, 0, 0]])
    assert torch.equal(row_ids(wide)[0], torch.tensor([0, 1, 0]))
    assert [len(x) for x in row_ids(torch.zeros((0, 4), dtype=torch.int64))] == [0]


def test_the_original_layouts_keep_their_keys():
    with META:
        assert _shapes(SparseDenoiser(4, 3, (8, 16), 2, 4)) == DENOISER_KEYS
        plain = SparseDenoiser(4, 3, (8, 16), 2, 4, attention_levels=(), heads=3, layout="plain")
        assert _shapes(plain) == DENOISER_KEYS
        assert _shapes(SparseStructureVAE(VAEConfig(widths=(8, 16), blocks=1))) == VAE_KEYS
        assert _shapes(SparseStructureVAE(VAEConfig(widths=(8, 16), blocks=0))) == VAE0_KEYS
        # decoder_blocks 1 is the original decoder
        assert _shapes(SparseStructureVAE(VAEConfig(widths=(8, 16), blocks=1, decoder_blocks=1))) == VAE_KEYS
        with_attention = _shapes(SparseDenoiser(4, 3, (8, 16), 2, 4, attention_levels=(1,), heads=2))
        with_stem = _shapes(SparseStructureVAE(VAEConfig(widths=(8, 16), blocks=1, input_width=4, decoder_blocks=3)))
    new = set(with_attention) - set(DENOISER_KEYS)
    assert set(DENOISER_KEYS) <= set(with_attention)
    assert new and all(k.split(".")[0] in ("enc_attn", "dec_attn") for k in new)
    new = set(with_stem) - set(VAE_KEYS)
    assert {k.split(".")[0] for k in new} == {"stem", "dec_more"}
    assert {k: v for k, v in with_stem.items() if k in VAE_KEYS and k != "down.0.0.weight"} == \
        {k: v for k, v in VAE_KEYS.items() if k != "down.0.0.weight"}
    assert with_stem["down.0.0.weight"] == (8, 4, 8)  # the first halving reads the stem's 4 channels


# ---------------------------------------------------------------------------- the ldm layout, attention
def test_the_ldm_layout_with_attention_runs_forward_and_backward():
    torch.manual_seed(0)
    net = SparseDenoiser(4, 3, (8, 16), 1, 4, attention_levels=(1,), heads=2, layout="ldm")
    assert isinstance(net.enc_attn[1], SparseSelfAttention) and isinstance(net.enc_attn[0], torch.nn.Identity)
    assert isinstance(net.mid_attn, SparseSelfAttention)  # level 1 is the deepest
    assert sum(isinstance(m, SparseSelfAttention) for m in net.dec_attn) == 2
    x = _sparse_input(1, 7)
    assert set(x.coords[:, 0].tolist()) == {0, 1}
    fresh = net(x, torch.tensor([0, 999]))
    assert fresh.grid is x.grid and fresh.feats.shape == (len(x), 4) and bool((fresh.feats == 0).all())
    _randomise(net)
    feats = x.feats.clone().requires_grad_(True)
    out = net(x.replace(feats), torch.tensor([3, 500])).feats
    out.square().mean().backward()
    assert bool(torch.isfinite(out).all()) and bool(torch.isfinite(feats.grad).all())
    assert float(feats.grad.abs().sum()) > 0
    for name, p in net.named_parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name
    assert float(net.enc_attn[1].qkv.weight.grad.abs().sum()) > 0


@pytest.mark.parametrize("layout", ["plain", "ldm"])
def test_attention_does_not_mix_batch_elements(layout):
    torch.manual_seed(0)
    net = SparseDenoiser(4, 3, (8, 16), 1, 4, attention_levels=(0, 1), heads=2, layout=layout)
    _randomise(net)
    x = _sparse_input(2, 7)
    one = x.coords[:, 0] == 1
    x2 = x.feats.clone()
    x2[one] = torch.randn(int(one.sum()), 7)
    t = torch.tensor([10, 10])
    with torch.no_grad():
        y, y2 = net(x, t).feats, net(x.replace(x2), t).feats
    assert torch.equal(y[~one], y2[~one])  # element 0 untouched
    assert float((y[one] - y2[one]).abs().max()) > 1e-4  # element 1 moved


def test_sparse_attention_is_global_within_an_element_and_skips_empty_ones():
    torch.manual_seed(0)
    block = SparseSelfAttention(8, 2, 4)
    _randomise(block)
    # batch of 3 with element 1 empty
    c = torch.tensor([[0, 0, 0, 0], [0, 5, 5, 5], [0, 2, 3, 1], [2, 0, 0, 0], [2, 1, 0, 0]])
    x = SparseTensor.from_coords(c, torch.randn(len(c), 8), batch_size=3)
    with torch.no_grad():
        y = block(x).feats
        x2 = x.feats.clone()
        x2[0] += 1.0  # site (0, 0, 0): the far site (5, 5, 5) of the same element moves too
        y2 = block(x.replace(x2)).feats
    assert bool(torch.isfinite(y).all())
    assert float((y2[1] - y[1]).abs().max()) > 1e-4 and torch.equal(y2[3:], y[3:])


def test_sparse_attention_on_a_full_box_is_the_dense_attention():
    torch.manual_seed(0)
    dense, sparse = SelfAttention3d(8, 2, 4), SparseSelfAttention(8, 2, 4)
    _randomise(dense)
    _copy_dense_into_sparse(dense, sparse)
    xs, xd = _full_box(2, 3, 8)
    with torch.no_grad():
        yd, ys = dense(xd), sparse(xs).feats
    c = xs.coords
    assert torch.allclose(ys, yd[c[:, 0], :, c[:, 1], c[:, 2], c[:, 3]], atol=1e-5)


def test_the_ldm_layout_on_a_full_box_is_the_dense_network():
    """Sparse = dense where every voxel is active: submanifold 3^3 convolutions are the zero-padded
    dense ones, the average pooling and nearest up-sampling the dense ones."""
    torch.manual_seed(0)
    args, kw = (4, 3, (8, 16), 1, 4), dict(attention_levels=(1,), heads=2, layout="ldm")
    dense, sparse = Denoiser3d(*args, **kw), SparseDenoiser(*args, **kw)
    _randomise(dense)
    _copy_dense_into_sparse(dense, sparse)
    xs, xd = _full_box(2, 4, 7, seed=3)
    t = torch.tensor([5, 800])
    with torch.no_grad():
        yd, ys = dense(xd[:, :4], xd[:, 4:], t), sparse(xs, t).feats
    c = xs.coords
    assert float(yd.abs().max()) > 1e-2
    assert torch.allclose(ys, yd[c[:, 0], :, c[:, 1], c[:, 2], c[:, 3]], atol=1e-4)


@pytest.mark.parametrize("args, kw", [
    ((8, 32, (64, 128, 256, 256), 2, 32), dict(attention_levels=(3,), heads=8, layout="ldm")),  # geometry-fine-paper
    ((4, 4, (16, 32, 32), 1, 8), dict(attention_levels=(1, 2), heads=4, layout="ldm")),
    ((4, 3, (8, 16), 2, 4), dict(layout="ldm")),
])
def test_the_ldm_layout_has_the_dense_parameters(args, kw):
    with META:
        sparse, dense = SparseDenoiser(*args, **kw), Denoiser3d(*args, **kw)
    assert _params(sparse) == _params(dense)
    s, d = _shapes(sparse), _shapes(dense)
    assert set(s) == set(d) and all(torch.Size(s[k]).numel() == torch.Size(d[k]).numel() for k in s)


def test_the_attention_has_the_dense_parameters():
    with META:
        assert _params(SparseSelfAttention(64, 8, 32)) == _params(SelfAttention3d(64, 8, 32))


def test_bad_denoiser_settings_are_refused():
    with pytest.raises(ValueError, match="levels 0 to 1"):
        SparseDenoiser(4, 3, (8, 16), 1, 4, attention_levels=(2,))
    with pytest.raises(ValueError, match="16 channels do not split into 3 heads"):
        SparseDenoiser(4, 3, (8, 16), 1, 4, attention_levels=(1,), heads=3, layout="ldm")
    with pytest.raises(ValueError, match="layout"):
        SparseDenoiser(4, 3, (8, 16), 1, 4, layout="dit")


def test_sparse_resampling_averages_the_active_children_and_copies_the_parent():
    c = torch.tensor([[0, 0, 0, 0], [0, 1, 1, 0], [0, 3, 0, 0], [1, 0, 0, 1]])
    x = SparseTensor.from_coords(c, torch.tensor([[1.0], [3.0], [5.0], [7.0]]), batch_size=2)
    pooled = avg_pool2(x)
    assert pooled.stride == 2 and pooled.coords.tolist() == [[0, 0, 0, 0], [0, 1, 0, 0], [1, 0, 0, 0]]
    assert pooled.feats[:, 0].tolist() == [2.0, 5.0, 7.0]
    back = upsample_nearest2(pooled, x.grid)
    assert back.grid is x.grid and back.feats[:, 0].tolist() == [2.0, 2.0, 5.0, 7.0]


# ---------------------------------------------------------------------------- the VAE's optional layout
def test_the_vae_with_a_full_resolution_stem_and_its_own_decoder_blocks():
    torch.manual_seed(0)
    cfg = VAEConfig(widths=(8, 16), blocks=1, input_width=4, decoder_blocks=2, latent_channels=2, groups=4)
    vae = SparseStructureVAE(cfg)
    assert len(vae.stem) == 2 and [len(m) for m in vae.dec_more] == [1, 1]
    x = _sparse_input(4, 1, side=8, n=200, batch=2)
    coords, labels = x.coords, torch.randint(0, 5, (len(x),))
    vae.train()
    loss, parts = vae.loss(coords, labels, 2)
    loss.backward()
    assert bool(torch.isfinite(loss)) and set(parts) == {"bce", "ce", "kl"}
    for m in (vae.stem[0], vae.stem[1].c1, vae.dec_more[0][0].c1, vae.dec_more[1][0].c1):
        assert bool(torch.isfinite(m.weight.grad).all()) and float(m.weight.grad.abs().sum()) > 0
    vae.eval()
    with torch.no_grad():
        mu, _ = vae.encode(coords, labels, 2)
        levels = vae.decode(mu)
    assert mu.stride == 4 and len(levels) == 2 and levels[-1][2].shape[1] == NUM_LABELS


def test_the_paper_vae_layout_is_about_the_dense_size():
    cfg = VAEConfig(input_width=32, widths=(64, 128), blocks=1, decoder_blocks=2, latent_channels=8, groups=8)
    with META:
        sparse, dense = _params(SparseStructureVAE(cfg)), _params(StructureVAE(cfg))
    assert abs(sparse / dense - 1) < 0.02  # the latent projections and heads differ (SparseStructureVAE)
