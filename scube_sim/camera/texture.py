"""Texture statistics that say how matchable an image is for multi-view stereo.

A stereo matcher compares small windows of grey levels between views at its own angular scale.
So every image is first brought to one angular resolution (`to_common_scale`: a focal length of
`COMMON_FOCAL_PX` pixels, about that of the procedural worlds' images), turned into grey
(`to_grey`), and then measured (`texture_statistics`, per class `class_statistics`):

- gradient_energy: mean of |grad I|^2 (I grey in [0, 1]; the Sobel derivative divided by 8, i.e.
  grey levels per pixel), over the measured pixels;
- contrast_7, contrast_15: the median over the measured pixels of the local normalised standard
  deviation std / mean in 7 x 7 and 15 x 15 windows (gain-free: what normalised cross-correlation
  sees);
- matchable: the share of measured pixels whose 7 x 7 normalised std exceeds `MATCHABLE_THRESHOLD`;
- pixels: how many pixels were measured.

The measured pixels are those whose largest window (15 x 15) lies wholly inside the image and
inside the mask: a class's statistics describe the texture *within* its surface, not the edges
between surfaces (a car's silhouette against the road) nor an image border.

Pure functions of their inputs (numpy and scipy.ndimage): the same image gives the same numbers.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

# The common angular scale, in pixels of focal length: the worlds' images (the waymo-5 rig at the
# datasets' image scale 0.25: fx 511-516 px) are at about this scale, so they are left as rendered.
COMMON_FOCAL_PX = 500.0
# A focal within this share of the target is left as is: resampling by a factor so close to 1
# only blurs (a fractional-pixel shift interpolates neighbours, which lowers the gradient energy of
# the finest texture by up to about half) while it changes the angular scale by under 5 %.
SCALE_TOLERANCE = 0.05
# Local window sizes in pixels at the common scale (a typical stereo matching window and a wide one).
SMALL_WINDOW = 7
LARGE_WINDOW = 15
# The 7 x 7 normalised std above which a window is taken to be discriminative for matching.
# Reasoning: two views of a window with signal std s, each under independent noise of std n,
# correlate (NCC) at s^2 / (s^2 + n^2) on average; for the true match to reach 0.9 the signal must
# have s >= 3 n. An 8-bit automotive camera's noise at mid grey is about 2 DN (quantisation alone
# 1/sqrt(12) = 0.29 DN), so s >= 6 DN = 0.024 in grey levels, which at the typical grey level of
# street scenes (about 0.45) is a normalised std of about 0.05.
MATCHABLE_THRESHOLD = 0.05
# Rec. 601 luma weights, applied to the sRGB-encoded values as stereo pipelines do.
LUMA = np.array([0.299, 0.587, 0.114])
# The smallest local mean a std is divided by (1 DN): a black window counts as texture-free
# instead of dividing by zero.
MEAN_FLOOR = 1.0 / 255.0
# Local standard deviations below this (grey levels) are rounding noise of the box filters.
STD_FLOOR = 1e-6


def _area_matrix(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) weights of exact area averaging: output pixel i covers input [i*r, (i+1)*r)
    with r = n_in / n_out; each row sums to 1."""
    r = n_in / n_out
    lo = np.arange(n_out)[:, None] * r  # (n_out, 1) start of each output pixel in input pixels
    hi = lo + r
    j = np.arange(n_in)[None, :]  # (1, n_in) input pixel j spans [j, j + 1)
    overlap = np.clip(np.minimum(hi, j + 1) - np.maximum(lo, j), 0.0, None)
    return overlap / r


