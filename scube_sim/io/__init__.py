"""File formats: point clouds (PCD, PLY, KITTI .bin, .npz), 3DGS PLY, USD."""
