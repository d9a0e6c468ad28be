"""One oriented 3D box type for every producer (worlds, the simulator, dataset adapters) and
every consumer (sinks, reconstruction, evaluation), with one JSON form."""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass, field

import numpy as np

from .errors import InputError


@dataclass
class Box:
    """An oriented box. center (3,) float64 metres and rotation (3, 3) box-to-parent (world, unless
    said otherwise); size (3,) length/width/height along the box's x/y/z. label: our label id
    (`scube_sim.labels`); instance: the instance id the box's points carry (0: none); track_id:
    the dataset's own object id; category: the dataset's own class name; velocity (3,) m/s in the
    parent frame, NaN where unknown. yaw: the heading in radians as its producer states it (a
    track's unwrapped angle may leave (-pi, pi]); default, and checked against, the rotation's."""

    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray
    _: KW_ONLY
    label: int = 0
    instance: int = 0
    track_id: str = ""
    category: str = ""
    velocity: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    yaw: float | None = None

    def __post_init__(self):
        self.center = np.asarray(self.center, np.float64).reshape(3)
        self.size = np.asarray(self.size, np.float64).reshape(3)
        self.rotation = np.asarray(self.rotation, np.float64).reshape(3, 3)
        self.velocity = np.asarray(self.velocity, np.float64).reshape(3)
        heading = float(np.arctan2(self.rotation[1, 0], self.rotation[0, 0]))
        if self.yaw is None:
            self.yaw = heading
        else:
            self.yaw = float(self.yaw)
            if abs(np.angle(np.exp(1j * (self.yaw - heading)))) > 1e-6:
                raise InputError(f"box: yaw {self.yaw} rad disagrees with its rotation's heading {heading} rad")

    @classmethod
    def on_ground(cls, pose: np.ndarray, size, **kw) -> "Box":
        """The box of an object whose (4, 4) pose sits at the middle of its bottom face."""
        p = np.asarray(pose, np.float64)
        size = np.asarray(size, np.float64)
        center = p[:3, :3] @ np.array([0.0, 0.0, size[2] / 2]) + p[:3, 3]
        return cls(center, size.copy(), p[:3, :3].copy(), **kw)

    @property
    def speed(self) -> float:
        return float(np.linalg.norm(self.velocity)) if np.all(np.isfinite(self.velocity)) else float("nan")

    def box_to_world(self) -> np.ndarray:
        """(4, 4) float64 box-to-parent."""
        t = np.eye(4)
        t[:3, :3], t[:3, 3] = self.rotation, self.center
        return t

    def to_json(self) -> dict:
        """{instance, label, center, size, yaw} and, where they carry information, rotation (when
        the box is not upright), track_id, category and velocity."""
        out = {"instance": int(self.instance), "label": int(self.label), "center": [float(v) for v in self.center],
               "size": [float(v) for v in self.size], "yaw": self.yaw}
        if not np.allclose(self.rotation, _rot_z(self.yaw), rtol=0.0, atol=1e-9):
            out["rotation"] = [[float(v) for v in row] for row in self.rotation]
        if self.track_id:
            out["track_id"] = str(self.track_id)
        if self.category:
            out["category"] = str(self.category)
        if np.all(np.isfinite(self.velocity)):
            out["velocity"] = [float(v) for v in self.velocity]
        return out

    @classmethod
    def from_json(cls, data: dict) -> "Box":
        """The inverse of `to_json` (a missing rotation is the upright one of `yaw`)."""
        yaw = float(data["yaw"])
        rot = np.asarray(data["rotation"], np.float64) if "rotation" in data else _rot_z(yaw)
        vel = np.asarray(data["velocity"], np.float64) if "velocity" in data else np.full(3, np.nan)
        return cls(np.asarray(data["center"], np.float64), np.asarray(data["size"], np.float64), rot,
                   label=int(data.get("label", 0)), instance=int(data.get("instance", 0)),
                   track_id=str(data.get("track_id", "")), category=str(data.get("category", "")), velocity=vel,
                   yaw=yaw)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def points_in_boxes(points: np.ndarray, boxes: list[Box], margin: float = 0.0) -> np.ndarray:
    """(N,) int64 index of the first box containing each point (-1: none); points (N, 3) in the
    boxes' parent frame. margin: metres added on every side (LiDAR points on a box's surface lie
    just outside a tight label)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.full(p.shape[0], -1, np.int64)
    for i, b in enumerate(boxes):
        half = 0.5 * b.size + margin
        r = np.linalg.norm(half)
        cand = np.flatnonzero((out < 0) & (np.sum((p - b.center) ** 2, axis=1) <= r * r))
        if cand.size == 0:
            continue
        local = (p[cand] - b.center) @ b.rotation
        inside = np.all(np.abs(local) <= half, axis=1)
        out[cand[inside]] = i
    return out
