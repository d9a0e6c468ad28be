"""The geometry stage's image encoders: shapes and strides of every kind, the shipped
EfficientNet-Lite0 ImageNet weights (strict load, and the classifier they make recognises the
vehicles in a real nuScenes photo), dinov2 state dicts in and out, freezing, input errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from scube_sim.config import ConfigError, validate_model
from scube_sim.errors import InputError
from scube_sim.model.nn.image_encoder import (
    LITE_MEAN,
    LITE_STD,
    ImageEncoderConfig,
    build_image_encoder,
    efficientnet_lite0_classifier,
    efficientnet_lite0_weights_path,
)
from tests.conftest import require

TINY = {"embed_dim": 32, "depth": 2, "num_heads": 2, "img_size": 56}  # a 4 x 4 position grid
SIZES = [(64, 96), (37, 53), (13, 7), (1, 1)]  # odd sizes: the map covers the image (ceil)

# ImageNet ids of vehicles and street furniture (555 fire engine and 660 mobile home are
# vehicles too: the photo's box truck is easily read as either)
VEHICLES = {407, 436, 468, 479, 511, 555, 569, 575, 581, 609, 627, 654, 656, 660, 661, 675, 705, 717,
            734, 751, 757, 779, 803, 817, 829, 864, 867, 874, 919, 920}
TRUCKS = {569, 675, 867}  # garbage truck, moving van, trailer truck


def encoder(**kw):
    return build_image_encoder(validate_model(ImageEncoderConfig, kw, "encoder.yaml"))


@pytest.mark.parametrize("kw", [
    {"kind": "cnn", "stride": 4}, {"kind": "cnn", "stride": 8}, {"kind": "cnn", "stride": 16},
    {"kind": "cnn", "stride": 4, "context_stride": 8}, {"kind": "cnn", "stride": 4, "context_stride": 16},
    {"kind": "efficientnet-lite0", "stride": 4, "pretrained": False},
    {"kind": "efficientnet-lite0", "stride": 8, "pretrained": False},
    {"kind": "efficientnet-lite0", "stride": 16, "pretrained": False},
    {"kind": "dinov2", "stride": 14, "dinov2_arch": TINY},
], ids=lambda kw: f"{kw['kind']}-{kw['stride']}-{kw.get('context_stride')}")
def test_output_shape_is_ceil_of_size_over_stride(kw):
    enc = encoder(channels=24, **kw).eval()
    assert (enc.out_channels, enc.stride) == (24, kw["stride"])
    for h, w in SIZES:
        with torch.no_grad():
            y = enc(torch.rand(2, 3, h, w))
        assert y.shape == (2, 24, math.ceil(h / enc.stride), math.ceil(w / enc.stride)), (h, w)
        assert torch.isfinite(y).all()


@pytest.mark.parametrize("kw, key", [
    ({"kind": "dinov2"}, "stride"),  # default stride 8: dinov2 has 14 only
    ({"kind": "cnn", "stride": 14}, "stride"),
    ({"kind": "efficientnet-lite0", "stride": 32}, "stride"),
    ({"kind": "cnn", "freeze_backbone": True}, "freeze_backbone"),
    ({"kind": "dinov2", "stride": 14, "dinov2_arch": {"embed_dim": 30, "num_heads": 4}}, "num_heads"),
    ({"kind": "resnet"}, "kind"),
    ({"kind": "cnn", "chanels": 8}, "chanels"),
    ({"kind": "cnn", "stride": 8, "context_stride": 4}, "context_stride"),
    ({"kind": "cnn", "stride": 4, "context_stride": 32}, "context_stride"),
    ({"kind": "efficientnet-lite0", "stride": 4, "context_stride": 8}, "context_stride"),
])
def test_bad_config_names_the_key(kw, key):
    with pytest.raises(ConfigError, match=key):
        validate_model(ImageEncoderConfig, kw, "encoder.yaml")


def _receptive_extent(enc, size: int = 96) -> int:
    """Width in pixels of the input region that moves the centre output pixel, group norms
    (whose statistics span the whole image) replaced by identities."""
    for m in list(enc.modules()):
        for name, child in m.named_children():
            if isinstance(child, torch.nn.GroupNorm):
                setattr(m, name, torch.nn.Identity())
    x = torch.rand(1, 3, size, size, requires_grad=True)
    y = enc(x)
    y[0, :, y.shape[2] // 2, y.shape[3] // 2].sum().backward()
    cols = torch.nonzero(x.grad.abs().sum((0, 1, 2)))[:, 0]
    return int(cols.max() - cols.min() + 1)


def test_context_stride_gives_a_fine_map_the_coarse_maps_context():
    torch.manual_seed(0)
    fine, coarse, both = (encoder(channels=8, **kw) for kw in (
        {"stride": 4}, {"stride": 8}, {"stride": 4, "context_stride": 8}))
    # the stride-4 map alone sees little; with the way back up it sees at least what stride 8 sees
    assert _receptive_extent(fine) < _receptive_extent(coarse) <= _receptive_extent(both)


def test_dinov2_stride_error_says_14():
    with pytest.raises(ConfigError, match="14"):
        validate_model(ImageEncoderConfig, {"kind": "dinov2"}, "encoder.yaml")


# ---------------------------------------------------------------------------- efficientnet-lite0
def test_shipped_lite0_weights_load_strict_and_unchanged():
    sd = torch.load(efficientnet_lite0_weights_path(), map_location="cpu", weights_only=True)
    net = efficientnet_lite0_classifier(pretrained=True)
    own = net.state_dict()
    assert own.keys() == sd.keys()
    assert all(torch.equal(own[k], sd[k]) for k in sd)
    assert net.load_state_dict(sd, strict=True)  # no missing / unexpected keys


@pytest.fixture(scope="module")
def front_photo(request):
    from PIL import Image

    data = request.getfixturevalue("shared_data")
    folder = require(data / "nuscenes-mmdet3d-demo")
    paths = sorted(folder.glob("*__CAM_FRONT__*.jpg"))
    if not paths:
        pytest.skip(f"no CAM_FRONT photo in {folder}")
    return Image.open(paths[0]).convert("RGB")  # 1600 x 900; a box truck parked on the left


def classify(net, image) -> tuple[list[int], list[float]]:
    """Top-5 ImageNet ids and probabilities of a PIL image resized to 224 x 224."""
    from PIL import Image

    x = np.asarray(image.resize((224, 224), Image.BICUBIC), dtype=np.float32) / 255.0
    x = torch.from_numpy(x).permute(2, 0, 1)[None]
    x = (x - torch.tensor(LITE_MEAN).view(1, 3, 1, 1)) / torch.tensor(LITE_STD).view(1, 3, 1, 1)
    with torch.no_grad():
        p = net(x).softmax(-1)[0]
    v, i = p.topk(5)
    return i.tolist(), v.tolist()


def test_lite0_classifier_sees_the_truck_in_a_street_photo(front_photo):
    net = efficientnet_lite0_classifier(pretrained=True)
    # the truck (its box fills a square crop, pixels x 100-680, y 180-760)
    top, prob = classify(net, front_photo.crop((100, 180, 680, 760)))
    assert top[0] in TRUCKS and prob[0] > 0.5, (top, prob)
    assert len(VEHICLES.intersection(top)) >= 4, (top, prob)
    # the whole frame (squashed to a square): a street scene with that truck in front
    top, prob = classify(net, front_photo)
    assert top[0] in VEHICLES and len(VEHICLES.intersection(top)) >= 4, (top, prob)
    # the same network with random weights does not (the weights carry the recognition)
    torch.manual_seed(0)
    top, _ = classify(efficientnet_lite0_classifier(pretrained=False), front_photo.crop((100, 180, 680, 760)))
    assert len(VEHICLES.intersection(top)) < 4


def test_frozen_backbone_gets_no_grads_and_keeps_its_statistics():
    enc = encoder(kind="efficientnet-lite0", stride=8, freeze_backbone=True).train()
    bn = enc.backbone._bn0
    stats = bn.running_mean.clone()
    enc(torch.rand(2, 3, 40, 56)).square().mean().backward()
    assert all(p.grad is None for p in enc.backbone.parameters())
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in enc.proj.parameters())
    assert not bn.training and torch.equal(bn.running_mean, stats)

    enc = encoder(kind="efficientnet-lite0", stride=8, freeze_backbone=False).train()
    enc(torch.rand(2, 3, 40, 56)).square().mean().backward()
    assert all(p.grad is not None for p in enc.backbone.parameters())


# ---------------------------------------------------------------------------- dinov2
def test_dinov2_state_dict_round_trip(tmp_path):
    torch.manual_seed(0)
    src = encoder(kind="dinov2", stride=14, dinov2_arch=TINY).eval()
    with torch.no_grad():  # LayerScale starts at 1e-5: make the blocks count in the comparison
        for blk in src.backbone.blocks:
            blk.ls1.gamma.fill_(0.5)
            blk.ls2.gamma.fill_(0.5)
    path = tmp_path / "vit.pth"
    torch.save(src.backbone.state_dict(), path)
    assert "blocks.1.attn.qkv.weight" in src.backbone.state_dict()  # the official key layout

    torch.manual_seed(1)
    dst = encoder(kind="dinov2", stride=14, dinov2_arch=TINY, dinov2_weights=str(path)).eval()
    dst.proj.load_state_dict(src.proj.state_dict())
    x = torch.rand(2, 3, 50, 71)  # 4 x 6 patches: the 4 x 4 grid is interpolated
    with torch.no_grad():
        a, b = src(x), dst(x)
        fresh = encoder(kind="dinov2", stride=14, dinov2_arch=TINY)(x)
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert not torch.allclose(a, fresh)


def test_dinov2_weights_errors_name_the_key(tmp_path):
    with pytest.raises(ConfigError, match="dinov2_weights: no such file"):
        encoder(kind="dinov2", stride=14, dinov2_arch=TINY, dinov2_weights=str(tmp_path / "absent.pth"))

    sd = encoder(kind="dinov2", stride=14, dinov2_arch=TINY).backbone.state_dict()
    sd["blocks.0.attn.qkv_renamed.weight"] = sd.pop("blocks.0.attn.qkv.weight")
    torch.save(sd, tmp_path / "renamed.pth")
    with pytest.raises(ConfigError) as err:
        encoder(kind="dinov2", stride=14, dinov2_arch=TINY, dinov2_weights=str(tmp_path / "renamed.pth"))
    msg = str(err.value)
    assert "dinov2_weights" in msg and "renamed.pth" in msg
    assert "missing keys: blocks.0.attn.qkv.weight" in msg
    assert "unexpected keys: blocks.0.attn.qkv_renamed.weight" in msg

    sd = encoder(kind="dinov2", stride=14, dinov2_arch=TINY).backbone.state_dict()
    torch.save(sd, tmp_path / "tiny.pth")  # a different arch: shapes do not fit
    with pytest.raises(ConfigError, match="wrong shapes: cls_token"):
        encoder(kind="dinov2", stride=14, dinov2_arch={**TINY, "embed_dim": 16},
                dinov2_weights=str(tmp_path / "tiny.pth"))

    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError, match="dinov2_weights: .*junk.pth"):
        encoder(kind="dinov2", stride=14, dinov2_arch=TINY, dinov2_weights=str(tmp_path / "junk.pth"))


# ---------------------------------------------------------------------------- input errors
@pytest.mark.parametrize("images", [
    torch.rand(3, 32, 32), torch.rand(2, 1, 32, 32), torch.rand(2, 32, 32, 3), torch.rand(0, 3, 32, 32),
    torch.zeros(2, 3, 32, 32, dtype=torch.uint8), np.zeros((2, 3, 32, 32), np.float32),
], ids=["no-batch", "gray", "channels-last", "empty", "uint8", "numpy"])
def test_bad_images_raise_input_error(images):
    enc = encoder(kind="cnn")
    with pytest.raises(InputError, match="images: expected"):
        enc(images)
