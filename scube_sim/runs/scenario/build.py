"""A validated scenario made runnable: `build_run` gives the `Simulator`, its pose source and
time span; `build_scene` the scene (a generated world, fitted or converted chunks, a file), with
the fitted and converted chunks cached in the run folder and keyed by everything that made them.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..._version import __version__
from ...atomic import atomic_path
from ...config import ConfigError, listed_twice
from ...converter.profile import ConverterProfile, load_profile
from ...errors import ScubeSimWarning
from ...lidar.config import LidarConfig
from ...raytrace.tracer import HardMode, SoftMode, Tracer, trace_mode
from ...run_manifest import RunManifest, sha256_file
from ...scene_file import load_scene
from ...sim.can import CanPoseSource, CanTrajectory
from ...sim.contracts import PoseSource
from ...sim.converted import DEFAULT_MODE, remove_boxes, scene_mode, scene_part
from ...sim.scene import ChunkSet, ChunkSpec, Part, SimScene
from ...sim.simulator import LidarSensor, Simulator
from ...sim.sinks import CanFrameSink, FileSink, RunInfo, Sink, UsdSink
from ...sim.sinks.rosbag import RosbagConfig, RosbagSink
from ...sim.sinks.viewer import ViewerConfig, ViewerSink
from ...sim.sources import EditedTrajectory, HeldPoses, TrajectorySource, track_pose_fn
from ...sim.vehicle import DeadReckoner
from ...voxsplat import VoxSplat
from ...worlds.dataset import render_frames_with_context
from ...worlds.generator import World, WorldConfig, generate_world
from ...worlds.groundtruth import chunk_frames, gt_voxsplat
from ...worlds.textures import TEXTURE_VERSION, world_albedo
from .schema import CanSpec, FramesSpec, OutputsSpec, Scenario, SceneSpec, resolve_path, sensor_config

CACHE_FOLDERS = ("scene_chunks",)  # kept by --overwrite / --resume (entries checked on use)


def run_manifest(sc: Scenario, base: Path, scenario_path: str | Path) -> RunManifest:
    """The replay's run manifest (`scube_sim.run_manifest`): the scenario file and every file it
    names, checksummed by role; as settings the validated scenario (CLI overrides applied), each
    sensor's resolved config and the package version."""
    inputs = {"scenario": Path(scenario_path)}
    spec = sc.scene
    if spec.voxsplat is not None:
        inputs["scene.voxsplat"] = resolve_path(spec.voxsplat, base)
    if spec.ply is not None:
        inputs["scene.ply"] = resolve_path(spec.ply, base)
    for i, c in enumerate(spec.chunks or []):
        inputs[f"scene.chunks[{i}]"] = resolve_path(c.path, base)
    tr = sc.trajectory
    if tr.source == "file":
        inputs["trajectory.file"] = resolve_path(tr.file, base)
    if tr.source == "can":
        inputs["trajectory.can.log"] = resolve_path(tr.can.log, base)
        inputs["trajectory.can.dbc"] = resolve_path(tr.can.dbc, base)
    configs = [sensor_config(s, sc.effects, base, f"sensors[{i}]") for i, s in enumerate(sc.sensors)]
    sensor_names(sc, configs, str(scenario_path))
    sensors = [c.model_dump(mode="json") for c in configs]
    settings = {"scenario": sc.model_dump(mode="json"), "sensors": sensors, "scube_sim": __version__}
    return RunManifest.for_inputs("replay", inputs, settings)


