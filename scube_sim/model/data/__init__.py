"""The converter's training data: worlds samples as torch items (`worlds`) and the photometric
augmentation and rig randomisation of the input images (`augment`)."""

from ..._moved import moved_name_getattr

__getattr__ = moved_name_getattr(__name__)  # names of the earlier layout: a message naming their module
