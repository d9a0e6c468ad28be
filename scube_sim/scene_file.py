"""Load a scene file by its suffix: a VoxSplat .npz or any 3DGS .ply."""

from __future__ import annotations

from pathlib import Path

from .config import VOXEL_SIZE_M
from .errors import InputError
from .io.ply3dgs import default_voxel_size, read_3dgs_ply
from .voxsplat import Gaussians, VoxSplat


def load_scene(path: str | Path) -> VoxSplat | Gaussians:
    """A VoxSplat (.npz written by scube_sim) or the Gaussians of a 3DGS .ply (Inria layout)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such scene file")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return VoxSplat.load(path)
    if suffix == ".ply":
        return read_3dgs_ply(path)
    raise InputError(f"{path}: unknown scene format {path.suffix!r}; expected a VoxSplat .npz or a 3DGS .ply")


def as_voxsplat(scene: VoxSplat | Gaussians, voxel_size: float | None = None) -> VoxSplat:
    """A VoxSplat for any scene (3DGS Gaussians are voxelized by their centres)."""
    if isinstance(scene, VoxSplat):
        return scene
    if voxel_size is None:  # 0 is an error, not "automatic"
        return VoxSplat.from_gaussians(scene, default_voxel_size(scene))
    return VoxSplat.from_gaussians(scene, VOXEL_SIZE_M.check(voxel_size, "voxel_size"))
