"""Converted scenes in the simulator loop: a VoxSplat the caller converted from camera frames
(`scube_sim.convert`) placed in the world, with the moving actors the loop traces as instances cut out of it.

The converter sees each actor where it stood when the cameras fired; the loop also traces the
actor's own mesh where it is at each fire time. Left in, the actor would be seen twice (a frozen
copy and the moving one), so its voxels are removed (as the paper's data pipeline removes dynamic
objects): every voxel whose centre lies inside the actor's box at the frames' instant, grown by
half a voxel on each side, except the ground under it (GROUND_LABEL_NAMES), which the actor
stands on and does not hide once it has moved.
"""

from __future__ import annotations

import numpy as np

from ..boxes import Box, points_in_boxes
from ..camera.frames import Frames
from ..labels import GROUND_LABEL_NAMES, LABEL_IDS
from ..raytrace.posed import scene_to_world
from ..raytrace.tracer import HardMode, SoftMode, Tracer
from ..transforms import transform_points
from ..voxsplat import VoxSplat
from .scene import Part, SimScene

DEFAULT_MODE = "max_response"  # scenes that name no trace mode (ground-truth and measured VoxSplats)

__all__ = ["remove_boxes", "scene_mode", "scene_part", "simulated_scene"]


def scene_part(scene: VoxSplat, *, name: str = "scene", mode: str | HardMode | SoftMode | None = None) -> Part:
    """A static `Part` of a VoxSplat: placed by `scene_to_world`, traced in `mode` (default: the
    scene's metadata ``trace_mode``, else DEFAULT_MODE)."""
    return Part(Tracer(scene, mode or scene_mode(scene)), pose=scene_to_world(scene), name=name)


def scene_mode(scene: VoxSplat) -> str:
    """The trace mode a VoxSplat names (metadata ``trace_mode``), else DEFAULT_MODE."""
    return scene.metadata.get("trace_mode", DEFAULT_MODE)


def remove_boxes(scene: VoxSplat, boxes: list[Box], *, margin: float | None = None) -> tuple[VoxSplat, int]:
    """`scene` without the voxels inside `boxes` (world frame; module docstring): -> (the new
    scene, the number of voxels removed). margin: metres added on every side (default half a
    voxel)."""
    if not boxes:
        return scene, 0
    margin = 0.5 * scene.voxel_size if margin is None else float(margin)
    centres = scene.voxel_centers() + scene.origin
    pose = scene_to_world(scene)
    if pose is not None:
        centres = transform_points(pose, centres)
    inside = points_in_boxes(centres, boxes, margin) >= 0
    ground = np.isin(scene.labels, [LABEL_IDS[n] for n in GROUND_LABEL_NAMES])
    cut = inside & ~ground
    if not cut.any():
        return scene, 0
    out = scene.select_voxels(~cut)
    out.metadata["removed_actor_voxels"] = int(cut.sum())
    return out, int(cut.sum())


def simulated_scene(frames: Frames, scene: VoxSplat, *, actors: list[Part] | None = None,
                    static_boxes: list[Box] | None = None) -> tuple[SimScene, VoxSplat]:
    """A host's frames and the VoxSplat converted from them (`scube_sim.convert(frames, ...)`) ->
    (a `SimScene` of that VoxSplat and `actors`, the VoxSplat with the actors' voxels removed).
    The actors' boxes are taken at the frames' timestamp."""
    actors = list(actors or [])
    scene, _ = remove_boxes(scene, [a.box_at(float(frames.timestamp)) for a in actors])
    return SimScene(static=[scene_part(scene, name="converted")], actors=actors, static_boxes=static_boxes), scene
