"""Fit a VoxSplat to points on surfaces: mesh surface samples or accumulated LiDAR returns.

Per voxel the points are split into M clusters by recursive bisection along the principal axis
(so a planar patch splits 2 x 2 for M = 4), and each cluster becomes one Gaussian with the
cluster's mean, principal axes and standard deviations. The standard deviation along the axis of
least spread (the surface normal) is kept between `min_scale` and `max_normal_scale`: Gaussians
lie flat on the surface, but never degenerate. At k = 3 a cluster's ellipse covers its patch
(a uniform w x w patch has sigma = w / sqrt(12), and 3 sigma = 0.87 w > its half-diagonal).
Deterministic: no random initialisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .splat_params import EMPTY_OPACITY_RAW, NUM_RAW, OFFSET, QUAT, RGB, SCALE, SH_C0
from .transforms import rotmat_to_quat
from .voxsplat import VoxSplat, unique_voxels

_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _group_moments(key: np.ndarray, p: np.ndarray, nkeys: int, w: np.ndarray, extra=None):
    """Weight, weighted mean (K, 3) and covariance (K, 3, 3) of points grouped by integer key.

    extra: optional (cov6 (F, 6), index (N,)): each point stands for a small patch whose own
    covariance (xx, xy, xz, yy, yz, zz) is cov6[index], added to the spread of the points."""
    cnt = np.bincount(key, weights=w, minlength=nkeys)
    safe = np.where(cnt > 0, cnt, 1.0)
    mean = np.stack([np.bincount(key, weights=w * p[:, i], minlength=nkeys) for i in range(3)], 1) / safe[:, None]
    q = p - mean[key]  # centred first: the second moments stay accurate far from the origin
    cov = np.empty((nkeys, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(key, weights=w * q[:, i] * q[:, j], minlength=nkeys) / safe
    if extra is not None:
        cov6, index = extra
        for c, (i, j) in enumerate(_PAIRS):
            add = np.bincount(key, weights=w * cov6[index, c], minlength=nkeys) / safe
            cov[:, i, j] += add
            if i != j:
                cov[:, j, i] += add
    return cnt, mean, cov


@dataclass(frozen=True)
class FitOptions:
    """How `fit_voxsplat` fits. gaussians_per_voxel: M, a power of two. min_scale: floor on every
    standard deviation (metres; default 1 % of the voxel); max_normal_scale: optional cap on the
    smallest one (metres; flattens noisy LiDAR surfaces). opacity: every fitted Gaussian's, in
    (0, 1). Voxels with fewer than `min_points` points are dropped."""

    gaussians_per_voxel: int = 4
    min_scale: float | None = None
    max_normal_scale: float | None = None
    opacity: float = 0.99
    min_points: int = 1

    def __post_init__(self):
        m = int(self.gaussians_per_voxel)
        if m < 1 or m & (m - 1):
            raise InputError(f"gaussians_per_voxel: expected a power of two (1, 2, 4, 8, ...), got {m}")


def fit_voxsplat(
    points: np.ndarray,
    voxel_size: float,
    *,
    colors: np.ndarray | None = None,
    labels: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    patch_cov: tuple[np.ndarray, np.ndarray] | None = None,
    values: dict[str, np.ndarray] | None = None,
    origin: np.ndarray | None = None,
    fit: FitOptions = FitOptions(),
) -> VoxSplat:
    """Fit Gaussians to surface points.

    points (N, 3) float64 metres in the frame of `origin` (world = points + origin; default
    origin zero); what each point carries: colors (N, 3) in [0, 1]; labels (N,) label ids (voxel
    label = majority); weights (N,) (the surface each stands for; default 1); patch_cov: (cov6
    (F, 6), index (N,)), the covariance (xx, xy, xz, yy, yz, zz) of the patch each point stands
    for, added to the points' spread; values: per-point scalars (N,) by channel name (e.g.
    'reflectance'), averaged per Gaussian with the points' weights, NaN values left out, and
    stored as per-Gaussian channels (NaN where a Gaussian has none). fit: M, the scale limits,
    opacity and the voxels' minimum point count (`FitOptions`). Clusters left empty become invalid
    slots. Returns a VoxSplat whose local frame is that of `points`.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    m = int(fit.gaussians_per_voxel)
    if not voxel_size > 0:
        raise InputError(f"voxel_size: expected > 0 metres, got {voxel_size}")
    if not np.all(np.isfinite(p)):
        raise InputError("fit_voxsplat: points contain NaN or Inf")
    vs = float(voxel_size)
    min_scale = 0.01 * vs if fit.min_scale is None else float(fit.min_scale)
    origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64)

    w = np.ones(p.shape[0]) if weights is None else np.asarray(weights, np.float64).reshape(-1)
    uniq, inv, counts = unique_voxels(np.floor(p / vs))
    if fit.min_points > 1:
        keep_v = counts >= fit.min_points
        keep_p = keep_v[inv]
        p, w, inv = p[keep_p], w[keep_p], np.cumsum(keep_v)[inv[keep_p]] - 1
        if patch_cov is not None:
            patch_cov = (patch_cov[0], patch_cov[1][keep_p])
        colors = None if colors is None else np.asarray(colors)[keep_p]
        labels = None if labels is None else np.asarray(labels)[keep_p]
        values = None if values is None else {k: np.asarray(v)[keep_p] for k, v in values.items()}
        uniq = uniq[keep_v]
    nv = uniq.shape[0]

    # Recursive bisection: at each level split every cluster at its mean along its main axis.
    cluster = np.zeros(p.shape[0], np.int64)
    levels = m.bit_length() - 1
    for level in range(levels):
        nk = nv << level
        key = (inv << level) + cluster
        _, mean, cov = _group_moments(key, p, nk, w, patch_cov)
        _, vec = np.linalg.eigh(cov)
        axis = vec[:, :, 2]  # eigenvector of the largest eigenvalue
        side = np.einsum("ij,ij->i", p - mean[key], axis[key]) > 0
        cluster = cluster * 2 + side

    key = inv * m + cluster
    cnt, mean, cov = _group_moments(key, p, nv * m, w, patch_cov)
    evals, evecs = np.linalg.eigh(cov)  # ascending: column 0 is the surface normal
    sig = np.sqrt(np.maximum(evals, 0.0))
    if fit.max_normal_scale is not None:
        sig[:, 0] = np.minimum(sig[:, 0], fit.max_normal_scale)
    sig = np.maximum(sig, min_scale)
    evecs[np.linalg.det(evecs) < 0, :, 0] *= -1.0  # proper rotations only
    quats = rotmat_to_quat(evecs)

    params = np.zeros((nv * m, NUM_RAW), np.float32)
    centers = (uniq.astype(np.float64) + 0.5) * vs
    r = 3.0 * vs
    off = (mean - np.repeat(centers, m, axis=0)) / r
    params[:, OFFSET] = np.arctanh(np.clip(off, -1 + 1e-6, 1 - 1e-6))
    params[:, 3] = np.log(fit.opacity) - np.log1p(-fit.opacity)
    params[:, SCALE] = np.log(sig)
    params[:, QUAT] = quats
    if colors is not None:
        c = np.asarray(colors, np.float64)
        safe = np.where(cnt > 0, cnt, 1.0)
        cm = np.stack([np.bincount(key, weights=w * c[:, i], minlength=nv * m) for i in range(3)], 1) / safe[:, None]
        params[:, RGB] = (cm - 0.5) / SH_C0
    valid = (cnt > 0).reshape(nv, m)
    params = params.reshape(nv, m, NUM_RAW)
    params[~valid, 3] = EMPTY_OPACITY_RAW
    params[~valid, 7:11] = [1, 0, 0, 0]

    vox_labels = None
    if labels is not None:
        lab = np.asarray(labels, np.int64)
        pair = inv * 1024 + lab
        up, upi = np.unique(pair, return_inverse=True)
        pc = np.bincount(upi.reshape(-1), weights=w)  # label weight (area) per voxel
        pv, pl = up // 1024, up % 1024
        best = np.lexsort((pl, -pc, pv))  # most frequent, ties to the smaller id
        first = np.r_[True, pv[best][1:] != pv[best][:-1]]
        vox_labels = np.zeros(nv, np.int16)
        vox_labels[pv[best][first]] = pl[best][first]
    out = VoxSplat(uniq.astype(np.int32), params, vs, origin, valid, vox_labels)
    for name, val in (values or {}).items():
        v = np.asarray(val, np.float64).reshape(-1)
        if v.shape[0] != p.shape[0]:
            raise InputError(f"values[{name!r}]: expected ({p.shape[0]},) per-point values, got {v.shape}")
        known = np.isfinite(v)
        wk = np.where(known, w, 0.0)
        num = np.bincount(key, weights=wk * np.where(known, v, 0.0), minlength=nv * m)
        den = np.bincount(key, weights=wk, minlength=nv * m)
        mean = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
        out.set_channel(name, mean.reshape(nv, m).astype(np.float32), per="gaussian")
    return out
