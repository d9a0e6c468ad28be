"""scube-sim: LiDAR simulation on VoxSplats (SCube) with Embree hard-opacity ray tracing."""

from .voxsplat import Gaussians, VoxSplat

__all__ = ["Gaussians", "VoxSplat"]
__version__ = "0.1.0"
