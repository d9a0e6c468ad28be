"""Stages `geometry-vae` and `geometry` (paper section 3.1): posed camera images to a semantic
voxel grid, through a structure VAE and an image-conditioned latent diffusion (XCube).
`data` (the level's grid and dataset), `net` (the conditional model), `dense_nets` and
`sparse_nets` (the coarse and fine levels' VAEs and denoisers), `metrics` (IoU, Chamfer),
`stage` (both stages: losses, evaluation, the frozen VAE's loading)."""
