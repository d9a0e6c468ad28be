"""What a trace returns: per-ray hits, and counters of the work done."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Hits:
    """Per-ray results, all (N, ...) arrays.

    hit bool; t float64 range along the ray (inf on a miss); points float64 local frame;
    normals float32 unit, facing the ray; gaussian int64, an index into the tracer's `gaussians`
    (those at or above its opacity floor; -1: none or a mesh); voxel int64 (-1: none); face
    int64 (mesh triangle, -1 otherwise); label int16; instance int32; color float32 (N, 3) in
    [0, 1]; alpha float32 accumulated opacity (1 for hard hits);
    reflectance float32 measured reflectance of the surface hit (the VoxSplat `reflectance`
    channel), NaN where the scene has none. observed uint8 and confidence float32: a converted
    VoxSplat's ``observed`` and ``confidence`` channels of the voxel hit (1 where an input camera
    saw it; the converter's confidence in it); 1 and 1.0 on every other surface (meshes,
    ground-truth or measured VoxSplats: nothing there was inferred) and on misses.
    """

    hit: np.ndarray
    t: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    gaussian: np.ndarray
    voxel: np.ndarray
    face: np.ndarray
    label: np.ndarray
    instance: np.ndarray
    color: np.ndarray
    alpha: np.ndarray
    reflectance: np.ndarray
    observed: np.ndarray
    confidence: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "Hits":
        return cls(
            hit=np.zeros(n, bool), t=np.full(n, np.inf), points=np.full((n, 3), np.nan),
            normals=np.zeros((n, 3), np.float32), gaussian=np.full(n, -1, np.int64),
            voxel=np.full(n, -1, np.int64), face=np.full(n, -1, np.int64),
            label=np.zeros(n, np.int16), instance=np.zeros(n, np.int32),
            color=np.zeros((n, 3), np.float32), alpha=np.zeros(n, np.float32),
            reflectance=np.full(n, np.nan, np.float32), observed=np.ones(n, np.uint8),
            confidence=np.ones(n, np.float32),
        )


@dataclass
class TraceStats:
    casts: int = 0  # Embree calls
    rays_cast: int = 0  # rays over all calls
    exact_tests: int = 0  # (ray, Gaussian) pairs tested
    unfinished: int = 0  # rays stopped by max_iterations (best hit so far kept)
