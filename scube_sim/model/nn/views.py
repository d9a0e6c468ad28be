"""Camera views of a scene for users: any VoxSplat or 3DGS file through a camera rig, rendered by
the CPU Gaussian renderer (`splat_render`). Frames: the ego pose is in the scene's frame (z up);
the rig mounts its cameras on the ego (`camera.rig`). A VoxSplat with a ``sky_panorama`` channel
shows its sky through the transmittance the Gaussians leave (1 - accumulated alpha)."""

from __future__ import annotations

import numpy as np
import torch

from ...camera.rig import RigConfig
from ...voxsplat import Gaussians, VoxSplat
from .sky import sample_panorama
from .splat_render import rasterization

__all__ = ["render_rig"]


def render_rig(scene: VoxSplat | Gaussians, rig: RigConfig, ego_pose: np.ndarray, *, scale: float = 0.25,
               background=(0.0, 0.0, 0.0)) -> dict[str, np.ndarray]:
    """Render every camera of `rig` at `scale` of its resolution: name -> (H, W, 3) float32 RGB in
    [0, 1]. ego_pose (4, 4) ego-to-scene (metres). Colours are the Gaussians' SH degree 0. The
    background is the scene's sky panorama where it has one (`background` otherwise)."""
    g = scene.gaussians() if isinstance(scene, VoxSplat) else scene
    sky = None
    if isinstance(scene, VoxSplat) and "sky_panorama" in scene.channels:
        sky = torch.from_numpy(np.asarray(scene.channel("sky_panorama"), np.float32)).permute(2, 0, 1)
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
            img, alpha, _ = rasterization(means, quats, scales, opac, colors, viewmat,
                                          torch.from_numpy(intr.K.astype(np.float32))[None], intr.width, intr.height,
                                          backgrounds=bg if sky is None else None,
                                          camera_model=intr.model if dist is not None else "pinhole",
                                          dist_coeffs=dist, use_checkpoint=False)
            img = img[0]
            if sky is not None:
                # the camera's own lens model: its pixel rays, rotated into the scene's axes
                dirs = torch.from_numpy(np.asarray(intr.pixel_rays(), np.float64) @ cam_to_scene[:3, :3].T)
                img = img + (1 - alpha[0]) * sample_panorama(sky, dirs).permute(1, 2, 0)
            out[cam.name] = img.clamp(0, 1).numpy()
    return out
