"""Measured reconstruction, no learning: camera frames to the surfaces they saw.

- `stereo/`: plane-sweep multi-view stereo (`stereo.mvs.stereo_depth`), the choice of its source
  views, moving objects and the filling of depth gaps.
- `fusion`: depth maps fused into a sparse occupancy grid, free space carved by every ray.
- `ground`: the ground plane (RANSAC) and the height field over it.
- `surfels`: Gaussians fitted to the fused points, ground and box samples where no camera saw.
- `evidence`: the whole route (`measure_evidence`) and its record (`Evidence`).
- `config`: the settings of each step (no torch).

Frames: depths are metres along a camera's z; grids, points and surfels are in the chunk frame
(x forward, y left, z up from the road under the ego, metres).
"""