def build_run(sc: Scenario, base: Path, out: Path, *, progress=None, cache: Path | None = None):
    """A scenario -> (Simulator, pose source, t_start, t_end). Fits and caches VoxSplat chunks of
    procedural worlds (and converted frames) in `cache`, default `out/scene_chunks/` (reused by
    later runs with the same settings; a batch shares one per scenario file among its runs).

    The stages run in this order (the order things are read, drawn and fitted in): sensor
    configs, scene, pose source, sensors, sinks."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    configs = [sensor_config(s, sc.effects, base, f"sensors[{i}]") for i, s in enumerate(sc.sensors)]
    built = build_scene(sc, base, Path(cache) if cache is not None else out / CACHE_FOLDERS[0],
                        reach=max(c.range.max_m for c in configs), progress=progress)
    source = build_pose_source(sc, base, built.world)
    t0 = source.t_start
    t1 = min(source.t_end, t0 + sc.duration_s) if sc.duration_s else source.t_end
    if not t1 > t0:
        edit = sc.trajectory.edit
        why = (f"; trajectory.edit (time_shift_s {edit.time_shift_s:g}, speed_scale {edit.speed_scale:g}) moves it "
               f"past the end of the {sc.trajectory.source} trajectory") if edit is not None else ""
        raise ConfigError(f"trajectory: the run would simulate no time (from {t0:.3f} s to {t1:.3f} s){why}")
    sensors = build_sensors(sc, configs)
    sinks = build_sinks(sc.outputs, out)
    info = RunInfo(scene=built.file_scene, metadata={"scenario": sc.model_dump(mode="json")},
                   time_codes_per_second=100.0)
    sim = Simulator(built.scene, sensors, sinks, seed=sc.seed, run_info=info)
    return sim, source, t0, t1


@dataclass
class BuiltScene:
    """What `build_scene` makes: the simulated scene; the generated world (scene.world) or None;
    the scene object read from scene.voxsplat / scene.ply (for the USD stage) or None."""

    scene: SimScene
    world: World | None = None
    file_scene: object | None = None


def build_scene(sc: Scenario, base: Path, cache: Path, *, reach: float, progress=None) -> BuiltScene:
    """The scenario's scene: a generated world (its mesh, or VoxSplat chunks fitted along its route
    and loaded within `reach` metres of the ego, plus its actors), a VoxSplat / PLY file, or a
    list of VoxSplat chunks. Fitted and converted chunks are cached in the folder `cache`."""
    spec = sc.scene
    mode = _trace_mode(spec, DEFAULT_MODE)
    if spec.world is not None:
        world = generate_world(_world_for_run(sc, spec.world))
        static, chunks = [], None
        if spec.representation == "mesh":
            static.append(Part(Tracer(world.static), name="world"))
        else:
            chunks = ChunkSet(_world_chunks(world, spec, cache, progress), reach, mode)
        scene = SimScene(static=static, actors=_world_actors(sc, world), chunks=chunks,
                         static_boxes=world.boxes_static)
        return BuiltScene(scene, world=world)
    if spec.frames is not None:
        return _frames_scene(sc, base, cache, reach, progress)
    if spec.voxsplat is not None or spec.ply is not None:
        path = resolve_path(spec.voxsplat or spec.ply, base)
        file_scene = load_scene(path)
        if isinstance(file_scene, VoxSplat):  # placed by its chunk pose, traced in its own mode
            part = scene_part(file_scene, name=path.stem, mode=_trace_mode(spec, scene_mode(file_scene)))
        else:
            part = Part(Tracer(file_scene, mode), name=path.stem)
        return BuiltScene(SimScene(static=[part]), file_scene=file_scene)
    specs = [ChunkSpec(resolve_path(c.path, base), c.pose.matrix()) for c in spec.chunks]
    for s in specs:
        if not s.path.is_file():
            raise ConfigError(f"scene.chunks: {s.path}: no such VoxSplat file")
    return BuiltScene(SimScene(chunks=ChunkSet(specs, reach, mode)))


def _trace_mode(spec: SceneSpec, default: str) -> HardMode | SoftMode:
    """How the scene spec traces its Gaussians: its `depth` (else `default`), in soft mode with
    its `soft_alpha_min` where it names one."""
    mode = trace_mode(spec.depth or default)
    if isinstance(mode, SoftMode) and spec.soft_alpha_min is not None:
        mode = SoftMode(alpha_min=spec.soft_alpha_min)
    return mode


def _world_for_run(sc: Scenario, wcfg: WorldConfig) -> WorldConfig:
    """The world's config with its duration stretched to cover the run (plus a second)."""
    need = (sc.duration_s or wcfg.duration_s) + 1.0
    if wcfg.duration_s < need and sc.trajectory.source == "world":
        wcfg = wcfg.model_copy(update={"duration_s": need})
    return wcfg


def _world_actors(sc: Scenario, world: World) -> list[Part]:
    """The world's moving actors as instanced parts (none with `actors: none`)."""
    if sc.actors != "world":
        return []
    return [Part(Tracer(a.mesh), pose_fn=track_pose_fn(a.times, a.poses), instance=a.instance,
                 label=a.label, size=a.size, name=f"actor{a.instance}") for a in world.actors]


