"""Stages `geometry-vae` and `geometry` (paper section 3.1): posed camera images to a semantic
voxel grid, through a structure VAE and an image-conditioned latent diffusion (XCube).
`data` (the level's grid and dataset), `net` (the conditional model), `dense_nets` and
`sparse_nets` (the coarse and fine levels' VAEs and denoisers), `metrics` (IoU, Chamfer),
`stage` (both stages: losses, evaluation, the frozen VAE's loading); `fusion` (no learning:
measured depth fused into a sparse occupancy grid, surfels on what the cameras saw) and `ground`
(the ground's height field under them), which the evidence route (`model.evidence`) uses."""

from ..._moved import moved_name_getattr

__getattr__ = moved_name_getattr(__name__)  # names of the earlier layout: a message naming their module
