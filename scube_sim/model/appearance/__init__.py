"""Stage `appearance` (paper section 3.2): images and the geometry's voxels to M Gaussians per
voxel and a sky panorama. `net` (the network), `data` (the dataset), `losses` (the views' loss
and metrics), `fit` (the optional test-time fit to the input views), `stage`."""