def _frames_scene(sc: Scenario, base: Path, folder: Path, reach: float, progress=None) -> BuiltScene:
    """scene.frames: the frames converted (cached in `folder`), the moving actors' voxels
    cut out (`sim.converted.remove_boxes`), the actors traced as instances. With `route`, one
    conversion per chunk along the world's road, loaded as a `ChunkSet`."""
    from ...converter.frames import open_frames
    from ...converter.pipeline import TRACE_MODE

    f = sc.scene.frames
    profile = load_profile(resolve_path(f.profile, base) if f.profile.endswith((".yaml", ".yml")) else f.profile)
    context = profile.context if f.context is None else f.context
    key = conversion_key(f, profile, sc.seed)
    folder.mkdir(parents=True, exist_ok=True)
    if f.world is None:
        path = resolve_path(f.path, base)
        if not path.exists():
            raise ConfigError(f"scene.frames.path: {path}: no such folder")
        frames = open_frames(path, f.dataset, f.sample, context=context)
        scene = _cached_conversion(folder / "converted", frames, key, profile, sc.seed, f.max_range_m, progress)
        part = scene_part(scene, name="converted", mode=_trace_mode(sc.scene, scene_mode(scene)))
        return BuiltScene(SimScene(static=[part]), file_scene=scene)
    world = generate_world(_world_for_run(sc, f.world))
    actors = _world_actors(sc, world)
    if not f.route:
        if progress:
            progress(f"rendering the {f.rig} cameras of the world")
        frames = render_frames_with_context(world, f.rig, context)
        scene = _cached_conversion(folder / "converted", frames, key, profile, sc.seed, f.max_range_m, progress)
        scene, removed = remove_boxes(scene, [a.box_at(float(frames.timestamp)) for a in actors])
        if progress and removed:
            progress(f"removed {removed} voxels of {len(actors)} moving actors from the converted scene")
        part = scene_part(scene, name="converted", mode=_trace_mode(sc.scene, scene_mode(scene)))
        return BuiltScene(SimScene(static=[part], actors=actors, static_boxes=world.boxes_static), world=world,
                          file_scene=scene)
    specs = []
    for i, (t, pose) in enumerate(route_stops(world, sc.scene.chunk_spacing_m)):
        if progress:
            progress(f"route chunk {i + 1}: rendering the {f.rig} cameras at {t:.1f} s")
        frames = render_frames_with_context(world, f.rig, context, t_ref=t, ego_pose=pose)
        scene = _cached_conversion(folder / f"converted_{i:03d}", frames, key, profile, sc.seed, f.max_range_m,
                                   progress)
        scene, _ = remove_boxes(scene, [a.box_at(t) for a in actors])
        cut = folder / f"converted_{i:03d}_without_actors.npz"  # derived each run from the cached one
        scene.save(cut)
        specs.append(ChunkSpec(cut, np.asarray(scene.metadata["chunk_to_world"], np.float64)))
    # the converted chunks' own trace mode (one profile made them all: the scube route soft, evidence entry)
    mode = _trace_mode(sc.scene, scene.metadata.get("trace_mode", TRACE_MODE) if specs else TRACE_MODE)
    chunks = ChunkSet(specs, reach, mode)
    return BuiltScene(SimScene(actors=actors, chunks=chunks, static_boxes=world.boxes_static), world=world)


def conversion_key(frames_spec: FramesSpec, profile: ConverterProfile, seed: int) -> dict:
    """What a cached conversion of `frames_spec` depends on besides its frames: the spec, the seed,
    the profile's values and the sha256 of every checkpoint it names (a retrained checkpoint under
    the same name converts again). The spec's context is left out where it defers to the profile's,
    so caches made before the option existed stay valid."""
    from ...model.checkpoint import resolve_checkpoint

    f = frames_spec
    return {"spec": f.model_dump(mode="json", exclude={"context"} if f.context is None else None), "seed": seed,
            "profile": profile.model_dump(mode="json"),
            "checkpoints": {stage: sha256_file(resolve_checkpoint(name))
                            for stage, name in profile.checkpoints().items()}}


def route_stops(world: World, spacing_m: float) -> list[tuple[float, np.ndarray]]:
    """(time, chunk-to-world pose) per route chunk (`worlds.groundtruth.chunk_frames`): the rig is
    held at the chunk's origin at the instant the ego passes nearest to it (the actors are where
    they are then; a chunk beyond the ego's path gets its last instant)."""
    pos = np.asarray(world.ego_poses)[:, :3, 3]
    out = []
    for pose in chunk_frames(world, spacing_m):
        i = int(np.argmin(np.linalg.norm(pos[:, :2] - pose[:2, 3], axis=1)))
        out.append((float(world.ego_times[i]), np.asarray(pose, np.float64)))
    return out


