"""Texture statistics against analytic images: constants, sinusoids of known amplitude and period,
masks, and the resampling to the common scale."""

import math

import numpy as np
import pytest

from scube_sim.camera.texture import (
    LARGE_WINDOW,
    MATCHABLE_THRESHOLD,
    class_statistics,
    texture_statistics,
    to_common_scale,
    to_grey,
)

H = 40
MEAN = 0.5


def _sinusoid(width: int, period: float, amp: float, height: int = H) -> np.ndarray:
    """(height, width) float64: MEAN + amp * sin(2 pi x / period), varying along x only."""
    x = np.arange(width)
    return np.broadcast_to(MEAN + amp * np.sin(2 * np.pi * x / period), (height, width)).copy()


def test_constant_image_has_no_texture():
    st = texture_statistics(np.full((H, 50), 0.4))
    assert st["gradient_energy"] == 0.0 and st["contrast_7"] == 0.0 and st["contrast_15"] == 0.0
    assert st["matchable"] == 0.0
    # every pixel whose 15 x 15 window stays inside the image
    assert st["pixels"] == (H - (LARGE_WINDOW - 1)) * (50 - (LARGE_WINDOW - 1))


def test_black_image_counts_as_texture_free():
    st = texture_statistics(np.zeros((H, 30)))
    assert st["contrast_7"] == 0.0 and st["matchable"] == 0.0


def test_sinusoid_gradient_energy():
    # Sobel / 8 of a sinusoid along x is the central difference (the [1, 2, 1] smoothing across is
    # a no-op): a sin(w) cos(w x), w = 2 pi / P. Its mean square over a whole number of half
    # periods (cos^2 has period P / 2) is a^2 sin^2(w) / 2, exact up to float64 rounding (~1e-15).
    period, amp = 16, 0.1
    width = (LARGE_WINDOW - 1) + 8 * (period // 2)  # 8 half periods of measured columns
    w = 2 * np.pi / period
    st = texture_statistics(_sinusoid(width, period, amp))
    assert st["gradient_energy"] == pytest.approx(amp**2 * math.sin(w) ** 2 / 2, rel=1e-9)
    # ... and the continuous derivative's a^2 w^2 / 2 within the discretisation's relative error
    # 1 - sin^2(w) / w^2 ~ w^2 / 3 (5 % at P = 16)
    continuum = amp**2 * w**2 / 2
    assert st["gradient_energy"] == pytest.approx(continuum, rel=w**2 / 3 * 1.05)
    assert st["gradient_energy"] < continuum


@pytest.mark.parametrize("period,key", [(7, "contrast_7"), (5, "contrast_15")])
def test_sinusoid_normalised_std(period, key):
    # A window holding a whole number of periods (7 = 1 x 7, 15 = 3 x 5) samples the sinusoid at
    # equally spaced phases: its mean is MEAN and its (population) std amp / sqrt(2) exactly, at
    # every pixel, so the median is that too.
    amp = 0.1
    st = texture_statistics(_sinusoid(60, period, amp))
    assert st[key] == pytest.approx(amp / math.sqrt(2) / MEAN, rel=1e-9)


def test_matchable_share_follows_the_threshold():
    strong = texture_statistics(_sinusoid(60, 7, amp=2 * MATCHABLE_THRESHOLD * math.sqrt(2) * MEAN))
    weak = texture_statistics(_sinusoid(60, 7, amp=0.5 * MATCHABLE_THRESHOLD * math.sqrt(2) * MEAN))
    assert strong["matchable"] == 1.0 and weak["matchable"] == 0.0
    # the threshold is a parameter: lowered below the weak texture's contrast, it counts
    assert texture_statistics(_sinusoid(60, 7, amp=0.5 * MATCHABLE_THRESHOLD * math.sqrt(2) * MEAN),
                              window_threshold=0.2 * MATCHABLE_THRESHOLD)["matchable"] == 1.0


def test_mask_restricts_the_statistics():
    # left half: a sinusoid of period 7; right half: constant. Each half's mask gives that half's
    # numbers alone (the windows that straddle the seam are left out), and the pixel count is the
    # half's interior.
    half = 40
    img = np.concatenate([_sinusoid(half, 7, 0.1), np.full((H, half), MEAN)], axis=1)
    left = np.zeros(img.shape, bool)
    left[:, :half] = True
    st_left = texture_statistics(img, left)
    st_right = texture_statistics(img, ~left)
    interior = (H - (LARGE_WINDOW - 1)) * (half - (LARGE_WINDOW - 1))
    assert st_left["pixels"] == st_right["pixels"] == interior
    assert st_left["contrast_7"] == pytest.approx(0.1 / math.sqrt(2) / MEAN, rel=1e-9)
    assert st_left["matchable"] == 1.0
    assert st_right["gradient_energy"] == 0.0 and st_right["contrast_7"] == 0.0 and st_right["matchable"] == 0.0
    # the whole image mixes both
    st_all = texture_statistics(img)
    assert 0.0 < st_all["matchable"] < 1.0


def test_empty_mask_gives_nan_and_no_pixels():
    img = _sinusoid(30, 7, 0.1)
    thin = np.zeros(img.shape, bool)
    thin[:, 10:20] = True  # narrower than a 15 x 15 window: nothing measurable
    st = texture_statistics(img, thin)
    assert st["pixels"] == 0 and math.isnan(st["gradient_energy"]) and math.isnan(st["matchable"])


def test_class_statistics_adds_all():
    img = _sinusoid(40, 7, 0.1)
    road = np.ones(img.shape, bool)
    out = class_statistics(img, {"road": road})
    assert set(out) == {"road", "all"} and out["all"] == out["road"]
    own_all = class_statistics(img, {"all": np.zeros(img.shape, bool)})
    assert own_all["all"]["pixels"] == 0  # the caller's "all" wins


def test_to_common_scale_halves_a_double_focal_image():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (30, 50, 3), dtype=np.uint8)
    out = to_common_scale(img, focal_px=1000.0, target_focal_px=500.0)
    assert out.shape == (15, 25, 3) and out.dtype == np.float32
    # exact area averaging: each output pixel is the mean of its 2 x 2 block
    boxes = img.astype(np.float64).reshape(15, 2, 25, 2, 3).mean(axis=(1, 3)) / 255.0
    np.testing.assert_allclose(out, boxes, atol=1e-6)
    # a constant image stays constant at any factor
    np.testing.assert_allclose(to_common_scale(np.full((37, 41, 3), 200, np.uint8), 1266.0), 200 / 255, atol=1e-6)


def test_to_common_scale_leaves_near_and_coarser_scales_alone():
    img = np.arange(12 * 16 * 3, dtype=np.uint8).reshape(12, 16, 3)
    for focal in (511.0, 300.0):  # within 5 % of the target; coarser than it (never upscaled)
        out = to_common_scale(img, focal)
        assert out.shape == img.shape
        np.testing.assert_allclose(out, img / 255.0, atol=1e-7)


def test_to_grey_uses_luma_weights():
    rgb = np.zeros((2, 2, 3))
    rgb[..., 1] = 1.0
    np.testing.assert_allclose(to_grey(rgb), 0.587, atol=1e-6)
