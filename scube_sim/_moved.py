"""Where the modules and names of earlier layouts went (the package was arranged by role in
2026-12): importing an old path fails with a message that names the new one, instead of a bare
"No module named". Nothing here is an alias: the old paths do not work, they explain."""

from __future__ import annotations

import importlib.abc
import sys

# old module -> where its contents live now
MOVED_MODULES: dict[str, str] = {
    "scube_sim.batch": "scube_sim.parallel (the task pool) and scube_sim.runs.batch_jobs (the batch jobs)",
    "scube_sim.batch.executors": "scube_sim.parallel.executors",
    "scube_sim.batch.jobs": "scube_sim.runs.batch_jobs",
    "scube_sim.batch.runner": "scube_sim.parallel.runner",
    "scube_sim.batch.tasks": "scube_sim.parallel.tasks",
    "scube_sim.demo": "scube_sim.runs.demo",
    "scube_sim.fidelity": "scube_sim.realdata.fidelity (sweep_agreement, fidelity_config: scube_sim.lidar.compare)",
    "scube_sim.model.activations": "scube_sim.model.nn.activations",
    "scube_sim.model.augment": "scube_sim.model.data.augment",
    "scube_sim.model.camera": "scube_sim.model.nn.camera",
    "scube_sim.model.diffusion": "scube_sim.model.nn.diffusion",
    "scube_sim.model.geometry_metrics": "scube_sim.model.geometry.metrics",
    "scube_sim.model.geometry_nets": "scube_sim.model.geometry.dense_nets",
    "scube_sim.model.geometry_sparse": "scube_sim.model.geometry.sparse_nets",
    "scube_sim.model.image_encoder": "scube_sim.model.nn.image_encoder",
    "scube_sim.model.image_metrics": "scube_sim.model.nn.image_metrics",
    "scube_sim.model.lifting": "scube_sim.model.nn.lifting",
    "scube_sim.model.lpips": "scube_sim.model.nn.lpips",
    "scube_sim.model.sensor_to_sensor": "scube_sim.model.eval.sensor_to_sensor",
    "scube_sim.model.sky": "scube_sim.model.nn.sky",
    "scube_sim.model.sparse": "scube_sim.model.nn.sparse",
    "scube_sim.model.splat_render": "scube_sim.model.nn.splat_render",
    "scube_sim.model.views": "scube_sim.model.nn.views",
    "scube_sim.model.voxel_rays": "scube_sim.model.nn.voxel_rays",
    "scube_sim.model.voxel_semantics": "scube_sim.model.semantics (net, data, stage)",
    "scube_sim.raydrop": "scube_sim.realdata.raydrop",
    "scube_sim.reconstruct": "scube_sim.realdata.build",
    "scube_sim.registration": "scube_sim.datasets.icp",
    "scube_sim.sim.replay": "scube_sim.runs.replay",
    "scube_sim.sim.scenario": "scube_sim.runs.scenario",
    "scube_sim.sim.sim_scene": "scube_sim.sim.scene",
}