def to_common_scale(rgb: np.ndarray, focal_px: float, target_focal_px: float = COMMON_FOCAL_PX) -> np.ndarray:
    """An image resampled to the angular resolution of a `target_focal_px` focal length.

    rgb: (H, W, 3) uint8 sRGB (or (H, W) grey) taken with a focal length of `focal_px` pixels.
    Returns (H', W', 3) (or (H', W')) float32 in [0, 1] with H' = round(H * s), W' = round(W * s),
    s = target_focal_px / focal_px, by exact area averaging (antialiased: each output pixel is
    the mean of the input area it covers), so a 2x-focal image becomes a 2 x 2 box average.

    Not resampled, only converted to float: an image whose focal is within SCALE_TOLERANCE of the
    target (resampling by so little only blurs), and an image coarser than the target (upscaling
    adds no texture; it is then compared at its own, coarser scale, which the caller should
    report).
    """
    img = np.asarray(rgb)
    if img.dtype != np.uint8:
        raise TypeError(f"to_common_scale: expected a uint8 image, got {img.dtype}")
    if focal_px <= 0 or target_focal_px <= 0:
        raise ValueError(f"to_common_scale: focal lengths must be positive, got {focal_px} and {target_focal_px}")
    out = img.astype(np.float64) / 255.0
    s = float(target_focal_px) / float(focal_px)
    if s >= 1.0 - SCALE_TOLERANCE:
        return out.astype(np.float32)
    h, w = img.shape[:2]
    ay = _area_matrix(h, max(1, round(h * s)))
    ax = _area_matrix(w, max(1, round(w * s)))
    # separable: rows then columns; the channel axis (if any) rides along
    out = np.tensordot(ay, out, axes=(1, 0))  # (H', W[, 3])
    out = np.moveaxis(np.tensordot(ax, out, axes=(1, 1)), 0, 1)  # (W', H'[, 3]) -> (H', W'[, 3])
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def to_grey(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float in [0, 1] (sRGB-encoded) -> (H, W) float32 luma in [0, 1]; (H, W) passes."""
    img = np.asarray(rgb, np.float64)
    if img.ndim == 2:
        return img.astype(np.float32)
    return (img @ LUMA).astype(np.float32)


def measured_pixels(mask: np.ndarray | None, shape: tuple[int, int], window: int = LARGE_WINDOW) -> np.ndarray:
    """(H, W) bool: the pixels of `mask` (all if None) whose `window` x `window` neighbourhood
    lies wholly inside the image and inside the mask."""
    m = np.ones(shape, bool) if mask is None else np.asarray(mask, bool)
    if m.shape != tuple(shape):
        raise ValueError(f"mask of shape {m.shape} for an image of shape {tuple(shape)}")
    # a minimum filter with zeros beyond the border: 1 only where the whole window is 1
    return ndimage.minimum_filter(m.astype(np.uint8), size=window, mode="constant", cval=0).astype(bool)


def gradient_energy_map(grey: np.ndarray) -> np.ndarray:
    """(H, W) float64 |grad I|^2 in (grey levels per pixel)^2: Sobel derivatives divided by 8 (a
    central difference of the image smoothed by [1, 2, 1] / 4 across), so a ramp of slope g gives
    g^2 exactly. Border pixels are meaningless (callers exclude them)."""
    g = np.asarray(grey, np.float64)
    gx = ndimage.sobel(g, axis=1, mode="nearest") / 8.0
    gy = ndimage.sobel(g, axis=0, mode="nearest") / 8.0
    return gx * gx + gy * gy


def normalised_std_map(grey: np.ndarray, window: int) -> np.ndarray:
    """(H, W) float64 local std / mean of the grey image over `window` x `window` boxes (the
    population std; the mean floored at MEAN_FLOOR). Border pixels are meaningless."""
    g = np.asarray(grey, np.float64)
    mean = ndimage.uniform_filter(g, size=window, mode="nearest")
    mean_sq = ndimage.uniform_filter(g * g, size=window, mode="nearest")
    std = np.sqrt(np.clip(mean_sq - mean * mean, 0.0, None))  # clip: rounding can go a hair below 0
    # E[x^2] - E[x]^2 of the running box sums leaves rounding noise (~1e-8) on a flat window: set
    # it to exactly 0 (STD_FLOOR is far below one 8-bit step, 0.004)
    std[std < STD_FLOOR] = 0.0
    return std / np.maximum(mean, MEAN_FLOOR)


def texture_samples(grey: np.ndarray, mask: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The per-pixel values `texture_statistics` summarises, at the measured pixels (row-major):
    {"gradient_energy", "contrast_7", "contrast_15"}: (N,) float64 each. Samples of several
    images pooled (concatenated) and passed to `summarise` give the statistics of their union.

    grey: (H, W) float in [0, 1]; mask: (H, W) bool or None (the whole image).
    """
    g = np.asarray(grey, np.float64)
    if g.ndim != 2:
        raise ValueError(f"texture statistics: expected a (H, W) grey image, got shape {g.shape}")
    sel = measured_pixels(mask, g.shape)
    return {"gradient_energy": gradient_energy_map(g)[sel],
            "contrast_7": normalised_std_map(g, SMALL_WINDOW)[sel],
            "contrast_15": normalised_std_map(g, LARGE_WINDOW)[sel]}


def summarise(samples: dict[str, np.ndarray] | None, *, window_threshold: float = MATCHABLE_THRESHOLD) -> dict:
    """`texture_statistics`' dict from `texture_samples`' arrays (None or empty: NaN, 0 pixels)."""
    n = 0 if samples is None else len(samples["contrast_7"])
    if n == 0:
        nan = float("nan")
        return {"gradient_energy": nan, "contrast_7": nan, "contrast_15": nan, "matchable": nan, "pixels": 0}
    return {
        "gradient_energy": float(samples["gradient_energy"].mean()),
        "contrast_7": float(np.median(samples["contrast_7"])),
        "contrast_15": float(np.median(samples["contrast_15"])),
        "matchable": float((samples["contrast_7"] > window_threshold).mean()),
        "pixels": n,
    }


def texture_statistics(grey: np.ndarray, mask: np.ndarray | None = None, *,
                       window_threshold: float = MATCHABLE_THRESHOLD) -> dict:
    """How matchable the texture of `grey` is, over `mask`.

    grey: (H, W) float in [0, 1] at the common scale (`to_common_scale`, `to_grey`).
    mask: (H, W) bool or None (the whole image). Measured pixels: `measured_pixels(mask)` (their
    15 x 15 window inside the image and the mask).
    window_threshold: the 7 x 7 normalised std above which a pixel counts as matchable
    (default MATCHABLE_THRESHOLD = 0.05, derived there from the camera noise).

    Returns {"gradient_energy": mean |grad I|^2 ((grey levels / pixel)^2), "contrast_7",
    "contrast_15": median normalised std (dimensionless), "matchable": share in [0, 1],
    "pixels": int}; the statistics are NaN where no pixel is measured.
    """
    return summarise(texture_samples(grey, mask), window_threshold=window_threshold)


def class_statistics(grey: np.ndarray, classes: dict[str, np.ndarray], *,
                     window_threshold: float = MATCHABLE_THRESHOLD) -> dict[str, dict]:
    """`texture_statistics` per named (H, W) bool mask of `classes`, plus "all" (the whole image
    unless `classes` names its own "all", e.g. everything but the sky)."""
    out = {name: texture_statistics(grey, m, window_threshold=window_threshold) for name, m in classes.items()}
    if "all" not in out:
        out["all"] = texture_statistics(grey, None, window_threshold=window_threshold)
    return out
