"""The fixed semantic label table (Waymo-like), shared by worlds, VoxSplats, LiDAR and datasets.

Ids 0..22 follow the Waymo Open Dataset 3D semantic segmentation classes; 23..25 add the classes
the procedural worlds need (fence, terrain, sky). Frozen at LABEL_TABLE_VERSION: a model trained
on one version reads labels by these ids, so change it only by appending and bumping the version.

`reflectivity` is a diffuse near-infrared (~905 nm) reflectance used by the LiDAR intensity model:
rough figures for asphalt, paint, concrete, foliage and retroreflective sheeting, not measurements.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import NotFoundError

LABEL_TABLE_VERSION = 1


@dataclass(frozen=True)
class Label:
    id: int
    name: str
    color: tuple[int, int, int]  # sRGB 0..255 for previews
    reflectivity: float  # 0..1, near-infrared diffuse reflectance


LABELS: tuple[Label, ...] = (
    Label(0, "undefined", (0, 0, 0), 0.20),
    Label(1, "car", (0, 0, 142), 0.30),
    Label(2, "truck", (0, 0, 70), 0.30),
    Label(3, "bus", (0, 60, 100), 0.30),
    Label(4, "other_vehicle", (0, 0, 90), 0.30),
    Label(5, "motorcyclist", (0, 0, 230), 0.35),
    Label(6, "bicyclist", (119, 11, 32), 0.35),
    Label(7, "pedestrian", (220, 20, 60), 0.35),
    Label(8, "sign", (220, 220, 0), 0.90),
    Label(9, "traffic_light", (250, 170, 30), 0.50),
    Label(10, "pole", (153, 153, 153), 0.40),
    Label(11, "construction_cone", (255, 120, 0), 0.80),
    Label(12, "bicycle", (119, 11, 60), 0.30),
    Label(13, "motorcycle", (0, 0, 200), 0.30),
    Label(14, "building", (70, 70, 70), 0.35),
    Label(15, "vegetation", (107, 142, 35), 0.50),
    Label(16, "tree_trunk", (120, 80, 40), 0.30),
    Label(17, "curb", (196, 196, 196), 0.30),
    Label(18, "road", (128, 64, 128), 0.12),
    Label(19, "lane_marker", (255, 255, 255), 0.60),
    Label(20, "other_ground", (152, 121, 90), 0.20),
    Label(21, "walkable", (160, 140, 200), 0.25),
    Label(22, "sidewalk", (244, 35, 232), 0.28),
    Label(23, "fence", (190, 153, 153), 0.30),
    Label(24, "terrain", (152, 251, 152), 0.25),
    Label(25, "sky", (70, 130, 180), 0.00),
)

NUM_LABELS = len(LABELS)
LABEL_NAMES: tuple[str, ...] = tuple(lab.name for lab in LABELS)
LABEL_IDS: dict[str, int] = {lab.name: lab.id for lab in LABELS}
LABEL_COLORS = np.array([lab.color for lab in LABELS], dtype=np.uint8)  # (NUM_LABELS, 3)
LABEL_REFLECTIVITY = np.array([lab.reflectivity for lab in LABELS], dtype=np.float32)

assert all(lab.id == i for i, lab in enumerate(LABELS))


def label_id(name: str) -> int:
    """Label id for a class name; NotFoundError (a KeyError) lists the known names."""
    try:
        return LABEL_IDS[name]
    except KeyError:
        raise NotFoundError(f"unknown label {name!r}; known: {', '.join(LABEL_NAMES)}") from None
