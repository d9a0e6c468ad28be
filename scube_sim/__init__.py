"""scube-sim: LiDAR simulation on VoxSplats (SCube) with Embree hard-opacity ray tracing.

Public faces: this package (the VoxSplat container and the error base), `scube_sim.raytrace`,
`scube_sim.lidar`, `scube_sim.camera`, `scube_sim.worlds`, `scube_sim.datasets`, `scube_sim.sim`.
"""

import os

# Idle OpenMP threads sleep rather than spin (read when torch's OpenMP starts): on a machine other
# jobs share, a spinning thread holds a core another thread of ours is waiting for.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from ._version import __version__  # noqa: E402
from .errors import ScubeSimError  # noqa: E402
from .voxsplat import Gaussians, VoxSplat  # noqa: E402


def convert(frames, **options) -> VoxSplat:
    """The sensor-to-sensor converter: posed camera `frames` (`scube_sim.camera.Frames`) -> a
    VoxSplat in their ego frame (`scube_sim.converter.pipeline.convert`: its options, the default
    profile among them). torch and the models load on the first call, not on `import scube_sim`."""
    from .converter.pipeline import convert as _convert

    return _convert(frames, **options)


__all__ = ["Gaussians", "ScubeSimError", "VoxSplat", "__version__", "convert"]
