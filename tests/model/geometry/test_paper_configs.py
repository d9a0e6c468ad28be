"""The paper-size geometry configs (SCube appendix: "Hyperparameters for VAE" and "... for voxel
latent diffusion models") built on torch's meta device, with their parameter counts against the
paper's, and the denoiser's self-attention and layouts. `pytest -s` prints the counts."""

from __future__ import annotations

import pytest
import torch

from scube_sim.model.config import configs_dir, load_config, stage_configs
from scube_sim.model.geometry.dense_nets import Denoiser3d, SelfAttention3d, StructureVAE, VAEConfig
from scube_sim.model.geometry.sparse_nets import SparseDenoiser, SparseSelfAttention, SparseStructureVAE
from scube_sim.model.stages import get_stage

META = torch.device("meta")
TOLERANCE = 0.15
# the paper's "Model Size" of each config's network (the diffusion's: the denoiser alone)
PAPER_SIZE = {"geometry-vae-coarse-paper": 14.9e6, "geometry-vae-fine-paper": 3.8e6,
              "geometry-coarse-paper": 728e6, "geometry-fine-paper": 83.0e6}
# XCube's UNet (GeometryModelConfig.layout)
PAPER_LAYOUT = "ldm"



def _run(name: str):
    return load_config(configs_dir() / f"{name}.yaml")


def _validated(name: str):
    run = _run(name)
    stage = get_stage(run.stage)
    model_cfg, data_cfg = stage_configs(run, stage.model_config, stage.data_config)
    return stage, model_cfg, data_cfg


