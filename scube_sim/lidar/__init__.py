"""The LiDAR model: validated sensor configs, scan patterns and sweeps."""

from .config import ConfigError, LidarConfig, list_presets, load_lidar_config
from .model import CONVERTED_POINT_DTYPE, POINT_DTYPE, Lidar, Sweep

__all__ = ["CONVERTED_POINT_DTYPE", "ConfigError", "Lidar", "LidarConfig", "POINT_DTYPE", "Sweep", "list_presets", "load_lidar_config"]
