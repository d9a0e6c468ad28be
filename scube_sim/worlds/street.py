"""A small fixed street scene from primitives: road, sidewalks, buildings, cars, poles, trees.

A compact mesh scene with exact geometry and labels, used by tests and benchmarks that need a
realistic-looking surface layout without the full procedural generator.
"""

from __future__ import annotations

import numpy as np

from ..labels import label_id
from ..mesh import TriangleMesh
from . import primitives as pr


def car(center_xy, yaw, *, instance: int, color=(0.6, 0.1, 0.1), z0: float = 0.0) -> TriangleMesh:
    """A car of body, cabin and four wheels (about 4.5 x 1.8 x 1.5 m), wheels on z0."""
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s], [s, c]])
    lab = label_id("car")
    parts = [
        pr.box([0, 0, 0.65], [4.5, 1.8, 0.7], label=lab, color=color, instance=instance),
        pr.box([-0.3, 0, 1.25], [2.4, 1.6, 0.55], label=lab, color=(0.15, 0.2, 0.25), instance=instance),
    ]
    for x in (-1.45, 1.45):
        for y in (-0.8, 0.8):
            parts.append(pr.cylinder([x, y - 0.12, 0.35], 0.35, 0.24, segments=10, axis="y",
                                     label=lab, color=(0.05, 0.05, 0.05), instance=instance))
    m = TriangleMesh.concatenate(parts)
    m.vertices[:, :2] = m.vertices[:, :2] @ rot.T + np.asarray(center_xy, np.float64)
    m.vertices[:, 2] += z0
    return m


def tree(base_xy, *, height: float = 6.0, crown: float = 2.0, z0: float = 0.15) -> TriangleMesh:
    trunk = pr.cylinder([base_xy[0], base_xy[1], z0], 0.18, height - crown, segments=8,
                        label=label_id("tree_trunk"), color=(0.35, 0.25, 0.15))
    top = pr.icosphere([base_xy[0], base_xy[1], z0 + height - crown * 0.6], crown, subdivisions=1,
                       label=label_id("vegetation"), color=(0.2, 0.45, 0.15), squash=(1, 1, 0.8))
    return TriangleMesh.concatenate([trunk, top])


def street_scene(length: float = 80.0) -> TriangleMesh:
    """A straight street along x, centred on the origin: 10 m road, 3 m sidewalks (0.15 m curb),
    building rows at |y| > 9.5 m, parked cars, poles with signs and trees. Local frame, z up."""
    h = length / 2
    parts = [
        pr.ground_grid(-h, -5, h, 5, 0.0, 10.0, label=label_id("road"), color=(0.25, 0.25, 0.27)),
        pr.box([0, 6.5, 0.075], [length, 3.0, 0.15], label=label_id("sidewalk"), color=(0.6, 0.6, 0.58)),
        pr.box([0, -6.5, 0.075], [length, 3.0, 0.15], label=label_id("sidewalk"), color=(0.6, 0.6, 0.58)),
        pr.ground_grid(-h, -0.08, h, 0.08, 0.002, 10.0, label=label_id("lane_marker"), color=(0.95, 0.95, 0.9)),
    ]
    widths = [12.0, 9.0, 15.0, 10.0, 14.0, 11.0, 13.0]
    heights = [9.0, 14.0, 7.0, 18.0, 11.0, 8.0, 16.0]
    for side in (-1, 1):
        x = -h
        i = 0 if side > 0 else 3
        while x < h - 2:
            w = min(widths[i % 7], h - x)
            hh = heights[(i * 3) % 7]
            depth = 8.0
            setback = 0.5 * (i % 3)
            parts.append(pr.box([x + w / 2, side * (8.0 + setback + depth / 2), hh / 2], [w - 0.6, depth, hh],
                                label=label_id("building"), color=(0.55 + 0.05 * (i % 4), 0.45, 0.4)))
            x += w
            i += 1
    instance = 1
    for x, side, yaw in [(-22, 1, 0.0), (-8, 1, 0.05), (15, -1, np.pi), (27, -1, np.pi - 0.04)]:
        parts.append(car([x, side * 3.6], yaw, instance=instance, color=(0.2 + 0.2 * instance % 3, 0.15, 0.5)))
        instance += 1
    for x in np.arange(-h + 6, h, 16.0):
        for side in (-1, 1):
            parts.append(pr.cylinder([x, side * 5.4, 0.15], 0.08, 6.0, segments=8, label=label_id("pole"),
                                     color=(0.4, 0.4, 0.4)))
    for x in (-30.0, 2.0, 30.0):
        parts.append(pr.box([x, -5.4, 2.6], [0.05, 0.7, 0.7], label=label_id("sign"), color=(0.9, 0.9, 0.1)))
    for x in np.arange(-h + 14, h, 16.0):
        parts.append(tree([x, 7.2]))
    return TriangleMesh.concatenate(parts)
