"""Procedural driving worlds and the training data made from them.

`generate_world(WorldConfig(...))` builds a seeded street world (static mesh, moving actors with
tracks and boxes, the ego's path); `generate_dataset` renders and voxelizes worlds into the
on-disk layout of `worlds.dataset` (read back with `load_sample`, or as a dataset adapter with
``scube_sim.datasets.open_dataset("worlds", DIR)``); `preview_world` writes a look at one world.
World frame: z up, metres; the ego starts at x = 0 heading +x.
"""

from .dataset import (
           DatasetConfig,
           ensure_dataset_config,
           generate_dataset,
           load_sample,
           make_sample,
           read_dataset_config,
           sample_frames,
           sample_world_config,
           write_sample,
)
from .generator import STYLES, Actor, World, WorldConfig, generate_world
from .groundtruth import CHUNK_CORNER, CHUNK_SIZE, VoxelGrid, gt_voxsplat
from .preview import preview_world
from .textures import TEXTURE_VERSION, ObjectFrames, albedo, world_albedo

__all__ = ["CHUNK_CORNER", "CHUNK_SIZE", "STYLES", "Actor", "DatasetConfig", "VoxelGrid", "World", "WorldConfig",
           "ObjectFrames", "TEXTURE_VERSION", "albedo", "ensure_dataset_config", "generate_dataset", "generate_world", "gt_voxsplat", "load_sample",
           "make_sample", "preview_world", "read_dataset_config", "sample_frames", "sample_world_config",
           "world_albedo", "write_sample"]
