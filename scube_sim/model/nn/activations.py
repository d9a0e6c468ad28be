"""The paper's VoxSplat activations in torch, for training: the twins of `scube_sim.splat_params`.

Same layout (OFFSET, OPACITY, SCALE, QUAT, RGB slices into NUM_RAW = 14 raw values), same bounds,
same numbers (a parity test holds them together). Every function is finite, with finite
gradients, for any finite raw value: clamps stand where exp() could overflow, and a zero-norm
quaternion becomes the identity with a zero gradient.
"""

from __future__ import annotations

import torch

from ...splat_params import LOG_SCALE_MAX, LOG_SCALE_MIN, NUM_RAW, OFFSET, OPACITY, QUAT, RGB, SCALE, SH_C0

__all__ = [
    "NUM_RAW",
    "OFFSET",
    "OPACITY",
    "QUAT",
    "RGB",
    "SCALE",
    "SH_C0",
    "activate",
    "colors",
    "offsets",
    "opacities",
    "quats",
    "rotations",
    "scales",
]

_QUAT_EPS = 1e-12


def offsets(raw: torch.Tensor, r: float) -> torch.Tensor:
    """(..., 3) raw offsets -> (..., 3) metres from the voxel centre, in (-r, r)."""
    return r * torch.tanh(raw)


def opacities(raw: torch.Tensor) -> torch.Tensor:
    """(...) raw logits -> (...) alpha in [0, 1]. torch's sigmoid is stable at any magnitude."""
    return torch.sigmoid(raw)


def scales(raw: torch.Tensor) -> torch.Tensor:
    """(..., 3) raw log-scales -> (..., 3) metres in [1e-9, 1e4]."""
    return torch.exp(raw.clamp(LOG_SCALE_MIN, LOG_SCALE_MAX))


def quats(raw: torch.Tensor) -> torch.Tensor:
    """(..., 4) raw wxyz -> (..., 4) unit wxyz; a quaternion of norm below 1e-12 becomes
    (1, 0, 0, 0), as `transforms.normalize_quat` does."""
    # Divide by the largest component first (a constant for autograd: q / |q| does not depend
    # on it), so that |q|^2 of components near 1e20 does not overflow float32.
    m = raw.detach().abs().amax(dim=-1, keepdim=True).clamp_min(1e-30)
    q = raw / m
    n = torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    zero = (m * n) < _QUAT_EPS
    identity = torch.zeros_like(raw)
    identity[..., 0] = 1.0
    # clamp_min: the branch torch.where drops still gets a (zeroed) gradient, which must be finite
    return torch.where(zero, identity, q / n.clamp_min(_QUAT_EPS))


def colors(raw: torch.Tensor) -> torch.Tensor:
    """(..., 3) SH degree-0 coefficients -> (..., 3) RGB in [0, 1]."""
    return (0.5 + SH_C0 * raw).clamp(0.0, 1.0)


def rotations(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) unit wxyz -> (..., 3, 3) rotation matrices (columns: the Gaussian's axes)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(q.shape[:-1] + (3, 3))


def activate(params: torch.Tensor, centers: torch.Tensor, voxel_size: float,
             offset_range: float = 3.0) -> dict[str, torch.Tensor]:
    """(V, M, 14) raw values of V voxels with M Gaussians, (V, 3) voxel centres (metres, the
    VoxSplat's local frame) -> means (V, M, 3), opacities (V, M), scales (V, M, 3), quats
    (V, M, 4), colors (V, M, 3)."""
    if params.shape[-1] != NUM_RAW:
        raise ValueError(f"params: expected a last dimension of {NUM_RAW}, got shape {tuple(params.shape)}")
    r = offset_range * voxel_size
    return {
        "means": offsets(params[..., OFFSET], r) + centers[:, None, :],
        "opacities": opacities(params[..., OPACITY][..., 0]),
        "scales": scales(params[..., SCALE]),
        "quats": quats(params[..., QUAT]),
        "colors": colors(params[..., RGB]),
    }
