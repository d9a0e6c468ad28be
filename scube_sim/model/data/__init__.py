"""The converter's training data: worlds samples as torch items (`worlds`) and the photometric
augmentation and rig randomisation of the input images (`augment`)."""
