"""Camera rigs: validated YAML in `sensors/rigs/`, resolvable by name like the LiDAR presets.

A camera's `mount` is the pose of its body frame (x forward along the optical axis, y left, z up)
in the ego frame, in metres and degrees; `cam_to_ego` turns it into the OpenCV optical frame
(x right, y down, z forward). `time_offset_s` is when the camera fires relative to the rig's
reference instant (real rigs fire cameras tens of milliseconds apart).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from ..config import ConfigError, Mount, StrictModel, listed_twice, load_yaml, normalize_name, validate_model
from ..errors import NotFoundError
from ..resources import sensors_dir
from .model import Intrinsics

# Body (x forward, y left, z up) -> OpenCV optical (x right, y down, z forward).
BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0, 0, 0, 1.0]])


class Distortion(StrictModel):
    model: Literal["pinhole", "opencv", "fisheye"] = "pinhole"
    coeffs: list[float] = Field(default_factory=list)


class CameraConfig(StrictModel):
    name: str
    width: int = Field(gt=0, le=20000)
    height: int = Field(gt=0, le=20000)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    distortion: Distortion = Distortion()
    mount: Mount = Mount()
    time_offset_s: float = 0.0

    def intrinsics(self) -> Intrinsics:
        return Intrinsics(self.width, self.height, self.fx, self.fy, self.cx, self.cy,
                          self.distortion.model, tuple(self.distortion.coeffs))

    def cam_to_ego(self) -> np.ndarray:
        """(4, 4) OpenCV camera frame -> ego frame."""
        return self.mount.matrix() @ BODY_FROM_OPTICAL


class RigConfig(StrictModel):
    name: str
    source: str = ""
    notes: str = ""
    cameras: list[CameraConfig] = Field(min_length=1)

    @field_validator("cameras")
    @classmethod
    def _unique(cls, v):
        msg = listed_twice([c.name for c in v])
        if msg:
            raise ValueError(f"camera names must be unique: {msg}")
        return v

    def camera(self, name: str) -> CameraConfig:
        for c in self.cameras:
            if c.name == name:
                return c
        raise NotFoundError(f"rig {self.name!r} has no camera {name!r}")


def rig_paths() -> dict[str, Path]:
    return {normalize_name(p.stem): p for p in sorted((sensors_dir() / "rigs").glob("*.yaml"))}


def load_rig(name_or_path: str | Path) -> RigConfig:
    """A rig by name ('waymo-5', 'nuscenes-6') or a YAML path; errors name the file and key."""
    s = str(name_or_path)
    p = Path(s)
    if not (p.suffix.lower() in (".yaml", ".yml") or p.is_file()):
        paths = rig_paths()
        key = normalize_name(s)
        if key not in paths:
            raise ConfigError(f"unknown camera rig {s!r}; rigs: {', '.join(sorted(q.stem for q in paths.values()))}")
        p = paths[key]
    return validate_model(RigConfig, load_yaml(p), str(p), "camera rig settings")
