"""The valid ranges of `realdata.build.BuildOptions`' numbers, in one place: `BuildOptions` checks
them when it is made (a batch's `options`, the API) and `scube-sim build` names its options by them."""

from __future__ import annotations

from ..config import MAX_RANGE_M, SAMPLE_INDEX, VOXEL_SIZE_M, Range
from ..errors import InputError

BUILD_RANGES: dict[str, Range] = {
    "min_range": Range(ge=0, le=1000, unit="metres"),
    "max_range": MAX_RANGE_M,
    "mesh_max_angle_deg": Range(gt=0, le=90, unit="degrees"),
    "mesh_max_edge": Range(gt=0, le=100, unit="metres"),
    "mesh_max_edge_rel": Range(gt=0, le=10),
    "mesh_max_incidence_deg": Range(gt=0, le=90, unit="degrees"),
    "voxel_size": VOXEL_SIZE_M,
    "gaussians_per_voxel": Range(ge=1, le=16, integer=True),
    "patch_scale": Range(gt=0, le=10),
    "max_patch_sigma": Range(gt=0, le=10, unit="metres"),
    "max_normal_scale": Range(gt=0, le=10, unit="metres"),
}
LIST_RANGES: dict[str, Range] = {"samples": SAMPLE_INDEX, "carve_with": SAMPLE_INDEX}


def check_build_options(opts) -> None:
    """InputError naming the field and its range for the first number out of range."""
    for name, rng in BUILD_RANGES.items():
        rng.check(getattr(opts, name), name)
    for name, rng in LIST_RANGES.items():
        values = getattr(opts, name)
        if not isinstance(values, (list, tuple)):
            raise InputError(f"{name}: expected a list of sample indices, got {values!r}")
        for i, v in enumerate(values):
            rng.check(v, f"{name}[{i}]")
