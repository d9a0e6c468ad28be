"""The sensor-to-sensor converter: posed camera frames to a VoxSplat (`converter`, inference only),
its learned stages and their training.

- `converter`: profiles and `Converter` (geometry, then appearance); `checkpoint`: checkpoint
  files and `load_model`; `stages`: the stage registry; `config`: run configs; `trainer`: the one
  trainer every stage uses.
- `nn/`: the building blocks no stage owns (sparse convolutions, lifting, diffusion, the image
  encoders, the Gaussian renderer, the sky panorama, activations).
- Stages, each a folder with `net`, `data` and `stage`: `geometry/` (structure VAE and latent
  diffusion), `appearance/` (Gaussians and the sky), `semantics/` (voxel labels).
- `data/`: the worlds as training data, augmentation; `eval/`: evaluation of a checkpoint and the
  converter end to end (`sensor_to_sensor`).
"""
