"""The converter's learned parts: the networks, their stages and their training. Inference runs
them from `scube_sim.converter`; measured geometry is in `scube_sim.reconstruct`.

- `checkpoint`: checkpoint files and `load_model`; `stages`: the stage registry; `config`: run
  configs; `trainer`: the one trainer every stage uses; `evaluate`: a stage's checkpoint on a split.
- `nn/`: the building blocks no stage owns (sparse convolutions, dense 3D blocks, lifting,
  diffusion, the image encoders, the Gaussian renderer, the sky panorama, label metrics).
- Stages, each a folder with `net`, `data` and `stage`: `geometry/` (structure VAE and latent
  diffusion), `appearance/` (Gaussians and the sky), `semantics/` (voxel labels), `completion/`
  (what no camera saw, from the measured evidence).
- `data/`: the worlds as training data, augmentation.
"""
