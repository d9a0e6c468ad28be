"""Look at a world: the rig's views at the reference instant and a top view of its GT voxels."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera.render import render_camera
from ..camera.rig import load_rig
from ..mesh import TriangleMesh
from ..raytrace.tracer import Tracer
from ..transforms import invert_pose, transform_points
from ..viz import mosaic_png, voxel_bev_png
from .generator import WorldConfig, generate_world
from .groundtruth import CHUNK_CORNER, coarsen, depth_to_points, mark_visible, voxelize_mesh
from .textures import world_albedo


def preview_world(cfg: WorldConfig, out: str | Path, *, name: str | None = None, rig: str = "waymo-5",
                  image_scale: float = 0.3, voxel_size: float = 0.2) -> dict:
    """Write <name>_views.png and <name>_voxels.png into `out`; returns paths and counts."""
    out = Path(out)
    name = name or f"{cfg.style}-{cfg.seed}"
    world = generate_world(cfg)
    rig_cfg = load_rig(rig)
    tracers = [Tracer(world.static)]
    if world.actors:
        tracers.append(Tracer(TriangleMesh.concatenate(world.actor_meshes_at(0.0))))
    ego = world.ego_pose_at(0.0)
    images, seen = {}, []
    for cam in rig_cfg.cameras:
        intr = cam.intrinsics().scaled(image_scale)
        pose = ego @ cam.cam_to_ego()
        r = render_camera(tracers, intr, pose, sun_dir=world.sun_dir, albedo_fn=world_albedo(world, 0.0))
        images[cam.name] = r["rgb"]
        seen.append(transform_points(invert_pose(ego), depth_to_points(r["depth"], intr, pose)))
    fine = voxelize_mesh(world.mesh_at(0.0), ego, voxel_size)
    fine.visible = mark_visible(fine, np.concatenate(seen))
    coarse = coarsen(fine, 2)
    views = mosaic_png(out / f"{name}_views.png", images,
                       title=f"{name}: {cfg.style}, {world.layout.kind}, rig {rig} at T")
    bev = voxel_bev_png(out / f"{name}_voxels.png", coarse.ijk, coarse.labels, coarse.voxel_size,
                        corner=CHUNK_CORNER, visible=coarse.visible,
                        title=f"{name}: ground-truth voxels ({coarse.voxel_size:g} m) of the 102.4 m chunk")
    return {"views": views, "voxels": bev, "num_voxels": len(coarse), "visible": float(coarse.visible.mean())}