def _cached_conversion(stem: Path, frames, key: dict, profile, seed: int, max_range, progress=None) -> VoxSplat:
    """`frames` converted with `profile`, or the conversion cached at STEM.npz / STEM.json when
    its key (`key` and the frames' digest) matches and its checksum holds."""
    from ...converter.pipeline import Converter

    npz, meta_path = stem.with_suffix(".npz"), stem.with_suffix(".json")
    key = {**key, "frames": frames_digest(frames)}
    if _cache_entry_valid(npz, meta_path, key):
        return VoxSplat.load(npz)
    if progress:
        progress(f"converting {len(frames)} camera images (profile {profile.name})")
    # a scenario's sensors are LiDARs: the paper's route skips the sky (the evidence route has none)
    options = {"sky": False} if profile.route == "scube" else {}
    scene = Converter(profile).convert(frames, seed=seed, max_range=max_range, **options).scene
    scene.save(npz)
    with atomic_path(meta_path) as tmp:
        Path(tmp).write_text(json.dumps({"key": key, "sha256": sha256_file(npz)}))
    return scene


def frames_digest(frames) -> str:
    """sha256 of the frames' images, intrinsics and poses (the converter's whole input)."""
    h = hashlib.sha256()
    for im in frames.images:
        h.update(im.name.encode())
        h.update(np.ascontiguousarray(im.image).tobytes())
        h.update(np.asarray(im.intrinsics.K, np.float64).tobytes())
        h.update(np.asarray(im.intrinsics.dist or (), np.float64).tobytes())
        h.update(np.asarray(im.cam_to_world, np.float64).tobytes())
    h.update(np.asarray(frames.ego_pose, np.float64).tobytes())
    h.update(json.dumps({str(k): str(v) for k, v in frames.metadata.items()}, sort_keys=True).encode())
    for other in frames.context:  # (none: the digest of caches made before context existed)
        h.update(f"offset {other.offset}".encode())
        h.update(frames_digest(other).encode())
    return h.hexdigest()


def build_pose_source(sc: Scenario, base: Path, world: World | None) -> PoseSource:
    """The ego's path: the world's, a pose file's or dead-reckoned CAN, then the scenario's edit,
    then held still within each sweep when motion distortion is off."""
    tr = sc.trajectory
    if tr.source == "world":
        if world is None:
            raise ConfigError("trajectory.source 'world' needs scene.world")
        source = TrajectorySource(world.ego_times, world.ego_poses, "world ego path")
    elif tr.source == "file":
        source = TrajectorySource.from_file(resolve_path(tr.file, base), tr.rate_hz)
    elif tr.source == "openscenario":
        path = resolve_path(tr.file, base)
        if not path.is_file():
            raise ConfigError(f"trajectory.file: {path}: no such OpenSCENARIO file")
        source = TrajectorySource.from_openscenario(path, tr.entity)
    else:
        source = _can_source(tr.can, base, world.ego_pose_at(0.0) if world is not None else np.eye(4))
    if tr.edit is not None:
        e = tr.edit
        source = EditedTrajectory(source, lateral_offset_m=e.lateral_offset_m, lateral_ramp=e.lateral_ramp_s,
                                  speed_scale=e.speed_scale, time_shift=e.time_shift_s)
    if not sc.effects.motion_distortion:
        source = HeldPoses(source)
    return source


def sensor_names(sc: Scenario, configs: list[LidarConfig], source: str = "scenario") -> list[str]:
    """Each sensor entry's name: its `name`, else its LiDAR config's id or name (as `LidarSensor`).
    Two entries of one name (outputs are kept by sensor name) are a ConfigError naming `source`:
    `s.yaml: sensors: 'vlp16' is listed twice (at [0] and [1]); give each sensor its own name`."""
    names = [spec.name or cfg.id or cfg.name for spec, cfg in zip(sc.sensors, configs)]
    msg = listed_twice(names)
    if msg:
        raise ConfigError(f"{source}: sensors: {msg}; give each sensor its own name")
    return names


def build_sensors(sc: Scenario, configs: list[LidarConfig]) -> list[LidarSensor]:
    """One `LidarSensor` per sensor entry, from its config (`sensor_config`)."""
    return [LidarSensor.from_config(cfg, spec.name, rate_hz=spec.rate_hz, phase=spec.phase_s)
            for cfg, spec in zip(configs, sc.sensors)]


