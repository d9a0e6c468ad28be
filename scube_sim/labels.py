"""The fixed semantic label table (Waymo-like), shared by worlds, VoxSplats, LiDAR and datasets.

Ids 0..22 follow the Waymo Open Dataset 3D semantic segmentation classes; 23..25 add the classes
the procedural worlds need (fence, terrain, sky). Frozen at LABEL_TABLE_VERSION: a model trained
on one version reads labels by these ids, so change it only by appending and bumping the version.

`reflectivity` is the factor the LiDAR model's class formula uses where a surface has no measured
reflectance (intensity = reflectivity x cos x fall-off, with no sensor response): rough figures for
asphalt, paint, concrete, foliage and retroreflective sheeting, not measurements.

`REFLECTANCE_DEFAULTS` is the default *reflectance* of each class on the scale of the VoxSplat
`reflectance` channel (Lambertian-equivalent: 1 = a white diffuse target; what the build measures
by inverting each sensor's response): what the converter, which has labels but no LiDAR, writes
into that channel (`reflectance_from_labels`). Each entry names its source; the measured ones are
medians over the real logs in ../shared/data through the build's own estimate
(`tools/measure_class_reflectance.py`; docs/lidar-intensity-and-drop.md has the figures).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError, NotFoundError

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
# The surfaces a vehicle stands on: kept when a moving actor's voxels are cut out of a scene.
GROUND_LABEL_NAMES = ("road", "lane_marker", "curb", "other_ground", "walkable", "sidewalk", "terrain")
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


# --- default reflectance per class (the converter's table) --------------------------------------

# Where the numbers come from (medians of the build's per-return reflectance estimates; nuScenes'
# HDL-32E reports calibrated reflectivity, Argoverse 2's VLP-32C is assumed to; KITTI's HDL-64E
# has no published scale and is not used).
REFLECTANCE_SOURCES: dict[str, str] = {
    "nuscenes": "measured: median over the returns in this class's boxes, nuScenes demo keyframe (HDL-32E)",
    "ground": "measured: mean of the medians of ground returns (< 0.15 m above the local ground; road, paint, "
              "sidewalk together) of nuScenes (0.181) and Argoverse 2 sweep 0 (0.100)",
    "ground_q75": "measured: mean of the ground returns' upper quartiles, nuScenes (0.290) and Argoverse 2 (0.146): "
                  "the lighter part of the ground (concrete), not measured per class",
    "above_ground": "measured: mean of the medians of unlabelled returns above the ground (walls, poles, "
                    "vegetation, objects together) of nuScenes (0.223) and Argoverse 2 (0.162), not per class",
    "all_returns": "measured: median of all of the nuScenes keyframe's returns (0.191)",
    "retroreflective": "not measured: HDL-32E manual, calibrated reflectivity reads retroreflectors above "
                       "100 (rho > 1); 1.0 is the floor of that range",
    "vegetation": "not measured per class: green leaves reflect ~0.45-0.5 in the near infrared (the red edge "
                  "plateau, a standard remote-sensing figure); canopies read lower where beams hit leaves partly",
    "guess": "not measured: a rough figure (material named in the note)",
    "no_return": "the sky returns nothing",
}


@dataclass(frozen=True)
class ReflectanceDefault:
    """label: a class name; reflectance: Lambertian-equivalent (0-1, above 1 for retroreflectors);
    source: a key of REFLECTANCE_SOURCES, or 'as <class>' (taken from a measured similar class)."""

    label: str
    reflectance: float
    source: str
    note: str = ""


REFLECTANCE_DEFAULTS: tuple[ReflectanceDefault, ...] = (
    ReflectanceDefault("undefined", 0.19, "all_returns"),
    ReflectanceDefault("car", 0.13, "nuscenes", "92 returns, 8 boxes; quartiles 0.06-0.24"),
    ReflectanceDefault("truck", 0.17, "nuscenes", "502 returns, 2 boxes; quartiles 0.06-0.27"),
    ReflectanceDefault("bus", 0.17, "as truck"),
    ReflectanceDefault("other_vehicle", 0.15, "as car", "between car (0.13) and truck (0.17)"),
    ReflectanceDefault("motorcyclist", 0.21, "as pedestrian"),
    ReflectanceDefault("bicyclist", 0.21, "as pedestrian"),
    ReflectanceDefault("pedestrian", 0.21, "nuscenes", "137 returns, 30 boxes; quartiles 0.08-0.43"),
    ReflectanceDefault("sign", 1.00, "retroreflective", "retroreflective sheeting"),
    ReflectanceDefault("traffic_light", 0.19, "above_ground"),
    ReflectanceDefault("pole", 0.19, "above_ground"),
    ReflectanceDefault("construction_cone", 0.50, "guess", "orange plastic with a retroreflective collar"),
    ReflectanceDefault("bicycle", 0.13, "as car"),
    ReflectanceDefault("motorcycle", 0.13, "as car"),
    ReflectanceDefault("building", 0.19, "above_ground"),
    ReflectanceDefault("vegetation", 0.45, "vegetation"),
    ReflectanceDefault("tree_trunk", 0.19, "above_ground"),
    ReflectanceDefault("curb", 0.22, "ground_q75"),
    ReflectanceDefault("road", 0.14, "ground"),
    ReflectanceDefault("lane_marker", 0.50, "guess", "white paint with glass beads (partly retroreflective)"),
    ReflectanceDefault("other_ground", 0.14, "ground"),
    ReflectanceDefault("walkable", 0.22, "ground_q75"),
    ReflectanceDefault("sidewalk", 0.22, "ground_q75"),
    ReflectanceDefault("fence", 0.14, "nuscenes", "nuScenes 'barrier' boxes: 317 returns, 22 boxes; quartiles 0.08-0.26"),
    ReflectanceDefault("terrain", 0.30, "guess", "soil and grass"),
    ReflectanceDefault("sky", 0.00, "no_return"),
)
assert tuple(d.label for d in REFLECTANCE_DEFAULTS) == LABEL_NAMES

LABEL_REFLECTANCE = np.array([d.reflectance for d in REFLECTANCE_DEFAULTS], dtype=np.float32)  # (NUM_LABELS,)


def reflectance_from_labels(labels) -> np.ndarray:
    """Default reflectance (same shape as `labels`, float32, Lambertian-equivalent) of integer label
    ids `labels` (any shape; see REFLECTANCE_DEFAULTS). InputError for ids outside the table."""
    a = np.asarray(labels)
    if a.size and not np.issubdtype(a.dtype, np.integer):
        if not np.issubdtype(a.dtype, np.floating) or not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            raise InputError(f"reflectance_from_labels: labels must be integer label ids, got dtype {a.dtype}")
    ids = a.astype(np.int64)
    if ids.size and (ids.min() < 0 or ids.max() >= NUM_LABELS):
        raise InputError(f"reflectance_from_labels: labels hold ids {int(ids.min())}..{int(ids.max())}, "
                         f"expected 0..{NUM_LABELS - 1} (scube_sim.labels)")
    return LABEL_REFLECTANCE[ids]
