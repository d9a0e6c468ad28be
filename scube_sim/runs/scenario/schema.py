"""The scenario file's schema: what to simulate, from where, with which sensors, into which outputs.

A scenario is YAML validated by pydantic (an unknown key or a bad value names the file and the key
path). Relative paths are relative to the scenario file; a path starting with `shared:` is looked
up in the third-party data folder (SCUBE_SIM_SHARED_DATA, default `../shared/data` beside the
repository). `build_run` turns a scenario into a ready `Simulator`, its pose source and time span.

    name: lane-change
    seed: 0
    duration_s: 8              # default: the trajectory's span
    tick_hz: 10
    scene:                     # exactly one of world / voxsplat / ply / chunks / frames
      world: {style: boulevard, seed: 5, layout: straight, length_m: 200}
      representation: voxsplat # or mesh (the world's exact triangles)
      voxel_size: 0.4
    trajectory:
      source: world            # world | file | can
      edit: {lateral_offset_m: 3.4, lateral_ramp_s: [2, 5]}
    sensors:
      - {preset: hdl64e}
    effects: {noise: true, drops: true, motion_distortion: true, divergence: true}
    outputs: {files: [pcd], usd: replay.usdc}

`scene.frames` converts camera frames into the scene (`scube_sim.convert`, the converter's
profile) on first use and caches the result under -o/scene_chunks/: either `path` (a worlds sample
folder, or any adapter's folder with `dataset` and `sample`; the string shorthand `frames: PATH`)
or `world` (a generated world whose `rig` cameras are rendered at time 0, and at the `context`
instants either side of it as a log's frames would be; the world's ego path and moving actors then
drive the run, and the actors' voxels are cut out of the converted scene, `sim.converted`). With
`world` and `route: true`, a long road is converted chunk by chunk (`scene.chunk_spacing_m`
apart), each from the rig held at the chunk's origin when the ego passes it (`route_stops`), and
loaded as a `ChunkSet` within the sensors' reach (`build.py`).
"""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Literal

from pydantic import Field, field_validator, model_validator

from ...config import (
    CONTEXT_INSTANTS,
    MAX_RANGE_M,
    SAMPLE_INDEX,
    SCENE_VOXEL_M,
    SEED,
    Mount,
    StrictModel,
    laid_over,
    load_yaml,
    unique_names,
    validate_model,
)
from ...converter.profile import DEFAULT_PROFILE
from ...lidar.config import LidarConfig, config_from_dict, load_lidar_config
from ...sim.sinks.rosbag import RosbagConfig
from ...sim.sinks.viewer import ViewerConfig
from ...worlds.generator import WorldConfig


class ChunkEntry(StrictModel):
    path: str
    pose: Mount = Mount()  # chunk-to-world: metres and degrees


class FramesSpec(StrictModel):
    """scene.frames (module docstring): exactly one of `path` and `world`."""

    path: str | None = None
    dataset: str | None = None
    sample: int = SAMPLE_INDEX.field(0)
    world: WorldConfig | None = None
    rig: str = "waymo-5"
    profile: str = DEFAULT_PROFILE
    max_range_m: float | None = MAX_RANGE_M.field(None)
    route: bool = False  # world only: one conversion per chunk along the road (scene.chunk_spacing_m apart)
    # the instants before and after the sample in the same log (`convert --context`), or rendered
    # around the world's instant at its frame rate; None: the profile's own
    context: int | None = CONTEXT_INSTANTS.field(None)

    @model_validator(mode="after")
    def _one_source(self):
        if (self.path is None) == (self.world is None):
            raise ValueError("give exactly one of path (camera frames on disk) or world (frames rendered from it)")
        if self.route and self.world is None:
            raise ValueError("route: needs world (the rig is rendered at each chunk along its road)")
        return self


