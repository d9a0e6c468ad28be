"""Does a sweep's geometry agree with its stated origin? The check that refuses merged clouds.

A log may store one cloud merged from several LiDARs (Argoverse 2 stores its two VLP-32C in one
table, in the ego frame at ground level). Traced or meshed from the stated origin, such a cloud
is wrong: the range-image mesh sees the ground edge-on from ground level and keeps a fifth of it,
and fidelity fires rays that pass through surfaces the other sensor saw. A sweep that says where
its points came from (`LidarSweep.origin_id` / `origins`, see `merge_sweeps`) is split by origin
instead; one that does not is checked here, on two figures read from the points alone:

- **seen through**: the share of returns that lie behind another return of the same cloud, as
  seen from the stated origin (the two directions within `SEEN_THROUGH_DEG`, the far one more than
  0.5 m + 5 % of the range further; where the sweep has ring ids, pairs on one ring are skipped:
  neighbours along a scan line across a depth edge, or one laser's two echoes). A single sensor
  sees nothing behind what it hit: the real single-sensor sweeps in ../shared/data stay under
  `MAX_SEEN_THROUGH` (without ring ids, depth edges count), Argoverse 2's two units merged in its
  ego frame do not (the figures per log: docs/lidar-intensity-and-drop.md).
- **origin height**: the stated origin's height above the ground under it (the median over
  2 m cells 3-40 m away of each cell's lowest return, along world z). A LiDAR's rays start above
  the road; a stated origin within `MIN_ORIGIN_HEIGHT_M` of it (or under it) is an ego frame at
  ground level, not a sensor (a roof sensor stands well above it; Argoverse 2's ego origin lies
  at the road).

Merged clouds whose sensors sit close together (Argoverse 2's two units, 12 cm apart, seen from
the upper one) pass: traced from either origin they differ by centimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .base import LidarSweep

SEEN_THROUGH_DEG = 0.2  # two returns this close in direction share a line of sight
MAX_SEEN_THROUGH = 0.10  # a share of returns behind others above this: not one origin
MIN_ORIGIN_HEIGHT_M = 0.3  # a stated origin lower than this above the ground is not a sensor
MIN_GROUND_SHARE = 0.03  # the height test needs this share of returns on the ground
MIN_RETURNS = 500  # fewer returns: no verdict


class MergedCloudError(InputError):
    """A sweep's geometry shows several origins, but the sweep does not say where its points came from."""


@dataclass
class OriginCheck:
    """The figures of `check_origin`. returns: returns used (>= min_range); seen_through: share of
    them behind another return from the origin; origin_height_m: the origin's height above the
    ground (NaN where no ground was found); ground_share: share of returns within 0.3 m of that
    ground; reasons: why the sweep looks merged ([] if it does not, or too few returns to tell)."""

    returns: int
    seen_through: float
    origin_height_m: float
    ground_share: float
    reasons: list[str]

    @property
    def single_origin(self) -> bool:
        return not self.reasons


def check_origin(sweep: LidarSweep, *, min_range: float = 1.0) -> OriginCheck:
    """The figures of the module docstring for `sweep` as stated (its points from its frame's
    origin; world z is up). A merged sweep is checked per origin (the worst part is returned)."""
    if sweep.merged:
        parts = [check_origin(p, min_range=min_range) for p in sweep.by_origin()]
        return max(parts, key=lambda c: (len(c.reasons), c.seen_through))
    from scipy.spatial import cKDTree

    p = sweep.compensated().points if not sweep.motion_compensated else sweep.points
    r = np.linalg.norm(p, axis=1)
    keep = np.isfinite(r) & (r >= min_range)
    p, r = p[keep], r[keep]
    ring = None if sweep.ring is None else np.asarray(sweep.ring)[keep]
    n = len(p)
    if n < MIN_RETURNS:
        return OriginCheck(n, float("nan"), float("nan"), float("nan"), [])
    d = p / r[:, None]
    pairs = cKDTree(d).query_pairs(2 * np.sin(np.deg2rad(SEEN_THROUGH_DEG) / 2), output_type="ndarray")
    behind = np.zeros(n, bool)
    if len(pairs):
        if ring is not None:  # neighbours on one scan line (and a laser's two echoes) are no conflict
            pairs = pairs[ring[pairs[:, 0]] != ring[pairs[:, 1]]]
        i, j = pairs[:, 0], pairs[:, 1]
        margin = 0.5 + 0.05 * np.minimum(r[i], r[j])
        behind[i[r[i] > r[j] + margin]] = True
        behind[j[r[j] > r[i] + margin]] = True
    seen = float(behind.mean())
    # Heights along world up, relative to the origin; the ground: median of 2 m cells' minima.
    up = sweep.sensor_to_world[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    h = p @ up
    flat = p - h[:, None] * up
    e1 = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    dist = np.linalg.norm(flat, axis=1)
    near = (dist > 3.0) & (dist < 40.0)
    height, ground = float("nan"), float("nan")
    if near.sum() >= MIN_RETURNS // 5:
        cell = np.floor(np.stack([flat[near] @ e1, flat[near] @ e2], 1) / 2.0).astype(np.int64)
        _, inv = np.unique(cell, axis=0, return_inverse=True)
        inv = inv.ravel()
        low = np.full(inv.max() + 1, np.inf)
        np.minimum.at(low, inv, h[near])
        g = float(np.median(low))
        height, ground = -g, float(np.mean(np.abs(h - g) < 0.3))
    reasons = []
    if seen > MAX_SEEN_THROUGH:
        reasons.append(f"{100 * seen:.1f} % of its {n} returns lie behind another return as seen from the stated "
                       f"origin (one sensor: under {100 * MAX_SEEN_THROUGH:.0f} %; 0-6.7 % on real single-sensor "
                       f"sweeps)")
    if np.isfinite(height) and height < MIN_ORIGIN_HEIGHT_M and ground >= MIN_GROUND_SHARE:
        reasons.append(f"the stated origin is {height:.2f} m above the ground under it ({100 * ground:.0f} % of "
                       f"the returns are ground): no LiDAR fires from there, it is a frame at ground level")
    return OriginCheck(n, seen, height, ground, reasons)


def require_single_origin(sweep: LidarSweep, where: str, *, min_range: float = 1.0,
                          allow_flag: str = "assume_single_origin=True") -> OriginCheck:
    """`check_origin`, raising MergedCloudError (naming `where`, the sweep and its file) when a
    sweep without per-point origins looks merged. Merged sweeps pass (their origins are known)."""
    if sweep.merged:
        return OriginCheck(len(sweep), float("nan"), float("nan"), float("nan"), [])
    c = check_origin(sweep, min_range=min_range)
    if c.reasons:
        src = f" ({sweep.source})" if sweep.source else ""
        raise MergedCloudError(
            f"{where}: sweep {sweep.sensor!r}{src} looks merged from several LiDARs, but says only one origin: "
            + "; ".join(c.reasons) + ". Meshing or tracing it from that origin would be wrong. Say where each "
            "point came from: in a scube-sim-folder, a 'sensor_id' point field and the sweep's 'origins' list "
            "in sample.yaml (docs/dataset-folder-format.md); in code, LidarSweep(origin_id=..., origins=...) or "
            f"merge_sweeps(). If the sweep really is one sensor's, pass {allow_flag}.")
    return c


__all__ = ["OriginCheck", "MergedCloudError", "check_origin", "require_single_origin", "MAX_SEEN_THROUGH",
           "MIN_ORIGIN_HEIGHT_M", "SEEN_THROUGH_DEG"]
