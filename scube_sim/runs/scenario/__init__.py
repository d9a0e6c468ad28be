"""Scenario files: `schema` says what a file may hold (pydantic models; the format is in its
docstring), `build` turns a validated scenario into a ready `Simulator`."""

from .build import (
    CACHE_FOLDERS,
    BuiltScene,
    build_pose_source,
    build_run,
    build_scene,
    build_sensors,
    build_sinks,
    conversion_key,
    frames_digest,
    route_stops,
    run_manifest,
    sensor_names,
)
from .schema import (
    CanSpec,
    ChunkEntry,
    EditSpec,
    EffectsSpec,
    FramesSpec,
    OutputsSpec,
    Scenario,
    SceneSpec,
    SensorSpec,
    TrajectorySpec,
    load_scenario,
    resolve_path,
    sensor_config,
    shared_data_dir,
)

__all__ = ["CACHE_FOLDERS", "BuiltScene", "CanSpec", "ChunkEntry", "EditSpec", "EffectsSpec", "FramesSpec",
           "OutputsSpec", "Scenario", "SceneSpec", "SensorSpec", "TrajectorySpec", "build_pose_source", "build_run",
           "build_scene", "build_sensors", "build_sinks", "conversion_key", "frames_digest", "load_scenario",
           "resolve_path", "route_stops", "run_manifest", "sensor_config", "sensor_names", "shared_data_dir"]