def build_sinks(outputs: OutputsSpec, out: Path) -> list[Sink]:
    """The outputs' sinks, in this order: files (under `out/frames`), USD stage, ROS 2 bag, viewer
    recording, CAN."""
    sinks = []
    if outputs.files:
        sinks.append(FileSink(out / "frames", outputs.files))
    if outputs.usd:
        sinks.append(UsdSink(out / outputs.usd, clips=outputs.usd_clips, frames_per_clip=outputs.frames_per_clip,
                             write_scene=outputs.usd_scene))
    if outputs.rosbag is not None:
        o = outputs.rosbag
        sinks.append(RosbagSink(out / o.folder, RosbagConfig(**o.model_dump(exclude={"folder"}))))
    if outputs.viewer is not None:
        o = outputs.viewer
        sinks.append(ViewerSink(out / o.file, ViewerConfig(**o.model_dump(exclude={"file"}))))
    if outputs.can is not None:
        o = outputs.can
        sinks.append(CanFrameSink(interface=o.interface, channel=o.channel, arbitration_id=o.arbitration_id))
    return sinks


def _can_source(c: CanSpec, base: Path, start_pose: np.ndarray) -> CanTrajectory:
    kw = {}
    if c.wheelbase_m is not None:
        kw["wheelbase"] = c.wheelbase_m
    if c.steering_ratio is not None:
        kw["steer_ratio"] = c.steering_ratio
    src = CanPoseSource.from_log(resolve_path(c.log, base), resolve_path(c.dbc, base),
                                 reckoner=DeadReckoner(start_pose=start_pose, **kw), start=c.start_s,
                                 stop=c.start_s + c.duration_s, realtime=c.realtime, speed=c.speed)
    return CanTrajectory(src, c.duration_s if c.realtime else min(c.duration_s, src.duration))


def _world_chunks(world: World, spec: SceneSpec, folder: Path, progress=None) -> list[ChunkSpec]:
    """Ground-truth VoxSplat chunks along the world's route, fitted once and cached on disk.

    Entry i is ``scene_chunks/chunk_<i>.npz`` and ``chunk_<i>.json`` (the settings that made it
    and the npz's sha256), both written atomically. An entry is reused when its settings match
    and its checksum holds; a corrupt one (unreadable JSON, checksum off) is rebuilt with a
    warning, not fatal."""
    folder.mkdir(parents=True, exist_ok=True)
    key = {"world": world.config.model_dump(mode="json"), "texture_version": TEXTURE_VERSION, "voxel_size": spec.voxel_size,
           "M": spec.gaussians_per_voxel, "spacing": spec.chunk_spacing_m}
    frames = chunk_frames(world, spec.chunk_spacing_m)
    specs = []
    for i, c2w in enumerate(frames):
        path = folder / f"chunk_{i:03d}.npz"
        meta_path = folder / f"chunk_{i:03d}.json"
        if not _cache_entry_valid(path, meta_path, key):
            if progress:
                progress(f"fitting VoxSplat chunk {i + 1}/{len(frames)}")
            vs = gt_voxsplat(world.static, c2w, spec.voxel_size, gaussians_per_voxel=spec.gaussians_per_voxel,
                             albedo_fn=world_albedo(world, 0.0))
            vs.save(path)
            with atomic_path(meta_path) as tmp:
                Path(tmp).write_text(json.dumps({"key": key, "sha256": sha256_file(path)}))
        specs.append(ChunkSpec(path, np.asarray(c2w)))
    return specs


def _cache_entry_valid(path: Path, meta_path: Path, key: dict) -> bool:
    """True if the chunk cache entry holds `key`'s chunk, intact; warns when it is corrupt."""
    if not (path.is_file() and meta_path.is_file()):
        return False
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        warnings.warn(f"{meta_path}: chunk cache entry unreadable; rebuilding it", ScubeSimWarning, stacklevel=3)
        return False
    if not isinstance(meta, dict) or meta.get("key") != key:
        return False  # made with other settings (or by an older version): refit, nothing is wrong
    if meta.get("sha256") != sha256_file(path):
        warnings.warn(f"{path}: chunk cache entry corrupt (checksum differs from {meta_path.name}); rebuilding it",
                      ScubeSimWarning, stacklevel=3)
        return False
    return True