class SceneSpec(StrictModel):
    world: WorldConfig | None = None
    representation: Literal["voxsplat", "mesh"] = "voxsplat"
    voxel_size: float = SCENE_VOXEL_M.field(0.4)
    gaussians_per_voxel: int = Field(default=4, ge=1, le=16)
    # None: a VoxSplat file's own trace mode (metadata trace_mode; converted scenes: soft), else max_response
    depth: Literal["entry", "max_response", "soft"] | None = None
    # soft mode's alpha floor (None: the tracer's 1/255): contributions fainter than it are
    # dropped and each Gaussian's box ends where its response reaches it; on converted scenes
    # 0.1 sweeps about 1.6x faster at a lower median error and 1.7 points fewer returns
    # (docs/converter.md, bench_s2s_trade)
    soft_alpha_min: float | None = Field(default=None, gt=0, lt=1)
    chunk_spacing_m: float = Field(default=96.0, gt=10, le=102.4)
    voxsplat: str | None = None
    ply: str | None = None
    chunks: list[ChunkEntry] | None = None
    frames: FramesSpec | None = None

    @field_validator("frames", mode="before")
    @classmethod
    def _frames_path(cls, v):
        return {"path": v} if isinstance(v, str) else v  # `frames: PATH` is the path alone

    @model_validator(mode="after")
    def _one_source(self):
        given = [k for k in ("world", "voxsplat", "ply", "chunks", "frames") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"give exactly one of world, voxsplat, ply, chunks or frames (got {given or 'none'})")
        return self


class CanSpec(StrictModel):
    log: str
    dbc: str
    start_s: float = Field(default=0.0, ge=0)
    duration_s: float = Field(default=20.0, gt=0)
    realtime: bool = False
    speed: float = Field(default=1.0, gt=0)
    wheelbase_m: float | None = Field(default=None, gt=0)
    steering_ratio: float | None = Field(default=None, gt=0)


class EditSpec(StrictModel):
    lateral_offset_m: float = 0.0
    lateral_ramp_s: tuple[float, float] | None = None
    speed_scale: float = Field(default=1.0, gt=0)
    time_shift_s: float = 0.0

    @field_validator("lateral_ramp_s")
    @classmethod
    def _ramp_runs_forward(cls, v):
        if v is not None and not v[1] > v[0]:
            raise ValueError(f"expected [start, end] seconds with end > start, got {list(v)}")
        return v


class TrajectorySpec(StrictModel):
    source: Literal["world", "file", "can", "openscenario"] = "world"
    file: str | None = None
    entity: str | None = None  # openscenario: the ego's ScenarioObject (default: 'Ego' or the first)
    rate_hz: float = Field(default=10.0, gt=0, le=1000)
    can: CanSpec | None = None
    edit: EditSpec | None = None

    @model_validator(mode="after")
    def _needs(self):
        if self.source in ("file", "openscenario") and not self.file:
            raise ValueError(f"source '{self.source}' needs 'file'")
        if self.source == "can" and self.can is None:
            raise ValueError("source 'can' needs a 'can' section")
        return self


class SensorSpec(StrictModel):
    preset: str
    name: str | None = None
    rate_hz: float | None = Field(default=None, gt=0, le=1000)
    mount: Mount | None = None
    phase_s: float = 0.0
    overrides: dict = Field(default_factory=dict)


class EffectsSpec(StrictModel):
    noise: bool = True
    drops: bool = True
    motion_distortion: bool = True
    divergence: bool = True
    output: Literal["raw", "compensated"] | None = None


class CanOutputSpec(StrictModel):
    interface: str = "virtual"
    channel: str = "scube-sim"
    arbitration_id: int = Field(default=0x5F0, ge=0, le=0x1FFFFFFF)


class RosbagOutputSpec(RosbagConfig):
    """`outputs.rosbag`: a rosbag2 folder (MCAP) inside -o, and what `RosbagSink` writes."""

    folder: str = "bag"


class ViewerOutputSpec(ViewerConfig):
    """`outputs.viewer`: a Foxglove-schema MCAP file inside -o, and what `ViewerSink` writes."""

    file: str = "viewer.mcap"


