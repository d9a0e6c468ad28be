"""`PosedScene`: a scene traced in its own frame, placed in the world by a rigid pose.

A converted VoxSplat lives in its chunk frame (axis-aligned with the ego at the frames' instant)
and keeps ``chunk_to_world`` in its metadata; anything that fires world-frame rays (the fidelity
report's replay of a real sweep, `Lidar.scan` with world poses) traces it through this wrapper.
"""

from __future__ import annotations

import numpy as np

from ..transforms import check_pose
from .contracts import TraceableScene
from .hits import Hits


class PosedScene:
    """scene: a `TraceableScene` (e.g. a Tracer) whose world frame is the scene frame;
    scene_to_world (4, 4) rigid. `trace_world` takes float64 world-frame rays and returns the
    scene's hits with normals rotated into the world and points in the world (NaN on a miss);
    ranges are unchanged (a rigid motion keeps them)."""

    def __init__(self, scene: TraceableScene, scene_to_world: np.ndarray):
        self.scene = scene
        self.pose = check_pose(np.asarray(scene_to_world, np.float64), "PosedScene: scene_to_world")
        self.accepts_times = bool(getattr(scene, "accepts_times", False))

    def trace_world(self, origins, dirs, t_min=0.0, t_max=np.inf, *args, **kwargs) -> Hits:
        r, t = self.pose[:3, :3], self.pose[:3, 3]
        o = np.asarray(origins, np.float64).reshape(-1, 3)
        d = np.asarray(dirs, np.float64).reshape(-1, 3)
        d = d / np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
        hits = self.scene.trace_world((o - t) @ r, d @ r, t_min, t_max, *args, **kwargs)
        hits.normals = (hits.normals.astype(np.float64) @ r.T).astype(np.float32)
        with np.errstate(invalid="ignore"):
            hits.points = o + hits.t[:, None] * d
        hits.points[~hits.hit] = np.nan
        return hits


def scene_to_world(scene) -> np.ndarray | None:
    """(4, 4) float64 pose in the world of a scene that says it lives in a chunk frame (metadata
    ``frame: chunk`` and ``chunk_to_world``, as the converter and the worlds' ground truth write);
    None for a scene in world coordinates."""
    meta = getattr(scene, "metadata", None) or {}
    if meta.get("frame") == "chunk" and meta.get("chunk_to_world") is not None:
        return np.asarray(meta["chunk_to_world"], np.float64)
    return None


def place_scene(tracer: TraceableScene, scene) -> TraceableScene:
    """`tracer` of a VoxSplat `scene` as a world-frame scene: wrapped in a `PosedScene` where
    `scene_to_world` gives a pose, itself otherwise."""
    pose = scene_to_world(scene)
    return tracer if pose is None else PosedScene(tracer, pose)


__all__ = ["PosedScene", "place_scene", "scene_to_world"]
