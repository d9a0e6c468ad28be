"""Independent reference answers for the tracer tests (no code shared with scube_sim.raytrace).

Rotations come from Rodrigues' formula, ellipsoid hits from the textbook quadratic in extended
precision (np.longdouble), soft compositing from sampling the response along the ray.
"""

from __future__ import annotations

import numpy as np


def rodrigues(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3,) axis, radians -> (3, 3) rotation matrix."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def quat_from_axis_angle(axis, angle) -> np.ndarray:
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    return np.r_[np.cos(angle / 2), np.sin(angle / 2) * a]


def ellipsoid_quadratic(o, d, mu, rot, scales, k):
    """Solve (x - mu)^T Sigma^-1 (x - mu) = k^2 on x = o + t d for each ray, in long double.

    o, d: (N, 3); rot (3, 3); scales (3,). Returns (disc, t_near, t_far, t_peak) as float64, where
    disc = b^2 - a c of the quadratic a t^2 + 2 b t + c (disc < 0: miss) and t_peak = -b / a."""
    ld = np.longdouble
    o, d, mu, rot, s = (np.asarray(x, ld) for x in (o, d, mu, rot, scales))
    sinv = rot @ np.diag(1 / s**2) @ rot.T  # Sigma^-1 = R S^-2 R^T
    w = o - mu
    a = np.einsum("ni,ij,nj->n", d, sinv, d)
    b = np.einsum("ni,ij,nj->n", d, sinv, w)
    c = np.einsum("ni,ij,nj->n", w, sinv, w) - ld(k) ** 2
    disc = b * b - a * c
    root = np.sqrt(np.maximum(disc, 0))
    t_near = (-b - root) / a
    t_far = (-b + root) / a
    return (disc / a).astype(np.float64), t_near.astype(np.float64), t_far.astype(np.float64), (-b / a).astype(np.float64)


def brute_force_hard(o, d, means, rots, scales, k, mode):
    """Nearest hard hit of every ray against every Gaussian (no acceleration). Returns t (N,)."""
    best = np.full(o.shape[0], np.inf)
    for mu, r, s in zip(means, rots, scales):
        disc, tn, tf, tp = ellipsoid_quadratic(o, d, mu, r, s, k)
        hit = disc >= 0
        t = np.where(tn >= 0, tn, np.where(tf >= 0, 0.0, np.inf)) if mode == "entry" else np.where(tp >= 0, tp, np.inf)
        best = np.minimum(best, np.where(hit, t, np.inf))
    return best


def sampled_soft_composite(o, d, means, rots, scales, opacities, k, t_max, samples=200_001,
                           min_transmittance=1e-3, alpha_min=1 / 255):
    """Soft depth along each ray by brute-force sampling: every Gaussian's response is evaluated
    on a dense t grid; its peak (found numerically) gives its alpha = opacity * peak and its
    depth = arg-peak; particles are composited front to back in order of depth.

    Returns (depth (N,), accumulated alpha (N,))."""
    t = np.linspace(0.0, t_max, samples)
    depth = np.full(o.shape[0], np.inf)
    acc = np.zeros(o.shape[0])
    for i in range(o.shape[0]):
        x = o[i] + t[:, None] * d[i]
        parts = []
        for mu, r, s, op in zip(means, rots, scales, opacities):
            u = (x - mu) @ r / s  # coordinates in the Gaussian's principal frame, in sigmas
            m2 = np.einsum("ij,ij->i", u, u)
            j = int(np.argmin(m2))
            if m2[j] <= k * k:
                a = op * np.exp(-0.5 * m2[j])
                if a >= alpha_min:
                    parts.append((t[j], min(a, 0.999)))
        parts.sort()
        tr, wsum, wt = 1.0, 0.0, 0.0
        for tj, a in parts:
            if tr < min_transmittance:
                break
            wsum += tr * a
            wt += tr * a * tj
            tr *= 1 - a
        if wsum > 0:
            depth[i] = wt / wsum
            acc[i] = wsum
    return depth, acc
