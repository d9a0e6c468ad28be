"""Road layouts: centreline polylines in the ground plane and a classifier of ground points.

World frame: z up, the ego starts near x = 0 heading +x (as the paper crops its chunks: the ego
near one edge, facing inward); right-hand traffic, so the ego's lane is at negative lateral offset.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InputError


@dataclass
class Road:
    """A road: centreline (K, 2) metres, lanes per direction, lane width, sidewalk width, an
    optional median (boulevards) and a parking lane along each curb. Half of the carriageway =
    median / 2 + lanes * lane_width + parking."""

    centerline: np.ndarray
    lanes: int = 1
    lane_width: float = 3.5
    sidewalk: float = 3.0
    median: float = 0.0
    parking: float = 0.0

    @property
    def half_width(self) -> float:
        return self.lanes * self.lane_width + self.median / 2 + self.parking

    def lengths(self) -> np.ndarray:
        seg = np.diff(self.centerline, axis=0)
        return np.r_[0.0, np.cumsum(np.linalg.norm(seg, axis=1))]

    @property
    def length(self) -> float:
        return float(self.lengths()[-1])

    def at(self, s: np.ndarray, lateral: np.ndarray | float = 0.0):
        """Points (N, 2) and unit tangents (N, 2) at arc lengths s, shifted `lateral` metres to the
        left of the centreline."""
        s = np.atleast_1d(np.asarray(s, np.float64))
        cum = self.lengths()
        i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(cum) - 2)
        seg = self.centerline[i + 1] - self.centerline[i]
        seg_len = np.maximum(cum[i + 1] - cum[i], 1e-12)
        tangent = seg / seg_len[:, None]
        p = self.centerline[i] + tangent * (s - cum[i])[:, None]
        left = np.stack([-tangent[:, 1], tangent[:, 0]], 1)
        return p + left * np.reshape(lateral, (-1, 1)), tangent


def polyline_distance(points: np.ndarray, line: np.ndarray):
    """Distance (N,) from 2D points to a polyline, and the signed side (+ left of travel).

    The nearest vertex (k-d tree) picks the two segments beside it, which hold the nearest point
    when segments are short against the polyline's curvature (ours are 2 m or less)."""
    k = cKDTree(line).query(points)[1]
    best_d = np.full(len(points), np.inf)
    best_side = np.zeros(len(points))
    for j in (k - 1, k):
        j = np.clip(j, 0, len(line) - 2)
        a, b = line[j], line[j + 1]
        ab = b - a
        ap = points - a
        t = np.clip(np.einsum("ij,ij->i", ap, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0.0, 1.0)
        d = np.linalg.norm(ap - t[:, None] * ab, axis=1)
        side = np.sign(ab[:, 0] * ap[:, 1] - ab[:, 1] * ap[:, 0])
        better = d < best_d
        best_d = np.where(better, d, best_d)
        best_side = np.where(better, side, best_side)
    return best_d, best_side


@dataclass
class Layout:
    """The road network of a world; `main` is the road the ego drives on."""

    roads: list[Road]
    kind: str
    junction: np.ndarray | None = None  # (2,) centre of the junction, if any
    extras: dict = field(default_factory=dict)

    @property
    def main(self) -> Road:
        return self.roads[0]

    def classify(self, xy: np.ndarray, chunk: int = 1_000_000):
        """Ground class per 2D point: 0 terrain, 1 road, 2 sidewalk, 3 median; and the distance to
        the nearest road edge (negative inside a carriageway)."""
        out = np.zeros(len(xy), np.int8)
        edge = np.full(len(xy), np.inf)
        for lo in range(0, len(xy), chunk):
            p = xy[lo:lo + chunk]
            cls = np.zeros(len(p), np.int8)
            best = np.full(len(p), np.inf)
            for road in self.roads:
                d, _ = polyline_distance(p, road.centerline)
                e = d - road.half_width
                side = (e > 0) & (e <= road.sidewalk) & (cls != 1)
                cls[side & (cls == 0)] = 2
                on = e <= 0
                cls[on] = 1
                if road.median > 0:
                    cls[on & (d < road.median / 2)] = 3
                best = np.minimum(best, e)
            out[lo:lo + chunk] = cls
            edge[lo:lo + chunk] = best
        return out, edge


def make_layout(kind: str, rng: np.random.Generator, *, length: float, lanes: int, lane_width: float,
                sidewalk: float, median: float, parking: float = 0.0) -> Layout:
    """Centrelines for 'straight', 'curved', 't_junction' and 'x_junction' layouts, starting
    20 m behind the ego's start (x = 0) and running `length` metres ahead."""
    main_kw = dict(lanes=lanes, lane_width=lane_width, sidewalk=sidewalk, median=median, parking=parking)
    x = np.linspace(-20.0, length + 20.0, int((length + 40.0) / 2.0) + 1)
    if kind == "straight":
        return Layout([Road(np.c_[x, np.zeros_like(x)], **main_kw)], kind)
    if kind == "curved":
        radius = rng.uniform(70.0, 180.0) * rng.choice([-1.0, 1.0])
        # A straight run-in, then an arc of the given radius (left if positive).
        s = x - x[0]
        run_in = 20.0 + rng.uniform(0.0, 20.0)
        theta = np.clip(s - run_in, 0.0, None) / radius
        xs = np.where(s < run_in, x, x[0] + run_in + radius * np.sin(theta))
        ys = np.where(s < run_in, 0.0, radius * (1.0 - np.cos(theta)))
        return Layout([Road(np.c_[xs, ys], **main_kw)], kind, extras={"radius": float(radius)})
    if kind in ("t_junction", "x_junction"):
        xj = rng.uniform(0.45, 0.65) * length
        cross_kw = dict(lanes=int(rng.integers(1, 3)), lane_width=lane_width, sidewalk=sidewalk, parking=parking)
        y = np.linspace(-length / 2 - 20.0, length / 2 + 20.0, int((length + 40.0) / 2.0) + 1)
        cross = Road(np.c_[np.full_like(y, xj), y], **cross_kw)
        if kind == "t_junction":
            xm = x[x <= xj]
            main = Road(np.c_[xm, np.zeros_like(xm)], **main_kw)
        else:
            main = Road(np.c_[x, np.zeros_like(x)], **main_kw)
        return Layout([main, cross], kind, junction=np.array([xj, 0.0]))
    raise InputError(f"layout: expected straight, curved, t_junction or x_junction, got {kind!r}")
