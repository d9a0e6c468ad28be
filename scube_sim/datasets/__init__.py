"""Dataset adapters, one module per format, opened by name (kiss-icp style factory).

    ds = open_dataset("nuscenes", "path/to/folder")
    sample = ds[0]          # Sample: Frames, LiDAR sweeps, boxes

Modules are imported only when their format is asked for.
"""

from __future__ import annotations

import importlib
import re
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


# other names users type for an adapter (compared as `_plain` spellings)
_ALIASES = {"av2": "argoverse2", "argoverse": "argoverse2", "dgp": "tri_dgp", "tri": "tri_dgp",
            "kittiraw": "kitti_raw", "kittiobject": "kitti_object", "waymoopen": "waymo"}


def available() -> list[str]:
    return sorted(_ADAPTERS)


def _plain(name: str) -> str:
    """A name as compared: lower case, letters and digits only (`KITTI-360`, `kitti_360` -> `kitti360`)."""
    return re.sub(r"[^a-z0-9]", "", str(name).lower())


def adapter_name(name: str) -> str:
    """The adapter a user's spelling names (`nuScenes`, `kitti-360`, `KITTI_360`, `av2`, ...);
    an unknown name is an InputError listing the known ones."""
    plain = {_plain(k): k for k in _ADAPTERS}
    key = plain.get(_plain(name)) or _ALIASES.get(_plain(name))
    if key is None:
        hint = " (kitti_raw or kitti_object?)" if _plain(name) == "kitti" else ""
        raise InputError(f"dataset: unknown format {name!r}{hint}; expected one of {', '.join(available())}")
    return key


def open_dataset(name: str, root: str | Path, **options) -> Dataset:
    """Open the dataset at `root` with the adapter called `name` (see `available()`; the spellings
    users type are accepted: `adapter_name`)."""
    key = adapter_name(name)
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"{root}: no such dataset path")
    module, cls = _ADAPTERS[key].split(":")
    return getattr(importlib.import_module(f"{__name__}.{module}"), cls)(root, **options)


__all__ = ["Box", "Dataset", "DatasetError", "LidarSpec", "LidarSweep", "Sample", "adapter_name", "available",
           "open_dataset", "points_in_boxes"]
