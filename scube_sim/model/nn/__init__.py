"""The converter's building blocks, in pure PyTorch, shared by the stages and knowing none of
them: sparse voxel tensors and convolutions (`sparse`), LSS lifting (`lifting`), the diffusion
schedule and sampler (`diffusion`), the image encoders (`image_encoder`), the CPU Gaussian
renderer (`splat_render`, `views`), the sky panorama (`sky`), the VoxSplat activations
(`activations`), camera projection (`camera`), voxel ray casts (`voxel_rays`), positional
encoding (`encoding`), image metrics (`image_metrics`, `lpips`)."""
