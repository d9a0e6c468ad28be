"""Dataset adapters, one module per format, opened by name (kiss-icp style factory).

    ds = open_dataset("nuscenes", "path/to/folder")
    sample = ds[0]          # Sample: Frames, LiDAR sweeps, boxes

Modules are imported only when their format is asked for.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from ..boxes import Box, points_in_boxes
from ..errors import InputError
from .base import Dataset, DatasetError, LidarSpec, LidarSweep, Sample

# name -> "module:Class"; each class takes (root: Path, **options).
_ADAPTERS = {
    "nuscenes": "nuscenes:NuScenesDataset",
    "kitti_raw": "kitti:KittiRawDataset",
    "kitti_object": "kitti:KittiObjectDataset",
    "kitti360": "kitti360:Kitti360Dataset",
    "waymo": "waymo:WaymoFrameDataset",
    "argoverse2": "argoverse2:Argoverse2Dataset",
    "tri_dgp": "tri_dgp:TriDgpDataset",
    "folder": "folder:FolderDataset",
    "worlds": "worlds:WorldsDataset",
}


def available() -> list[str]:
    return sorted(_ADAPTERS)


def open_dataset(name: str, root: str | Path, **options) -> Dataset:
    """Open the dataset at `root` with the adapter called `name` (see `available()`)."""
    key = name.lower().replace("-", "_")
    if key not in _ADAPTERS:
        raise InputError(f"dataset: unknown format {name!r}; expected one of {', '.join(available())}")
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"{root}: no such dataset path")
    module, cls = _ADAPTERS[key].split(":")
    return getattr(importlib.import_module(f"{__name__}.{module}"), cls)(root, **options)


__all__ = ["Box", "Dataset", "DatasetError", "LidarSpec", "LidarSweep", "Sample", "available", "open_dataset",
           "points_in_boxes"]