class OutputsSpec(StrictModel):
    files: list[Literal["pcd", "bin", "npz", "ply", "las", "laz"]] = Field(default_factory=lambda: ["pcd"])
    usd: str | None = "replay.usdc"  # a file name inside the output folder (-o)
    rosbag: RosbagOutputSpec | None = None
    viewer: ViewerOutputSpec | None = None
    usd_clips: bool = False
    frames_per_clip: int = Field(default=100, ge=1)
    usd_scene: bool = True
    can: CanOutputSpec | None = None

    _files_once = field_validator("files")(classmethod(lambda cls, v: unique_names(v)))

    @field_validator("rosbag", mode="before")
    @classmethod
    def _bag_folder(cls, v):
        return {"folder": v} if isinstance(v, str) else v  # `rosbag: DIR` is the folder alone

    @field_validator("viewer", mode="before")
    @classmethod
    def _viewer_file(cls, v):
        return {"file": v} if isinstance(v, str) else v

    @field_validator("rosbag", "viewer")
    @classmethod
    def _bag_inside(cls, v):
        if v is not None:
            cls._inside_the_output_folder(v.folder if isinstance(v, RosbagOutputSpec) else v.file)
        return v

    @field_validator("usd")
    @classmethod
    def _inside_the_output_folder(cls, v: str | None) -> str | None:
        # Every output stays inside -o: a scenario must not write wherever a path points.
        if v is None:
            return v
        posix, win = PurePosixPath(v), PureWindowsPath(v)
        if (not v.strip() or posix.is_absolute() or win.is_absolute() or win.drive or v.startswith("~")
                or ".." in posix.parts or ".." in win.parts):
            raise ValueError(f"expected a relative path inside the output folder (-o), without '..', got {v!r}")
        return v


class Scenario(StrictModel):
    name: str
    description: str = ""
    seed: int = SEED.field(0)
    duration_s: float | None = Field(default=None, gt=0, le=86_400)  # a day at most
    tick_hz: float = Field(default=10.0, gt=0, le=1000)
    scene: SceneSpec
    trajectory: TrajectorySpec = TrajectorySpec()
    actors: Literal["world", "none"] = "world"
    sensors: list[SensorSpec] = Field(min_length=1)
    effects: EffectsSpec = EffectsSpec()
    outputs: OutputsSpec = OutputsSpec()


def shared_data_dir() -> Path:
    env = os.environ.get("SCUBE_SIM_SHARED_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[3].parent / "shared" / "data"


def resolve_path(p: str, base: Path) -> Path:
    """A scenario path: `shared:<rel>` in the third-party data folder, else relative to `base`."""
    if p.startswith("shared:"):
        return shared_data_dir() / p[len("shared:"):].lstrip("/")
    q = Path(os.path.expanduser(p))
    return q if q.is_absolute() else (base / q).resolve()


def load_scenario(path: str | Path) -> tuple[Scenario, Path]:
    """Validate a scenario file; returns it and the folder its relative paths refer to."""
    path = Path(path)
    sc = validate_model(Scenario, load_yaml(path), str(path), "scenario settings")
    return sc, path.resolve().parent


def sensor_config(spec: SensorSpec, effects: EffectsSpec, base: Path, where: str) -> LidarConfig:
    """A sensor's LiDAR config: the preset, the scenario's overrides, then the effects switches."""
    preset = str(resolve_path(spec.preset, base)) if spec.preset.endswith((".yaml", ".yml")) else spec.preset
    cfg = load_lidar_config(preset)
    data = laid_over(cfg.model_dump(mode="json"), spec.overrides)
    if not effects.noise:
        data["noise"] = {"range_sigma_m": 0.0, "range_sigma_rel": 0.0, "quantization_m": 0.0}
    if not effects.drops:
        data["drop"] = {"random_rate": 0.0, "max_incidence_deg": 90.0, "min_intensity": 0.0}
    if not effects.divergence:
        data["beam"]["samples"] = 1
    if effects.output is not None:
        data["motion"]["output"] = effects.output
    if spec.mount is not None:
        data["mount"] = spec.mount.model_dump(mode="json")
    return config_from_dict(data, f"{where} (preset {spec.preset!r} with overrides)")