def _params(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def _within(name: str, count: int, what: str = "") -> bool:
    paper = PAPER_SIZE[name]
    print(f"\n{name}{what}: {count / 1e6:.2f} M parameters, the paper's {paper / 1e6:.1f} M "
          f"({count / paper - 1:+.1%})")
    return abs(count / paper - 1) <= TOLERANCE


def _paper_denoiser(model: dict) -> Denoiser3d:
    """The denoiser of a config's (unvalidated) model section, in the paper's layout, on meta."""
    with META:
        return Denoiser3d(model["vae"]["latent_channels"], model["cond_channels"], tuple(model["widths"]),
                          model["blocks"], model["groups"], attention_levels=tuple(model["attention_levels"]),
                          heads=model["heads"], layout=PAPER_LAYOUT)


# ---------------------------------------------------------------------------- the paper's sizes
@pytest.mark.parametrize("name", ["geometry-vae-coarse-paper", "geometry-vae-fine-paper",
                                  "geometry-coarse-paper", "geometry-fine-paper"])
def test_the_structure_vae_of_each_config(name):
    """Every config's VAE section builds the same StructureVAE; the VAE configs' is the paper's size."""
    vae_cfg = VAEConfig(**_run(name).model["vae"])
    vae_name = name if "-vae-" in name else name.replace("geometry-", "geometry-vae-")
    assert vae_cfg == VAEConfig(**_run(vae_name).model["vae"])  # the diffusion's frozen VAE is the level's
    with META:
        vae = StructureVAE(vae_cfg)
    assert _within(vae_name, _params(vae), " (StructureVAE)")


@pytest.mark.parametrize("name", ["geometry-coarse-paper", "geometry-fine-paper"])
def test_the_denoiser_of_each_diffusion_config(name):
    assert _within(name, _params(_paper_denoiser(_run(name).model)), f" (Denoiser3d, {PAPER_LAYOUT} layout)")


def test_the_tables_fine_multiples_cannot_give_its_size():
    """geometry-fine-paper.yaml takes the table's 1,2,2,4 for a typo of XCube's 1,2,4,4: in the same
    UNet, 1,2,2,4 is a third short of 83.0 M."""
    model = dict(_run("geometry-fine-paper").model, widths=[64, 128, 128, 256])
    assert not _within("geometry-fine-paper", _params(_paper_denoiser(model)), " with multiples 1,2,2,4")


@pytest.mark.parametrize("name", ["geometry-vae-coarse-paper", "geometry-coarse-paper"])
def test_the_coarse_configs_validate_and_build(name):
    stage, model_cfg, data_cfg = _validated(name)
    assert data_cfg.grid().dims == (256, 256, 256) and data_cfg.voxel_size == 0.4
    with META:
        net = stage.build_model(model_cfg)
    with META:
        vae = StructureVAE(model_cfg.vae)
    assert _params(net.vae) == _params(vae)
    if name == "geometry-coarse-paper":
        cond = net.conditioner
        vit = _params(cond.encoder.backbone)
        print(f"\n{name}: conditioner {_params(cond) / 1e6:.2f} M (DINOv2 ViT-B/14 {vit / 1e6:.2f} M, the rest "
              f"{(_params(cond) - vit) / 1e6:.2f} M); denoiser as GeometryNet builds it "
              f"({net.denoiser.layout} layout) {_params(net.denoiser) / 1e6:.2f} M")
        assert 80e6 < vit < 90e6  # ViT-B/14: 86.6 M
        assert net.denoiser.attention_levels == (2, 3)
        assert isinstance(net.denoiser.mid_attn, SelfAttention3d)


def test_the_coarse_diffusion_as_geometry_builds_it_is_the_papers_size():
    stage, model_cfg, _ = _validated("geometry-coarse-paper")
    with META:
        net = stage.build_model(model_cfg)
    assert _within("geometry-coarse-paper", _params(net.denoiser), " (GeometryNet's denoiser)")


@pytest.mark.parametrize("name", ["geometry-vae-fine-paper", "geometry-fine-paper"])
def test_the_fine_configs_validate_and_build(name):
    stage, model_cfg, data_cfg = _validated(name)
    assert data_cfg.level == "fine" and data_cfg.voxel_size == 0.1
    assert data_cfg.grid(data_cfg.voxel_size).dims == (1024, 1024, 1024)
    with META:
        net = stage.build_model(model_cfg)
    parts = ", ".join(f"{k} {_params(v) / 1e6:.2f} M ({type(v).__name__})" for k, v in net.named_children())
    print(f"\n{name} as geometry.py builds it: {parts}")
    assert isinstance(net.vae, SparseStructureVAE)
    assert net.vae.stem is not None and all(len(m) == 1 for m in net.vae.dec_more)  # input_width, decoder_blocks 2
    if name == "geometry-vae-fine-paper":
        assert _within(name, _params(net.vae), " (the geometry-vae stage's SparseStructureVAE)")
    else:
        den = net.denoiser
        assert isinstance(den, SparseDenoiser) and den.layout == "ldm" and den.attention_levels == (3,)
        assert isinstance(den.mid_attn, SparseSelfAttention)
        assert _within(name, _params(den), " (GeometryNet's SparseDenoiser)")
        assert _params(den) == _params(_paper_denoiser(_run(name).model))  # the dense count, exactly
        # the diffusion's frozen VAE is the VAE config's network
        _, vae_cfg, _ = _validated("geometry-vae-fine-paper")
        with META:
            vae_net = get_stage("geometry-vae").build_model(vae_cfg)
        assert _shapes(net.vae) == _shapes(vae_net.vae)


# ---------------------------------------------------------------------------- attention, layouts
# The state-dict keys and shapes of the original networks (recorded before attention, the ldm
# layout and the VAE's optional layout existed): checkpoints of runs with them must still load.
DENOISER_KEYS = {
    'time.0.weight': (32, 8), 'time.0.bias': (32,), 'time.2.weight': (32, 32), 'time.2.bias': (32,),
    'inp.weight': (8, 7, 3, 3, 3), 'inp.bias': (8,), 'enc.0.n1.weight': (8,), 'enc.0.n1.bias': (8,),
    'enc.0.c1.weight': (8, 8, 3, 3, 3), 'enc.0.c1.bias': (8,), 'enc.0.n2.weight': (8,), 'enc.0.n2.bias': (8,),
    'enc.0.c2.weight': (8, 8, 3, 3, 3), 'enc.0.c2.bias': (8,), 'enc.0.emb.weight': (8, 32), 'enc.0.emb.bias':
    (8,), 'enc.1.n1.weight': (8,), 'enc.1.n1.bias': (8,), 'enc.1.c1.weight': (8, 8, 3, 3, 3), 'enc.1.c1.bias':
    (8,), 'enc.1.n2.weight': (8,), 'enc.1.n2.bias': (8,), 'enc.1.c2.weight': (8, 8, 3, 3, 3), 'enc.1.c2.bias':
    (8,), 'enc.1.emb.weight': (8, 32), 'enc.1.emb.bias': (8,), 'enc.2.n1.weight': (8,), 'enc.2.n1.bias': (8,),
    'enc.2.c1.weight': (16, 8, 3, 3, 3), 'enc.2.c1.bias': (16,), 'enc.2.n2.weight': (16,), 'enc.2.n2.bias':
    (16,), 'enc.2.c2.weight': (16, 16, 3, 3, 3), 'enc.2.c2.bias': (16,), 'enc.2.emb.weight': (16, 32),
    'enc.2.emb.bias': (16,), 'enc.2.skip.weight': (16, 8, 1, 1, 1), 'enc.2.skip.bias': (16,), 'enc.3.n1.weight':
    (16,), 'enc.3.n1.bias': (16,), 'enc.3.c1.weight': (16, 16, 3, 3, 3), 'enc.3.c1.bias': (16,),
    'enc.3.n2.weight': (16,), 'enc.3.n2.bias': (16,), 'enc.3.c2.weight': (16, 16, 3, 3, 3), 'enc.3.c2.bias':
    (16,), 'enc.3.emb.weight': (16, 32), 'enc.3.emb.bias': (16,), 'downs.0.weight': (8, 8, 2, 2, 2),
    'downs.0.bias': (8,), 'mid.n1.weight': (16,), 'mid.n1.bias': (16,), 'mid.c1.weight': (16, 16, 3, 3, 3),
    'mid.c1.bias': (16,), 'mid.n2.weight': (16,), 'mid.n2.bias': (16,), 'mid.c2.weight': (16, 16, 3, 3, 3),
    'mid.c2.bias': (16,), 'mid.emb.weight': (16, 32), 'mid.emb.bias': (16,), 'dec.0.n1.weight': (32,),
    'dec.0.n1.bias': (32,), 'dec.0.c1.weight': (16, 32, 3, 3, 3), 'dec.0.c1.bias': (16,), 'dec.0.n2.weight':
    (16,), 'dec.0.n2.bias': (16,), 'dec.0.c2.weight': (16, 16, 3, 3, 3), 'dec.0.c2.bias': (16,),
    'dec.0.emb.weight': (16, 32), 'dec.0.emb.bias': (16,), 'dec.0.skip.weight': (16, 32, 1, 1, 1),
    'dec.0.skip.bias': (16,), 'dec.1.n1.weight': (32,), 'dec.1.n1.bias': (32,), 'dec.1.c1.weight': (16, 32, 3,
    3, 3), 'dec.1.c1.bias': (16,), 'dec.1.n2.weight': (16,), 'dec.1.n2.bias': (16,), 'dec.1.c2.weight': (16, 16,
    3, 3, 3), 'dec.1.c2.bias': (16,), 'dec.1.emb.weight': (16, 32), 'dec.1.emb.bias': (16,),
    'dec.1.skip.weight': (16, 32, 1, 1, 1), 'dec.1.skip.bias': (16,), 'dec.2.n1.weight': (24,), 'dec.2.n1.bias':
    (24,), 'dec.2.c1.weight': (8, 24, 3, 3, 3), 'dec.2.c1.bias': (8,), 'dec.2.n2.weight': (8,), 'dec.2.n2.bias':
    (8,), 'dec.2.c2.weight': (8, 8, 3, 3, 3), 'dec.2.c2.bias': (8,), 'dec.2.emb.weight': (8, 32),
    'dec.2.emb.bias': (8,), 'dec.2.skip.weight': (8, 24, 1, 1, 1), 'dec.2.skip.bias': (8,), 'dec.3.n1.weight':
    (16,), 'dec.3.n1.bias': (16,), 'dec.3.c1.weight': (8, 16, 3, 3, 3), 'dec.3.c1.bias': (8,),
    'dec.3.n2.weight': (8,), 'dec.3.n2.bias': (8,), 'dec.3.c2.weight': (8, 8, 3, 3, 3), 'dec.3.c2.bias': (8,),
    'dec.3.emb.weight': (8, 32), 'dec.3.emb.bias': (8,), 'dec.3.skip.weight': (8, 16, 1, 1, 1),
    'dec.3.skip.bias': (8,), 'ups.0.weight': (16, 16, 2, 2, 2), 'ups.0.bias': (16,), 'out.0.weight': (8,),
    'out.0.bias': (8,), 'out.2.weight': (4, 8, 3, 3, 3), 'out.2.bias': (4,),
}
VAE_KEYS = {
    'latent_std': (), '_latent_sq': (), '_latent_n': (), 'down.0.0.weight': (8, 27, 2, 2, 2), 'down.0.0.bias':
    (8,), 'down.0.1.n1.weight': (8,), 'down.0.1.n1.bias': (8,), 'down.0.1.c1.weight': (8, 8, 3, 3, 3),
    'down.0.1.c1.bias': (8,), 'down.0.1.n2.weight': (8,), 'down.0.1.n2.bias': (8,), 'down.0.1.c2.weight': (8, 8,
    3, 3, 3), 'down.0.1.c2.bias': (8,), 'down.1.0.weight': (16, 8, 2, 2, 2), 'down.1.0.bias': (16,),
    'down.1.1.n1.weight': (16,), 'down.1.1.n1.bias': (16,), 'down.1.1.c1.weight': (16, 16, 3, 3, 3),
    'down.1.1.c1.bias': (16,), 'down.1.1.n2.weight': (16,), 'down.1.1.n2.bias': (16,), 'down.1.1.c2.weight':
    (16, 16, 3, 3, 3), 'down.1.1.c2.bias': (16,), 'to_latent.0.weight': (16,), 'to_latent.0.bias': (16,),
    'to_latent.2.weight': (16, 16, 1, 1, 1), 'to_latent.2.bias': (16,), 'from_latent.weight': (16, 8, 3, 3, 3),
    'from_latent.bias': (16,), 'dec_blocks.0.0.n1.weight': (16,), 'dec_blocks.0.0.n1.bias': (16,),
    'dec_blocks.0.0.c1.weight': (16, 16, 3, 3, 3), 'dec_blocks.0.0.c1.bias': (16,), 'dec_blocks.0.0.n2.weight':
    (16,), 'dec_blocks.0.0.n2.bias': (16,), 'dec_blocks.0.0.c2.weight': (16, 16, 3, 3, 3),
    'dec_blocks.0.0.c2.bias': (16,), 'dec_blocks.1.0.n1.weight': (8,), 'dec_blocks.1.0.n1.bias': (8,),
    'dec_blocks.1.0.c1.weight': (8, 8, 3, 3, 3), 'dec_blocks.1.0.c1.bias': (8,), 'dec_blocks.1.0.n2.weight':
    (8,), 'dec_blocks.1.0.n2.bias': (8,), 'dec_blocks.1.0.c2.weight': (8, 8, 3, 3, 3), 'dec_blocks.1.0.c2.bias':
    (8,), 'occ_heads.0.weight': (1, 16, 1, 1, 1), 'occ_heads.0.bias': (1,), 'occ_heads.1.weight': (1, 8, 1, 1,
    1), 'occ_heads.1.bias': (1,), 'up.0.weight': (16, 8, 2, 2, 2), 'up.0.bias': (8,), 'child_head.0.weight':
    (8,), 'child_head.0.bias': (8,), 'child_head.2.weight': (216, 8, 1, 1, 1), 'child_head.2.bias': (216,),
}
VAE0_KEYS = {
    'latent_std': (), '_latent_sq': (), '_latent_n': (), 'down.0.0.weight': (8, 27, 2, 2, 2), 'down.0.0.bias':
    (8,), 'down.1.0.weight': (16, 8, 2, 2, 2), 'down.1.0.bias': (16,), 'to_latent.0.weight': (16,),
    'to_latent.0.bias': (16,), 'to_latent.2.weight': (16, 16, 1, 1, 1), 'to_latent.2.bias': (16,),
    'from_latent.weight': (16, 8, 3, 3, 3), 'from_latent.bias': (16,), 'dec_blocks.0.0.n1.weight': (16,),
    'dec_blocks.0.0.n1.bias': (16,), 'dec_blocks.0.0.c1.weight': (16, 16, 3, 3, 3), 'dec_blocks.0.0.c1.bias':
    (16,), 'dec_blocks.0.0.n2.weight': (16,), 'dec_blocks.0.0.n2.bias': (16,), 'dec_blocks.0.0.c2.weight': (16,
    16, 3, 3, 3), 'dec_blocks.0.0.c2.bias': (16,), 'dec_blocks.1.0.n1.weight': (8,), 'dec_blocks.1.0.n1.bias':
    (8,), 'dec_blocks.1.0.c1.weight': (8, 8, 3, 3, 3), 'dec_blocks.1.0.c1.bias': (8,),
    'dec_blocks.1.0.n2.weight': (8,), 'dec_blocks.1.0.n2.bias': (8,), 'dec_blocks.1.0.c2.weight': (8, 8, 3, 3,
    3), 'dec_blocks.1.0.c2.bias': (8,), 'occ_heads.0.weight': (1, 16, 1, 1, 1), 'occ_heads.0.bias': (1,),
    'occ_heads.1.weight': (1, 8, 1, 1, 1), 'occ_heads.1.bias': (1,), 'up.0.weight': (16, 8, 2, 2, 2),
    'up.0.bias': (8,), 'child_head.0.weight': (8,), 'child_head.0.bias': (8,), 'child_head.2.weight': (216, 8,
    1, 1, 1), 'child_head.2.bias': (216,),
}


def _shapes(module: torch.nn.Module) -> dict:
    return {k: tuple(v.shape) for k, v in module.state_dict().items()}


def test_the_original_layouts_keep_their_keys():
    with META:
        assert _shapes(Denoiser3d(4, 3, (8, 16), 2, 4)) == DENOISER_KEYS
        assert _shapes(Denoiser3d(4, 3, (8, 16), 2, 4, attention_levels=(), heads=3, layout="plain")) == DENOISER_KEYS
        assert _shapes(StructureVAE(VAEConfig(widths=(8, 16), blocks=1))) == VAE_KEYS
        assert _shapes(StructureVAE(VAEConfig(widths=(8, 16), blocks=0))) == VAE0_KEYS
        with_attention = _shapes(Denoiser3d(4, 3, (8, 16), 2, 4, attention_levels=(1,), heads=2))
    new = set(with_attention) - set(DENOISER_KEYS)
    assert set(DENOISER_KEYS) <= set(with_attention)
    assert new and all(k.split(".")[0] in ("enc_attn", "dec_attn", "mid_attn") for k in new)


def _randomise(module: torch.nn.Module) -> None:
    """Every parameter random (the zero-initialised projections would hide a dead branch)."""
    with torch.no_grad():
        for p in module.parameters():
            p.normal_(0.0, 0.2)


@pytest.mark.parametrize("layout", ["plain", "ldm"])
def test_a_denoiser_with_attention_runs_forward_and_backward(layout):
    torch.manual_seed(0)
    net = Denoiser3d(4, 3, (8, 16), 1, 4, attention_levels=(1,), heads=2, layout=layout)
    assert isinstance(net.enc_attn[1], SelfAttention3d) and isinstance(net.enc_attn[0], torch.nn.Identity)
    assert isinstance(net.mid_attn, SelfAttention3d)  # level 1 is the deepest
    assert sum(isinstance(m, SelfAttention3d) for m in net.dec_attn) == (2 if layout == "ldm" else 1)
    fresh = net(torch.randn(2, 4, 4, 4, 4), torch.randn(2, 3, 4, 4, 4), torch.tensor([0, 999]))
    assert fresh.shape == (2, 4, 4, 4, 4) and bool((fresh == 0).all())  # zero-initialised output
    _randomise(net)
    z = torch.randn(2, 4, 4, 4, 4, requires_grad=True)
    out = net(z, torch.randn(2, 3, 4, 4, 4), torch.tensor([3, 500]))
    out.square().mean().backward()
    assert bool(torch.isfinite(out).all()) and bool(torch.isfinite(z.grad).all())
    for name, p in net.named_parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name
    assert float(net.enc_attn[1].qkv.weight.grad.abs().sum()) > 0


def test_self_attention_is_permutation_equivariant_and_global():
    torch.manual_seed(0)
    block = SelfAttention3d(8, 2, 4)
    _randomise(block)
    x = torch.randn(1, 8, 3, 3, 3)
    perm = torch.randperm(27)
    with torch.no_grad():
        y = block(x).flatten(2)
        y_perm = block(x.flatten(2)[:, :, perm].reshape(x.shape)).flatten(2)
        assert torch.allclose(y_perm, y[:, :, perm], atol=1e-5)
        x2 = x.clone()
        x2[0, :, 0, 0, 0] += 1.0  # one corner voxel: the opposite corner's output moves too
        assert float((block(x2) - block(x))[0, :, 2, 2, 2].abs().max()) > 1e-4


def test_bad_denoiser_settings_are_refused():
    with pytest.raises(ValueError, match="levels 0 to 1"):
        Denoiser3d(4, 3, (8, 16), 1, 4, attention_levels=(2,))
    with pytest.raises(ValueError, match="16 channels do not split into 3 heads"):
        Denoiser3d(4, 3, (8, 16), 1, 4, attention_levels=(1,), heads=3)
    with pytest.raises(ValueError, match="layout"):
        Denoiser3d(4, 3, (8, 16), 1, 4, layout="dit")


def _ldm_unet_params(latent_in: int, latent_out: int, mc: int, mult, nrb: int, attention_ds: set) -> int:
    """Parameters of LDM's openai UNetModel (3D, use_scale_shift_norm, resblock_updown, middle
    attention), counted from its definition: the oracle of the ldm layout."""
    e = 4 * mc

    def res(cin, cout):
        return 2 * cin + 27 * cin * cout + cout + e * 2 * cout + 2 * cout + 2 * cout + 27 * cout * cout + cout + \
            (cin * cout + cout if cin != cout else 0)

    def attn(c):
        return 2 * c + 3 * c * c + 3 * c + c * c + c

    n = mc * e + e + e * e + e + 27 * latent_in * mc + mc
    ch, chans, ds = mc, [mc], 1
    for level, m in enumerate(mult):
        for _ in range(nrb):
            n += res(ch, m * mc) + (attn(m * mc) if ds in attention_ds else 0)
            ch = m * mc
            chans.append(ch)
        if level < len(mult) - 1:
            n += res(ch, ch)
            chans.append(ch)
            ds *= 2
    n += 2 * res(ch, ch) + attn(ch)
    for level, m in reversed(list(enumerate(mult))):
        for i in range(nrb + 1):
            n += res(ch + chans.pop(), m * mc) + (attn(m * mc) if ds in attention_ds else 0)
            ch = m * mc
            if level and i == nrb:
                n += res(ch, ch)
                ds //= 2
    return n + 2 * ch + 27 * ch * latent_out + latent_out


def test_the_ldm_layout_has_the_ldm_unets_parameters():
    with META:
        net = Denoiser3d(8, 32, (192, 384, 768, 768), 2, 32, attention_levels=(2, 3), heads=8, layout="ldm")
        small = Denoiser3d(4, 4, (16, 32, 32), 1, 8, attention_levels=(2,), heads=4, layout="ldm")
    assert _params(net) == _ldm_unet_params(40, 8, 192, (1, 2, 4, 4), 2, {4, 8})
    assert _params(small) == _ldm_unet_params(8, 4, 16, (1, 2, 2), 1, {4})


def test_the_vae_with_a_full_resolution_stem_and_its_own_decoder_blocks():
    torch.manual_seed(0)
    cfg = VAEConfig(widths=(8, 16), blocks=1, input_width=4, decoder_blocks=2, latent_channels=2, groups=4)
    vae = StructureVAE(cfg)
    assert len(vae.stem) == 2 and all(len(b) == 2 for b in vae.dec_blocks)
    occ = (torch.rand(1, 8, 8, 8) > 0.6).float()
    labels = torch.where(occ > 0, torch.randint(0, 5, occ.shape), torch.full(occ.shape, -1))
    mu, logvar, occ_levels, occ_final, lab = vae(occ, labels)
    assert mu.shape == (1, 2, 2, 2, 2) and [o.shape[-1] for o in occ_levels] == [2, 4]
    assert occ_final.shape == (1, 8, 8, 8) and lab.shape[-3:] == (8, 8, 8)
    loss, _ = vae.loss(occ, labels)
    loss.backward()
    assert bool(torch.isfinite(vae.stem[0].weight.grad).all()) and float(vae.stem[0].weight.grad.abs().sum()) > 0
