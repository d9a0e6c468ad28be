"""The ground plane of surface points: RANSAC over the lower half of the points by height, the
plane tilted at most `max_tilt_deg` from `up`, then a least-squares refit of its inliers (kept
only if it does not tilt beyond the limit: a wall among the inliers). Deterministic for a seed.
Real sweeps are split into ground and above-ground returns by it (`eval depth`, `fidelity
--regions`); the converter's ground height field is fitted over it (`model.geometry.ground`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["GroundPlane", "RANSAC_INLIER_M", "fit_ground_plane"]

RANSAC_ITERATIONS = 200
RANSAC_INLIER_M = 0.15


@dataclass(frozen=True)
class GroundPlane:
    """A plane through `origin` + `centre` ((3,) each: the points' mean and the plane's centre
    relative to it, so that distances keep their precision far from the frame's origin) with unit
    `normal` (3,) pointing along `up`."""

    origin: np.ndarray
    centre: np.ndarray
    normal: np.ndarray

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) -> (N,) signed distance along the normal, metres."""
        return ((np.asarray(points, np.float64) - self.origin) - self.centre) @ self.normal

    def z_at(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) -> (N,) the plane's z over each point (frame z up)."""
        n, c = self.normal, self.origin + self.centre
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        return c[2] - ((xy[:, 0] - c[0]) * n[0] + (xy[:, 1] - c[1]) * n[1]) / n[2]


def fit_ground_plane(points: np.ndarray, up=(0.0, 0.0, 1.0), *, seed: int = 0, max_tilt_deg: float = 15.0,
                     inlier_m: float = RANSAC_INLIER_M) -> GroundPlane | None:
    """The ground plane of (N, 3) points (module docstring); None when fewer than 3 points or no
    plane within the tilt."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    if len(p) < 3:
        return None
    origin = p.mean(0)
    q = p - origin  # local coordinates: world frames may sit 10^6 m from their origin
    height = q @ up
    cand = q[height <= np.median(height)]
    if len(cand) < 3:
        return None
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(cand), size=(RANSAC_ITERATIONS, 3))
    a, b, c = cand[picks[:, 0]], cand[picks[:, 1]], cand[picks[:, 2]]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    n[ok] /= norm[ok, None]
    n *= np.where(n @ up < 0, -1.0, 1.0)[:, None]
    cos_tilt = math.cos(math.radians(max_tilt_deg))
    ok &= n @ up >= cos_tilt
    if not ok.any():
        return None
    n, a = n[ok], a[ok]
    counts = [(np.abs((cand - a0) @ n0) < inlier_m).sum() for n0, a0 in zip(n, a)]
    k = int(np.argmax(counts))
    inl = cand[np.abs((cand - a[k]) @ n[k]) < inlier_m]
    centre = inl.mean(0)
    normal = np.linalg.svd(inl - centre, full_matrices=False)[2][-1]  # least squares: smallest singular vector
    normal *= 1.0 if normal @ up >= 0 else -1.0
    if normal @ up < cos_tilt:
        normal, centre = n[k], a[k]  # the refit tilted too far (a wall among the inliers): keep the RANSAC plane
    return GroundPlane(origin, centre, normal)
