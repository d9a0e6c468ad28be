"""scube-sim: LiDAR simulation on VoxSplats (SCube) with Embree hard-opacity ray tracing.

Public faces: this package (the VoxSplat container and the error base), `scube_sim.raytrace`,
`scube_sim.lidar`, `scube_sim.camera`, `scube_sim.worlds`, `scube_sim.datasets`, `scube_sim.sim`.
"""

from .errors import ScubeSimError
from .voxsplat import Gaussians, VoxSplat

__all__ = ["Gaussians", "ScubeSimError", "VoxSplat"]
__version__ = "0.1.0"
