"""scube-sim: LiDAR simulation on VoxSplats (SCube) with Embree hard-opacity ray tracing.

Public faces: this package (the VoxSplat container and the error base), `scube_sim.raytrace`,
`scube_sim.lidar`, `scube_sim.camera`, `scube_sim.worlds`, `scube_sim.datasets`, `scube_sim.sim`.
"""

from . import _moved
from ._version import __version__
from .errors import ScubeSimError
from .voxsplat import Gaussians, VoxSplat

_moved.install()  # an import of an earlier layout's module names its new place


def convert(frames, *, profile="cpu", steps=None, seed=0, confidence=False, k=None, sky=True,
            max_range=None, fit_steps=None) -> VoxSplat:
    """The sensor-to-sensor converter: posed camera `frames` (`scube_sim.camera.Frames`) -> a
    VoxSplat in their ego frame, with semantics, sky, per-voxel observation and confidence, and
    provenance (`scube_sim.model.converter.Converter.convert`). torch and the models load on the
    first call, not on `import scube_sim`."""
    from .model.converter import convert as _convert  # the one upward import: keeps the package torch-free

    return _convert(frames, profile=profile, steps=steps, seed=seed, confidence=confidence, k=k, sky=sky,
                    max_range=max_range, fit_steps=fit_steps)


__all__ = ["Gaussians", "ScubeSimError", "VoxSplat", "__version__", "convert"]
