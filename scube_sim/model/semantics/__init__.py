"""Stage `voxel-semantics`: labels for ground-truth voxels from their occupancy alone, a sparse
U-Net (`net`, `data`, `stage`)."""
