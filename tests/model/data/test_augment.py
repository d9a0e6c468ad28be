"""`scube_sim.model.augment` on synthetic images: each augmentation's measurable effect (linear-light
gain, high-frequency energy, noise variance against the shot + read model, JPEG error), identities
at zero strength, seeding, and the camera choice of rig randomisation."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from scube_sim.errors import InputError
from scube_sim.model.data.augment import (
    AugmentConfig,
    BlurConfig,
    CameraSelection,
    adjust_color,
    adjust_exposure,
    choose_cameras,
    color_jitter,
    front_camera,
    gaussian_blur,
    jpeg,
    linear_to_srgb,
    photometric,
    random_exposure,
    sensor_noise,
    srgb_to_linear,
)

WAYMO = ["FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT"]
NUSCENES = ["CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK_RIGHT", "CAM_BACK"]


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def scene(h: int = 48, w: int = 64, seed: int = 0) -> torch.Tensor:
    """A photograph-like test image: smooth colour gradients plus a few hard edges, in [0.1, 0.7]."""
    v, u = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    img = torch.stack([0.2 + 0.4 * u, 0.3 + 0.3 * v, 0.5 - 0.3 * u * v])
    img[:, h // 4: h // 2, w // 3: w // 2] = torch.tensor([0.7, 0.15, 0.1]).view(3, 1, 1)
    img += 0.03 * torch.rand(img.shape, generator=gen(seed))
    return img.clamp(0.1, 0.7)


def high_frequency_energy(img: torch.Tensor) -> float:
    return float((img[:, :, 1:] - img[:, :, :-1]).pow(2).sum() + (img[:, 1:] - img[:, :-1]).pow(2).sum())


# --- colour ------------------------------------------------------------------------------------------


def test_color_jitter_of_zero_is_identity():
    img = scene()
    assert torch.equal(color_jitter(img, gen(), 0.0, 0.0, 0.0, 0.0), img)
    assert torch.equal(adjust_color(img), img)


def test_adjust_color_factors():
    img = scene()
    np.testing.assert_allclose(adjust_color(img, brightness=0.5).numpy(), 0.5 * img.numpy(), rtol=1e-6)
    grey = adjust_color(img, saturation=0.0)
    assert torch.allclose(grey[0], grey[1], atol=1e-6) and torch.allclose(grey[1], grey[2], atol=1e-6)
    flat = adjust_color(img, contrast=0.0)
    assert float(flat.std()) < 1e-6  # everything at the mean grey
    # a third of a turn about the grey axis takes red to green and green to blue; greys stay
    prim = torch.tensor([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 0.5]]).view(3, 1, 3)
    rot = adjust_color(prim, hue=1 / 3)
    torch.testing.assert_close(rot[:, 0, 0], torch.tensor([0.0, 1.0, 0.0]), atol=1e-6, rtol=0)
    torch.testing.assert_close(rot[:, 0, 1], torch.tensor([0.0, 0.0, 1.0]), atol=1e-6, rtol=0)
    torch.testing.assert_close(rot[:, 0, 2], torch.tensor([0.5, 0.5, 0.5]), atol=1e-6, rtol=0)


def test_color_jitter_draws_within_its_ranges():
    img = scene()
    ratios = [float(color_jitter(img, gen(s), brightness=0.2).mean() / img.mean()) for s in range(20)]
    assert all(0.8 - 1e-6 <= r <= 1.2 + 1e-6 for r in ratios) and np.std(ratios) > 0.02
    with pytest.raises(InputError, match="hue"):
        color_jitter(img, gen(), hue=0.7)


# --- exposure, blur, noise -------------------------------------------------------------------------------


def test_exposure_gain_scales_linear_light():
    img = scene()  # at most 0.7 sRGB (0.45 linear): a gain of 2 does not clip
    lin = srgb_to_linear(img)
    for gain in (0.5, 1.7, 2.0):
        out = srgb_to_linear(adjust_exposure(img, gain))
        assert float(out.mean() / lin.mean()) == pytest.approx(gain, rel=1e-4)
        torch.testing.assert_close(out, lin * gain, atol=2e-6, rtol=1e-4)
    # the mean of the sRGB values does not scale by the gain: the gain acts in linear light
    assert float(adjust_exposure(img, 2.0).mean() / img.mean()) < 1.5
    ratio = float(srgb_to_linear(random_exposure(img, gen(3), stops=1.0)).mean() / lin.mean())
    assert 0.5 <= ratio <= 2.0 and ratio != pytest.approx(1.0, abs=1e-3)
    assert torch.equal(random_exposure(img, gen(3), 1.0), random_exposure(img, gen(3), 1.0))
    with pytest.raises(InputError, match="gain"):
        adjust_exposure(img, 0.0)


def test_srgb_curve_round_trips():
    x = torch.linspace(0, 1, 1001)
    torch.testing.assert_close(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-6, rtol=0)
    assert float(srgb_to_linear(torch.tensor(0.5))) == pytest.approx(0.21404, abs=1e-5)  # the standard's value


def test_blur_lowers_high_frequency_energy():
    img = torch.rand((3, 40, 40), generator=gen(1)) * 0.8 + 0.1
    e = high_frequency_energy(img)
    e1, e2 = high_frequency_energy(gaussian_blur(img, 1.0)), high_frequency_energy(gaussian_blur(img, 2.0))
    assert e2 < e1 < 0.5 * e
    assert torch.equal(gaussian_blur(img, 0.0), img)
    flat = torch.full((3, 20, 30), 0.4)
    torch.testing.assert_close(gaussian_blur(flat, 1.5), flat, atol=1e-6, rtol=0)  # borders replicated
    # a blur keeps the image's linear-light mean (energy), away from the borders
    big = scene(64, 96)
    inner = (slice(None), slice(8, -8), slice(8, -8))
    assert float(srgb_to_linear(gaussian_blur(big, 1.0))[inner].mean()) == pytest.approx(
        float(srgb_to_linear(big)[inner].mean()), rel=0.01)


@pytest.mark.parametrize("shot, read", [(0.01, 0.0), (0.0, 0.02), (0.005, 0.01)])
def test_noise_variance_matches_the_shot_and_read_model(shot, read):
    value = 0.5  # sRGB, 0.214 linear: 4 standard deviations from both clipping ends
    img = torch.full((3, 128, 128), value)
    out = srgb_to_linear(sensor_noise(img, gen(5), shot, read)).double()
    x = float(srgb_to_linear(torch.tensor(value)))
    expect = shot * x + read ** 2
    assert float(out.var()) == pytest.approx(expect, rel=0.03)
    assert float(out.mean()) == pytest.approx(x, abs=3 * np.sqrt(expect / out.numel()) + 1e-6)
    assert torch.equal(sensor_noise(img, gen(5), shot, read), sensor_noise(img, gen(5), shot, read))
    assert not torch.equal(sensor_noise(img, gen(5), shot, read), sensor_noise(img, gen(6), shot, read))


def test_no_noise_is_identity_up_to_the_srgb_round_trip():
    img = scene()
    torch.testing.assert_close(sensor_noise(img, gen(), 0.0, 0.0), img, atol=1e-6, rtol=0)


# --- JPEG ----------------------------------------------------------------------------------------------


def test_jpeg_changes_the_image_within_a_bounded_error():
    img = scene(64, 96)
    errors = {}
    for q in (10, 50, 95):
        out = jpeg(img, q)
        assert out.shape == img.shape and out.dtype == torch.float32
        assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0
        errors[q] = float((out - img).abs().mean())
        assert not torch.equal(out, img)
    assert errors[95] < errors[50] < errors[10] < 0.08
    assert errors[95] < 0.01
    # the artefacts are those of a decodable stream: re-encoding at the same quality changes little
    once = jpeg(img, 50)
    assert float((jpeg(once, 50) - once).abs().mean()) < errors[50]
    with pytest.raises(InputError, match="quality"):
        jpeg(img, 0)


# --- the pipeline ----------------------------------------------------------------------------------------


def test_photometric_with_every_probability_zero_is_identity():
    cfg = AugmentConfig.model_validate({k: {"p": 0.0} for k in ("color_jitter", "exposure", "blur", "noise", "jpeg")})
    img = scene()
    assert torch.equal(photometric(img, gen(), cfg), img)


def test_photometric_is_a_function_of_the_generator():
    cfg = AugmentConfig.model_validate({k: {"p": 1.0} for k in ("color_jitter", "exposure", "blur", "noise", "jpeg")})
    img = scene()
    a, b, c = photometric(img, gen(7), cfg), photometric(img, gen(7), cfg), photometric(img, gen(8), cfg)
    assert torch.equal(a, b) and not torch.equal(a, c) and not torch.equal(a, img)
    assert a.shape == img.shape and float(a.min()) >= 0 and float(a.max()) <= 1
    with pytest.raises(InputError, match=r"\(3, H, W\)"):
        photometric(img[0], gen(), cfg)


def test_augment_config_is_strict():
    with pytest.raises(ValidationError, match="low <= high"):
        BlurConfig(sigma=(2.0, 1.0))
    with pytest.raises(ValidationError):
        AugmentConfig.model_validate({"jpeg": {"quality": [0, 90]}})
    with pytest.raises(ValidationError, match="Extra inputs"):
        AugmentConfig.model_validate({"exposure": {"p": 0.5, "ev": 1}})


# --- rig randomisation ---------------------------------------------------------------------------------------


def test_front_camera_of_both_rigs():
    assert front_camera(WAYMO) == 0 and front_camera(NUSCENES) == 0
    assert front_camera(["SIDE_LEFT", "front"]) == 1
    with pytest.raises(InputError, match="front camera named FRONT or CAM_FRONT"):
        front_camera(["SIDE_LEFT", "SIDE_RIGHT"])


@pytest.mark.parametrize("names", [WAYMO, NUSCENES], ids=["waymo-5", "nuscenes-6"])
def test_choose_cameras_modes(names):
    assert choose_cameras(names, gen(), CameraSelection(mode="all")) == list(range(len(names)))
    assert choose_cameras(names, gen(), CameraSelection(mode="front")) == [0]
    assert choose_cameras(names, gen(), CameraSelection(mode="drop", drop_p=1.0, keep_front=True)) == [0]
    picks = [choose_cameras(names, gen(s), CameraSelection(mode="drop", drop_p=1.0, keep_front=False))
             for s in range(30)]
    assert all(len(p) == 1 for p in picks) and len({p[0] for p in picks}) > 2  # one, not always the same
    subsets = []
    for s in range(40):
        keep = choose_cameras(names, gen(s), CameraSelection(mode="drop", drop_p=0.5, keep_front=True))
        assert keep == sorted(set(keep)) and 0 in keep and all(0 <= i < len(names) for i in keep)
        subsets.append(tuple(keep))
    sizes = [len(k) for k in subsets]
    assert len(set(subsets)) > 10
    # each other camera stays with probability 1 - drop_p
    assert np.mean(sizes) - 1 == pytest.approx(0.5 * (len(names) - 1), abs=0.6)
    assert choose_cameras(names, gen(4), CameraSelection(mode="drop")) == \
        choose_cameras(names, gen(4), CameraSelection(mode="drop"))