# (package or module that still exists) -> {old name: the module that holds it now}
MOVED_NAMES: dict[str, dict[str, str]] = {
    "scube_sim.model.appearance": {
        "AppearanceDataConfig": "scube_sim.model.appearance.data",
        "AppearanceDataset": "scube_sim.model.appearance.data",
        "AppearanceModelConfig": "scube_sim.model.appearance.net",
        "AppearanceNet": "scube_sim.model.appearance.net",
        "AppearanceStage": "scube_sim.model.appearance.stage",
        "EVAL_OFFSETS": "scube_sim.model.appearance.data",
        "FIT_RATES": "scube_sim.model.appearance.fit",
        "ImageEncoder": "scube_sim.model.appearance.net",
        "LOSS_WEIGHTS": "scube_sim.model.appearance.losses",
        "NO_AUGMENT": "scube_sim.model.appearance.data",
        "NUM_RAW": "scube_sim.model.appearance.net",
        "evaluate_item": "scube_sim.model.appearance.losses",
        "first_hit_voxels": "scube_sim.model.appearance.net",
        "fit_input_views": "scube_sim.model.appearance.fit",
        "frame_at": "scube_sim.model.appearance.data",
        "is_front_camera": "scube_sim.model.appearance.data",
        "majority_labels": "scube_sim.model.nn.encoding",
        "positional_encoding": "scube_sim.model.nn.encoding",
        "static_mask": "scube_sim.model.appearance.data",
        "view_losses": "scube_sim.model.appearance.losses",
    },
    "scube_sim.model.data": {
        "CAMERA_KEYS": "scube_sim.model.data.worlds",
        "DataConfig": "scube_sim.model.data.worlds",
        "HELD_OUT_SPLIT": "scube_sim.model.data.worlds",
        "MOVING_SHIFT_M": "scube_sim.model.data.worlds",
        "MOVING_SPEED_MPS": "scube_sim.model.data.worlds",
        "PAD": "scube_sim.model.data.worlds",
        "WorldsTorchDataset": "scube_sim.model.data.worlds",
        "camera_distortion": "scube_sim.model.data.worlds",
        "collate": "scube_sim.model.data.worlds",
        "item_generator": "scube_sim.model.data.worlds",
        "moving_instances": "scube_sim.model.data.worlds",
        "nearest_index": "scube_sim.model.data.worlds",
        "resize_bilinear": "scube_sim.model.data.worlds",
        "resize_nearest": "scube_sim.model.data.worlds",
        "scale_intrinsics": "scube_sim.model.data.worlds",
        "target_size": "scube_sim.model.data.worlds",
    },
    "scube_sim.model.geometry": {
        "DEFAULT_REGION": "scube_sim.model.geometry.data",
        "GeometryDataConfig": "scube_sim.model.geometry.data",
        "GeometryDataset": "scube_sim.model.geometry.data",
        "GeometryModelConfig": "scube_sim.model.geometry.net",
        "GeometryNet": "scube_sim.model.geometry.net",
        "GeometryStage": "scube_sim.model.geometry.stage",
        "GeometryVAEModelConfig": "scube_sim.model.geometry.net",
        "GeometryVAEStage": "scube_sim.model.geometry.stage",
        "ImageConditioner": "scube_sim.model.geometry.net",
        "MASS_EPS": "scube_sim.model.geometry.net",
        "NUM_LABELS": "scube_sim.model.geometry.net",
        "SITE_PE_FREQUENCIES": "scube_sim.model.geometry.net",
        "calibrate_latent_std": "scube_sim.model.geometry.stage",
        "check_inputs": "scube_sim.model.geometry.net",
        "dense_target": "scube_sim.model.geometry.data",
        "flat_keys": "scube_sim.model.geometry.net",
        "grid_in_box": "scube_sim.model.geometry.data",
        "observed_voxels": "scube_sim.model.geometry.net",
    },
    "scube_sim.model.trainer": {
        "evaluate": "scube_sim.model.eval.evaluate",
        "evaluate_model": "scube_sim.model.eval.evaluate",
        "export_weights": "scube_sim.model.checkpoint",
        "load_model": "scube_sim.model.checkpoint",
    },
    "scube_sim.sim": {
        "Scenario": "scube_sim.runs.scenario",
        "build_run": "scube_sim.runs.scenario",
        "load_scenario": "scube_sim.runs.scenario",
    },
}


class _MovedFinder(importlib.abc.MetaPathFinder):
    """Last on `sys.meta_path`: asked only for modules no other finder found."""

    def find_spec(self, fullname, path=None, target=None):
        new = MOVED_MODULES.get(fullname)
        if new is not None:
            raise ModuleNotFoundError(f"No module named {fullname!r}: it moved to {new}", name=fullname)
        return None


def install() -> None:
    """Put the finder last on sys.meta_path (once)."""
    if not any(isinstance(f, _MovedFinder) for f in sys.meta_path):
        sys.meta_path.append(_MovedFinder())


def moved_name_getattr(module: str):
    """A module `__getattr__` for `module` whose names in MOVED_NAMES raise an ImportError naming
    their new module (`from old import name` reports it); any other name is an AttributeError."""
    table = MOVED_NAMES[module]

    def __getattr__(name: str):
        if name in table:
            raise ImportError(
                f"cannot import name {name!r} from {module!r}: it moved to {table[name]} "
                f"(from {table[name]} import {name})",
                name=module,
            )
        raise AttributeError(f"module {module!r} has no attribute {name!r}")

    return __getattr__
