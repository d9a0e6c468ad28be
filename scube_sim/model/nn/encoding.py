"""Voxel encodings shared by the stages: sinusoidal positional encoding of coordinates and the
most frequent label among a voxel's members.
"""

from __future__ import annotations

import math

import torch

from ...labels import NUM_LABELS


def majority_labels(inverse: torch.Tensor, labels: torch.Tensor, n: int) -> torch.Tensor:
    """(n,) int64 the most frequent of the `labels` (M,) that `inverse` (M,) maps to each of n
    coarse voxels (ties to the lower id): a coarsened grid's labels."""
    counts = torch.zeros(n, NUM_LABELS, dtype=torch.int64).index_put_(
        (inverse, labels.to(torch.int64)), torch.ones_like(inverse), accumulate=True)
    return counts.argmax(1)


def positional_encoding(x: torch.Tensor, frequencies: int) -> torch.Tensor:
    """(V, 3) chunk-frame centres, metres -> (V, 6 F): sin and cos of pi 2^f x / 51.2 m."""
    if frequencies == 0:
        return x.new_zeros((x.shape[0], 0))
    u = (x / 51.2)[:, None, :] * (math.pi * 2.0 ** torch.arange(frequencies, dtype=x.dtype))[None, :, None]
    return torch.cat([torch.sin(u), torch.cos(u)], 1).reshape(x.shape[0], 6 * frequencies)


