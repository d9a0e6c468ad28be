"""The raw layout of a VoxSplat Gaussian and the paper's activations, in numpy (the container).

Each Gaussian has NUM_RAW = 14 raw values, in this order:
offset(3), opacity(1), scale(3), quaternion wxyz(4), RGB as the SH degree-0 coefficient(3).

Activations (SCube, NeurIPS 2024):
    mu     = r * tanh(offset) + voxel_centre      r = offset_range * voxel_size (paper: 3 voxels)
    alpha  = sigmoid(opacity)
    s      = exp(scale)                           metres, clamped to [1 nm, 10 km]
    R      = quat2rot(normalize(q))               zero-norm q -> identity
    colour = clip(0.5 + C0 * rgb, 0, 1)           C0 = SH_C0

The torch twins the networks train with are `scube_sim.model.activations`; a parity test holds
the two to the same numbers. Bounds: every function here is finite for any finite raw value.
"""

from __future__ import annotations

import numpy as np

SH_C0 = 0.28209479177387814
NUM_RAW = 14
# Slices into the 14 raw values.
OFFSET, OPACITY, SCALE, QUAT, RGB = slice(0, 3), slice(3, 4), slice(4, 7), slice(7, 11), slice(11, 14)

# exp() of float32 overflows above ~88; a Gaussian larger than 10 km or smaller than 1 nm is
# not a scene element, so the scale activation is clamped to keep the numerics finite.
LOG_SCALE_MIN, LOG_SCALE_MAX = float(np.log(1e-9)), float(np.log(1e4))
# Past +-60 the logistic is 0 or 1 to float64 precision; the clip keeps exp() finite.
OPACITY_LOGIT_MAX = 60.0
# A VoxSplat Gaussian belongs to its voxel (its mean lies within offset_range voxels of the
# centre): one wider than this many voxels is a fitting or training failure, not a scene element.
# Such Gaussians turn a sweep into a crawl at hard opacity, so `VoxSplat.load` clamps them.
MAX_SCALE_VOXELS = 100.0
# Raw values of an empty slot: transparent, identity rotation.
EMPTY_OPACITY_RAW = -30.0


def offsets(raw: np.ndarray, r: float) -> np.ndarray:
    """(..., 3) raw offsets -> (..., 3) float64 metres from the voxel centre, in (-r, r)."""
    return r * np.tanh(np.asarray(raw).astype(np.float64))


def opacities(raw: np.ndarray) -> np.ndarray:
    """(...) raw opacity logits -> (...) float64 alpha in [0, 1]."""
    x = np.clip(np.asarray(raw).astype(np.float64), -OPACITY_LOGIT_MAX, OPACITY_LOGIT_MAX)
    return 1.0 / (1.0 + np.exp(-x))


def scales(raw: np.ndarray) -> np.ndarray:
    """(..., 3) raw log-scales -> (..., 3) float64 metres in [1e-9, 1e4]."""
    return np.exp(np.clip(np.asarray(raw).astype(np.float64), LOG_SCALE_MIN, LOG_SCALE_MAX))


def colors(raw: np.ndarray) -> np.ndarray:
    """(..., 3) SH degree-0 coefficients -> (..., 3) float32 RGB in [0, 1]."""
    return np.clip(0.5 + SH_C0 * raw, 0.0, 1.0).astype(np.float32)


# --- inverses: activated values -> raw (for building a VoxSplat from fitted Gaussians) ----------

def offsets_to_raw(off: np.ndarray, r: float) -> np.ndarray:
    """(..., 3) metres from the voxel centre -> raw offsets; |off| >= r saturates just inside."""
    return np.arctanh(np.clip(np.asarray(off, np.float64) / r, -1 + 1e-7, 1 - 1e-7))


def opacities_to_raw(alpha: np.ndarray) -> np.ndarray:
    """(...) alpha in [0, 1] -> raw logits (alpha clipped to [1e-12, 1 - 1e-7])."""
    op = np.clip(np.asarray(alpha, np.float64), 1e-12, 1 - 1e-7)
    return np.log(op) - np.log1p(-op)


def scales_to_raw(s: np.ndarray) -> np.ndarray:
    """(..., 3) metres -> raw log-scales (s clipped below at 1e-9)."""
    return np.log(np.clip(np.asarray(s, np.float64), 1e-9, None))
