"""The converter's networks, in pure PyTorch: sparse voxel tensors and convolutions (`sparse`),
the shared VoxSplat activations (`activations`), the worlds as training data (`data`) and the one
trainer both converter stages use (`trainer`, configs in `config`)."""
