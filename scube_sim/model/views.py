"""Camera views of a scene for users: any VoxSplat or 3DGS file through a camera rig, rendered by
the CPU Gaussian renderer (`splat_render`). Frames: the ego pose is in the scene's frame (z up);
the rig mounts its cameras on the ego (`camera.rig`)."""

from __future__ import annotations

import numpy as np
import torch

from ..camera.rig import RigConfig
from ..voxsplat import Gaussians, VoxSplat
from .splat_render import rasterization

__all__ = ["render_rig"]


def render_rig(scene: VoxSplat | Gaussians, rig: RigConfig, ego_pose: np.ndarray, *, scale: float = 0.25,
               background=(0.0, 0.0, 0.0)) -> dict[str, np.ndarray]:
    """Render every camera of `rig` at `scale` of its resolution: name -> (H, W, 3) float32 RGB in
    [0, 1]. ego_pose (4, 4) ego-to-scene (metres). Colours are the Gaussians' SH degree 0."""
    g = scene.gaussians() if isinstance(scene, VoxSplat) else scene
    means = torch.from_numpy(np.asarray(g.means, np.float32))
    quats = torch.from_numpy(np.asarray(g.quats, np.float32))
    scales = torch.from_numpy(np.asarray(g.scales, np.float32))
    opac = torch.from_numpy(np.asarray(g.opacities, np.float32))
    colors = torch.from_numpy(np.asarray(g.colors, np.float32))
    bg = torch.tensor([list(background)], dtype=torch.float32)
    out = {}
    with torch.no_grad():
        for cam in rig.cameras:
            intr = cam.intrinsics().scaled(scale)
            cam_to_scene = np.asarray(ego_pose, np.float64) @ cam.cam_to_ego()
            cam_to_scene[:3, 3] -= g.origin  # the Gaussians' local frame: small numbers in float32
            viewmat = torch.from_numpy(np.linalg.inv(cam_to_scene).astype(np.float32))[None]
            dist = None if intr.model == "pinhole" or not intr.dist else torch.tensor([intr.dist], dtype=torch.float64)
            img, _, _ = rasterization(means, quats, scales, opac, colors, viewmat,
                                      torch.from_numpy(intr.K.astype(np.float32))[None], intr.width, intr.height,
                                      backgrounds=bg, camera_model=intr.model if dist is not None else "pinhole",
                                      dist_coeffs=dist, use_checkpoint=False)
            out[cam.name] = img[0].clamp(0, 1).numpy()
    return out
