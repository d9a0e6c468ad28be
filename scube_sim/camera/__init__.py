"""Cameras: OpenCV intrinsics and distortion models, rig definitions (camera mounts and firing
offsets), the posed-image set `Frames` that the converter takes as input, and a mesh renderer
(RGB, z-depth, semantics, sky) that shades with an albedo its caller supplies.

Frames: OpenCV cameras (x right, y down, z forward); poses are (4, 4) float64 camera-to-world;
times in seconds.
"""

from .frames import CameraImage, Frames
from .model import Intrinsics
from .render import render_camera, sky_color
from .rig import CameraConfig, RigConfig, load_rig, rig_paths

__all__ = ["CameraConfig", "CameraImage", "Frames", "Intrinsics", "RigConfig", "load_rig", "render_camera",
           "rig_paths", "sky_color"]
