"""Procedural training and test data on disk: a documented, versioned layout.

    DIR/dataset.json                       format, version, DatasetConfig, label table, rigs
    DIR/<split>/<index:06d>/meta.json      world config and seed, rig, poses, cameras, timestamps,
                                           boxes
    DIR/<split>/<index:06d>/rgb_<frame>_<camera>.png     8-bit sRGB images; <frame> is the frame
                                           offset's tag (`frame_tag`: 05 for 5, m04 for -4)
    DIR/<split>/<index:06d>/frames.npz     depth_<frame>_<camera> (H, W) float16 metres along the
                                           optical axis (inf: sky), semantic_<frame>_<camera> (H, W)
                                           uint8 label ids, instance_<frame>_<camera> (H, W)
                                           int32 instance ids (0: ground and sky; each other
                                           object has its own id, a boxed one's is its box's
                                           `instance`; since version 2), cameras may
                                           differ in size
    DIR/<split>/<index:06d>/voxels.npz     fine and coarse ground-truth grids of the chunk:
                                           <level>_ijk (V, 3) int16, <level>_labels (V,) uint8,
                                           <level>_visible (V,) bool, <level>_voxel_size
    DIR/<split>/<index:06d>/lidar.npz      the ground-truth LiDAR sweep on the mesh at frame 0
                                           (POINT_DTYPE, sensor frame, raw motion distortion)
    DIR/<split>/<index:06d>/manifest.json  the sample's run manifest (`scube_sim.run_manifest`)

Frames: offset 0 is the input instant T (it defines the chunk); EVAL_OFFSETS (T+5, T+10 at 10 Hz,
the default's) are for evaluating novel views and never converter inputs; any other offset, before
T (negative, since version 3) or after, is a context instant the converter may take with T. Each
image has its own timestamp (the rig's firing offsets) and camera-to-world pose.
The chunk frame is the ego frame at T (see `groundtruth`); `meta.json` holds chunk_to_world.

Samples are written by the `worlds` batch job (`WorldsJob`, `scube-sim batch worlds` and `worlds
generate`): each into its folder under a run manifest (manifest.json), file by file atomically and
meta.json last, so a folder with a meta.json holds a whole sample and a rerun skips complete ones
(resumable). Seeds are fixed per split: the
test split is a held-out set of worlds no training run sees.

Read samples back as plain arrays with `load_sample`, or as typed `Sample`s (Frames, LiDAR sweep,
boxes, ground truth) with the dataset adapter ``scube_sim.datasets.open_dataset("worlds", DIR)``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from PIL import Image
from pydantic import Field, field_validator

from ..atomic import atomic_path
from ..camera.frames import CameraImage, Frames
from ..camera.model import Intrinsics
from ..camera.render import render_camera
from ..camera.rig import load_rig
from ..config import COARSE_FACTOR, FINE_VOXEL_M, SCALE_FACTOR, StrictModel, json_loads, normalize_name, unique_names
from ..errors import InputError
from ..io.images import read_rgb
from ..labels import LABEL_TABLE_VERSION, LABELS, label_id
from ..lidar.config import load_lidar_config
from ..lidar.model import Lidar
from ..mesh import TriangleMesh
from ..parallel.runner import run_batch
from ..parallel.tasks import BatchError, Job, Task
from ..raytrace.tracer import Tracer
from ..run_manifest import RunManifest
from ..transforms import invert_pose, transform_points
from .generator import STYLES, WORLD_VERSION, WorldConfig, generate_world
from .groundtruth import coarsen, depth_to_points, mark_visible, voxelize_mesh
from .textures import TEXTURE_VERSION, world_albedo

DATASET_FORMAT = "scube_sim.worlds"
# 2: per-pixel instance ids (instance_<frame>_<camera> in frames.npz); a rig per sample
# (DatasetConfig.rigs, meta.json `rig`).
# 3: frame offsets before T (negative, files tagged m<k>: `frame_tag`); the stored instants in
# time order, so T (offset 0) need not be the first. A folder is written with the lowest version
# that describes it (`dataset_version`): 2 where every offset is >= 0 (the version-2 layout, byte
# for byte), 3 where one is negative (a version-2 reader would take its first instant for T).
# 4: the images show the surface detail of `textures.TEXTURE_VERSION` 2 (brick, framed and
# reflecting windows, worn asphalt, vehicles with lights and plates; versions 2 and 3 have the
# flat patterns of texture version 1). The files and their layout are those of version 3.
# Every new dataset is version 4; older ones still read, but no sample is added to them.
DATASET_VERSION = 4
READABLE_VERSIONS = (2, 3, 4)
SPLIT_SEED_BASE = {"train": 0, "val": 1_000_000, "test": 2_000_000}
# The evaluation instants, in frames after T: T+5 and T+10 (the paper's novel views at 10 Hz).
# Never converter inputs (`scube_sim.datasets.worlds.WorldsDataset.context_frames` leaves them
# out; the appearance stage's loss never uses them either).
EVAL_OFFSETS = (5, 10)


def frame_tag(offset: int) -> str:
    """The file-name tag of frame offset `offset`: at least two digits, ``m`` before a negative
    one's magnitude (5 -> ``05``, 10 -> ``10``, -4 -> ``m04``, -12 -> ``m12``). A tag has no
    ``_`` and reads back one way (`parse_frame_tag`); the tags of one sign sort by magnitude."""
    k = int(offset)
    return f"{k:02d}" if k >= 0 else f"m{-k:02d}"


def parse_frame_tag(tag: str) -> int:
    """The frame offset of a file-name tag (`frame_tag`'s inverse); ValueError if it is none."""
    neg = tag.startswith("m")
    digits = tag[1:] if neg else tag
    if len(digits) < 2 or not digits.isdigit() or (len(digits) > 2 and digits[0] == "0") or (neg and int(digits) == 0):
        raise ValueError(f"not a frame offset tag: {tag!r} (expected 05, 10, m04, ...)")
    return -int(digits) if neg else int(digits)


class DatasetConfig(StrictModel):
    """How samples are made. Stored in dataset.json; frozen once a converter trains on it."""

    rigs: list[str] = Field(default_factory=lambda: ["waymo-5"], min_length=1)
    image_scale: float = SCALE_FACTOR.field(0.25)
    frame_offsets: list[int] = Field(default_factory=lambda: [0, 5, 10], min_length=1)  # frames after T
    frame_rate_hz: float = Field(default=10.0, gt=0, le=1000)
    fine_voxel_m: float = FINE_VOXEL_M.field(0.1)
    coarse_factor: int = COARSE_FACTOR.field(4)
    visibility_scale: float = Field(default=0.5, gt=0, le=1)
    lidar: str = "waymo-top"
    styles: list[str] = Field(default_factory=lambda: list(STYLES))

    # a rig or style twice would weigh it twice in the samples' cycle: refused, naming it
    _rigs_once = field_validator("rigs")(classmethod(lambda cls, v: unique_names(v, key=normalize_name)))
    _styles_once = field_validator("styles")(classmethod(lambda cls, v: unique_names(v)))

    @field_validator("frame_offsets")
    @classmethod
    def _offsets_with_t(cls, v: list[int]) -> list[int]:
        # offset 0 is the converter's input instant T (it defines the chunk); negative offsets
        # are instants before it (a version-3 dataset)
        if 0 not in v or any(b <= a for a, b in zip(v, v[1:])):
            raise ValueError(f"expected strictly increasing frame offsets that include 0 (the input instant T), "
                             f"got {v}")
        return v

    @property
    def rig(self) -> str:
        """The first rig: the dataset's reference rig (dataset.json `rig`)."""
        return self.rigs[0]


def dataset_version(cfg: DatasetConfig) -> int:
    """The version a dataset of `cfg` is written with: 4, the looks of texture version 2, whatever
    the frame offsets (`cfg` is kept for the rule's history: versions 2 and 3 differed by them)."""
    return DATASET_VERSION


def _min_version(cfg: DatasetConfig) -> int:
    """The oldest version whose layout can hold `cfg`'s frame offsets (3 for instants before T)."""
    return 3 if min(cfg.frame_offsets) < 0 else 2


def sample_rig(index: int, cfg: DatasetConfig) -> str:
    """The camera rig of sample `index`: the samples cycle through `cfg.rigs`, one rig for each
    full round of styles, so that every style meets every rig."""
    return cfg.rigs[(index // len(cfg.styles)) % len(cfg.rigs)]


def sample_world_config(split: str, index: int, cfg: DatasetConfig) -> WorldConfig:
    """The world of sample `index` of `split`: seed and style fixed by the split and the index."""
    if split not in SPLIT_SEED_BASE:
        raise InputError(f"split: expected one of {', '.join(SPLIT_SEED_BASE)}, got {split!r}")
    seed = SPLIT_SEED_BASE[split] + index
    style = cfg.styles[index % len(cfg.styles)]
    duration = max(cfg.frame_offsets) / cfg.frame_rate_hz + 0.5
    first = min(cfg.frame_offsets)
    if first >= 0:  # no history: the world exactly as before version 3
        return WorldConfig(style=style, seed=seed, duration_s=duration)
    # the ego path and the actor tracks back to the first instant, and the rig's firing offsets
    return WorldConfig(style=style, seed=seed, duration_s=duration, history_s=-first / cfg.frame_rate_hz + 0.5)


# The lens's fall-off at the image corners, every rig camera (typical automotive lenses lose
# 20-40 % there; vignetting and auto exposure are what census and NCC costs are robust to and
# plain intensity differences are not).
VIGNETTING = 0.25


def camera_exposure(world_seed: int, camera_index: int, t: float) -> float:
    """The auto-exposure gain of rig camera `camera_index` at time `t` (seconds) in the world of
    `world_seed`: a gain of its own per camera (0.88-1.12) drifting slowly in time (+-3 % over
    a few seconds), deterministic. Applied to linear light, after the texture: it changes no
    surface's detail, only how bright a camera sees it."""
    rng = np.random.default_rng([int(world_seed), int(camera_index), 4242])
    gain, phase, period = rng.uniform(0.88, 1.12), rng.uniform(0, 2 * np.pi), rng.uniform(3.0, 6.0)
    return float(gain * (1.0 + 0.03 * np.sin(2 * np.pi * t / period + phase)))


class _SceneAt:
    """The static tracer (built once) plus the actors' tracer per instant (cached)."""

    def __init__(self, world):
        self.world = world
        self.static = Tracer(world.static)
        self._actors: dict[float, Tracer | None] = {}

    def __call__(self, t: float) -> list[Tracer]:
        key = round(float(t), 9)
        if key not in self._actors:
            meshes = self.world.actor_meshes_at(t)
            self._actors[key] = Tracer(TriangleMesh.concatenate(meshes)) if meshes else None
        a = self._actors[key]
        return [self.static] if a is None else [self.static, a]


def render_frames(world, rig_name: str = "waymo-5", t_ref: float = 0.0, image_scale: float | None = None,
                  scene_at: _SceneAt | None = None, ego_pose: np.ndarray | None = None,
                  camera_effects: bool = True) -> Frames:
    """The rig's camera images of `world` around `t_ref` as the datasets render them (each camera
    at its own time offset, the ego and actors where they are then; `image_scale` of the rig's
    resolution, default the datasets'), with sky masks: the converter's input. Frames' ego pose
    is the ego's at `t_ref` (the chunk frame). ego_pose: (4, 4) ego-to-world to hold the rig at
    instead of the ego's path (a route's chunk origin); the actors still move with time.
    camera_effects: each camera's exposure and vignetting as the datasets have them (False: an
    ideal camera, to measure what they cost a matcher)."""
    rig = load_rig(rig_name)
    scale = DatasetConfig().image_scale if image_scale is None else float(image_scale)
    scene_at = scene_at or _SceneAt(world)
    images = []
    for i, cam in enumerate(rig.cameras):
        intr = cam.intrinsics().scaled(scale)
        t_cam = t_ref + cam.time_offset_s
        ego = world.ego_pose_at(t_cam) if ego_pose is None else np.asarray(ego_pose, np.float64)
        pose = ego @ cam.cam_to_ego()
        r = render_camera(scene_at(t_cam), intr, pose, sun_dir=world.sun_dir, albedo_fn=world_albedo(world, t_cam),
                          exposure=camera_exposure(world.config.seed, i, t_cam) if camera_effects else 1.0,
                          vignetting=VIGNETTING if camera_effects else 0.0)
        images.append(CameraImage(cam.name, r["rgb"], intr, pose, t_cam, sky=r["sky"]))
    return Frames(images, world.ego_pose_at(t_ref) if ego_pose is None else np.asarray(ego_pose, np.float64),
                  float(t_ref),
                  {"rig": rig_name, "world": json.dumps(world.config.model_dump(mode="json"), sort_keys=True)})


def render_frames_with_context(world, rig_name: str = "waymo-5", context: int = 0,
                               image_scale: float | None = None, log: str = "", t_ref: float = 0.0,
                               ego_pose: np.ndarray | None = None) -> Frames:
    """`render_frames` at T = `t_ref` with the instants up to `context` before and after it (at
    the datasets' `frame_rate_hz`) as its `Frames.context`, as a dataset with those frame offsets
    gives them to the converter. ego_pose: (4, 4) ego-to-world to hold the reference rig at (a
    route's chunk origin); the context rigs keep that pose relative to the ego's path, moving as
    the ego moves between T and their instant (a rig driving through the chunk). Each instant
    carries the world's actor boxes (`World.boxes_at`), as a dataset stores them: the converter
    masks and measures what moved."""
    rate = DatasetConfig().frame_rate_hz
    scene_at = _SceneAt(world)
    ctx = []
    for k in [k for k in range(-int(context), int(context) + 1) if k != 0]:
        t = t_ref + k / rate
        pose = None
        if ego_pose is not None:
            pose = world.ego_pose_at(t) @ invert_pose(world.ego_pose_at(t_ref)) @ np.asarray(ego_pose, np.float64)
        f = render_frames(world, rig_name, t, image_scale, scene_at=scene_at, ego_pose=pose)
        ctx.append(Frames(f.images, f.ego_pose, f.timestamp, f.metadata, log=log, offset=k, boxes=world.boxes_at(t)))
    f = render_frames(world, rig_name, t_ref, image_scale, scene_at=scene_at, ego_pose=ego_pose)
    return Frames(f.images, f.ego_pose, f.timestamp, f.metadata, log=log, offset=0, context=ctx,
                  boxes=world.boxes_at(t_ref))


def make_sample(split: str, index: int, cfg: DatasetConfig) -> dict:
    """Generate one sample in memory: {'meta', 'images', 'frames', 'voxels', 'lidar'}."""
    wcfg = sample_world_config(split, index, cfg)
    world = generate_world(wcfg)
    rig_name = sample_rig(index, cfg)
    rig = load_rig(rig_name)
    scene_at = _SceneAt(world)
    chunk_to_world = world.ego_pose_at(0.0)
    frames_meta, images, maps = [], {}, {}
    for k in cfg.frame_offsets:
        t_ref = k / cfg.frame_rate_hz
        tag = frame_tag(k)
        cams_meta = []
        for i, cam in enumerate(rig.cameras):
            intr = cam.intrinsics().scaled(cfg.image_scale)
            t_cam = t_ref + cam.time_offset_s
            pose = world.ego_pose_at(t_cam) @ cam.cam_to_ego()
            out = render_camera(scene_at(t_cam), intr, pose, sun_dir=world.sun_dir,
                                albedo_fn=world_albedo(world, t_cam),
                                exposure=camera_exposure(world.config.seed, i, t_cam), vignetting=VIGNETTING)
            images[f"rgb_{tag}_{cam.name}.png"] = out["rgb"]
            maps[f"depth_{tag}_{cam.name}"] = out["depth"].astype(np.float16)
            maps[f"semantic_{tag}_{cam.name}"] = out["semantic"].astype(np.uint8)
            maps[f"instance_{tag}_{cam.name}"] = out["instance"].astype(np.int32)
            cams_meta.append({"name": cam.name, "intrinsics": intr.to_dict(), "cam_to_world": pose.tolist(),
                              "timestamp": t_cam})
        frames_meta.append({"offset": k, "time": t_ref, "ego_pose": world.ego_pose_at(t_ref).tolist(),
                            "cameras": cams_meta,
                            "boxes": [b.to_json() for b in world.boxes_at(t_ref)]})

    # Ground-truth voxels of the chunk, with visibility from the input cameras at T.
    mesh0 = world.mesh_at(0.0)
    fine = voxelize_mesh(mesh0, chunk_to_world, cfg.fine_voxel_m)
    to_chunk = invert_pose(chunk_to_world)
    seen = []
    for cam in rig.cameras:
        intr = cam.intrinsics().scaled(cfg.visibility_scale)
        pose = world.ego_pose_at(cam.time_offset_s) @ cam.cam_to_ego()
        vis = render_camera(scene_at(cam.time_offset_s), intr, pose, sun_dir=world.sun_dir, shading=False)
        seen.append(transform_points(to_chunk, depth_to_points(vis["depth"], intr, pose)))
    fine.visible = mark_visible(fine, np.concatenate(seen))
    coarse = coarsen(fine, cfg.coarse_factor)

    # Ground-truth LiDAR sweep over the first frame interval, on the mesh (actors at T).
    lidar = Lidar(load_lidar_config(cfg.lidar))
    period = lidar.pattern.period_s
    sweep = lidar.scan(scene_at(0.0), lidar.sensor_pose(world.ego_pose_at(0.0)),
                       lidar.sensor_pose(world.ego_pose_at(period)), t_start=0.0, seed=index)

    meta = {
        "format": DATASET_FORMAT, "version": dataset_version(cfg), "split": split, "index": index,
        "world": wcfg.model_dump(), "world_version": WORLD_VERSION, "texture_version": TEXTURE_VERSION,
        "layout": world.layout.kind,
        "rig": rig_name, "chunk_to_world": chunk_to_world.tolist(), "sun_dir": world.sun_dir.tolist(), "frames": frames_meta,
        "lidar": {"sensor": cfg.lidar, "pose_start": sweep.pose_start.tolist(), "pose_end": sweep.pose_end.tolist(),
                  "t_start": sweep.t_start, "t_end": sweep.t_end},
        "voxels": {"fine": len(fine), "coarse": len(coarse), "fine_visible_fraction": float(fine.visible.mean())},
    }
    voxels = {}
    for name, g in (("fine", fine), ("coarse", coarse)):
        voxels[f"{name}_ijk"] = g.ijk.astype(np.int16)
        voxels[f"{name}_labels"] = g.labels.astype(np.uint8)
        voxels[f"{name}_visible"] = g.visible
        voxels[f"{name}_voxel_size"] = np.float64(g.voxel_size)
    return {"meta": meta, "images": images, "frames": maps, "voxels": voxels, "lidar": sweep.points}


def _save_npz(path: Path, **arrays) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)


def _save_png(path: Path, rgb: np.ndarray) -> None:
    # No timestamps or other metadata: the same image gives the same bytes.
    with atomic_path(path) as tmp:
        Image.fromarray(rgb).save(tmp, format="PNG", optimize=False, compress_level=6)


def write_sample_files(sample: dict, folder: Path) -> Path:
    """Write a sample's files into the existing folder `folder`, each atomically and meta.json last,
    so a folder with a meta.json holds a whole sample (what the dataset adapter lists)."""
    folder = Path(folder)
    for name, rgb in sample["images"].items():
        _save_png(folder / name, rgb)
    _save_npz(folder / "frames.npz", **sample["frames"])
    _save_npz(folder / "voxels.npz", **sample["voxels"])
    _save_npz(folder / "lidar.npz", points=sample["lidar"])
    with atomic_path(folder / "meta.json") as tmp:
        Path(tmp).write_text(json.dumps(sample["meta"], indent=1, sort_keys=True))
    return folder


def write_sample(sample: dict, folder: Path) -> Path:
    """Write a sample into `folder` atomically (a temporary sibling folder, then rename)."""
    folder = Path(folder)
    tmp = folder.with_name(f".tmp-{folder.name}")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        write_sample_files(sample, tmp)
        tmp.rename(folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder


def dataset_header(cfg: DatasetConfig) -> dict:
    rig = load_rig(cfg.rig)
    return {"format": DATASET_FORMAT, "version": dataset_version(cfg), "config": cfg.model_dump(),
            "world_version": WORLD_VERSION, "texture_version": TEXTURE_VERSION,
            "label_table_version": LABEL_TABLE_VERSION, "labels": [lab.name for lab in LABELS], "rig": rig.model_dump(mode="json"),
            "rigs": [load_rig(r).model_dump(mode="json") for r in cfg.rigs],
            "split_seed_base": SPLIT_SEED_BASE}


def read_dataset_config(out: Path) -> DatasetConfig:
    """The DatasetConfig stored in an existing DIR/dataset.json (InputError naming the file if it
    is another format, a version this scube_sim does not read (READABLE_VERSIONS), or a version
    that does not match its frame offsets)."""
    head = Path(out) / "dataset.json"
    old = json_loads(head.read_text(), head, InputError)  # a key twice: refused
    if old.get("format") != DATASET_FORMAT:
        raise InputError(f"{head}: not a scube_sim worlds dataset (format {old.get('format')!r})")
    version = old.get("version")
    if version not in READABLE_VERSIONS:
        raise InputError(f"{head}: dataset version {version} is not one this scube_sim reads "
                         f"({', '.join(map(str, READABLE_VERSIONS))}); write to a new folder")
    cfg = DatasetConfig.model_validate(old["config"])
    if version < _min_version(cfg):
        raise InputError(f"{head}: dataset version {version} cannot hold frame offsets before T "
                         f"({cfg.frame_offsets}: version {_min_version(cfg)} or later)")
    return cfg


def ensure_dataset_config(out: Path, cfg: DatasetConfig | None) -> DatasetConfig:
    """The config samples in DIR are made with: a new folder gets DIR/dataset.json written from
    `cfg` (default settings if None); an existing one must match `cfg` (resuming a run), or
    gives its own when `cfg` is None."""
    out = Path(out)
    head = out / "dataset.json"
    if head.exists():
        existing = read_dataset_config(out)
        version = json_loads(head.read_text(), head, InputError).get("version")
        if version != dataset_version(existing):
            # new samples would look different from the folder's (another texture version)
            raise InputError(f"{head}: dataset version {version} was made with older textures; this scube_sim "
                             f"writes version {dataset_version(existing)}: write to a new folder")
        if cfg is not None and cfg != existing:
            raise InputError(f"{head}: the folder holds a dataset made with other settings; "
                             f"use a new folder or the same settings")
        return existing
    cfg = cfg or DatasetConfig()
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(head) as tmp:
        Path(tmp).write_text(json.dumps(dataset_header(cfg), indent=1))
    return cfg


class WorldsJob(Job):
    """The `worlds` batch job: one task per sample, `split:index` or `split:first-last` inputs,
    each written into DIR/<split>/<index:06d>/ under its run manifest (`scube_sim.batch`)."""

    name = "worlds"

    def __init__(self, cfg: DatasetConfig | None = None):
        self.cfg = cfg
        self._header: dict | None = None

    def prepare(self, out: Path) -> None:
        self.cfg = ensure_dataset_config(out, self.cfg)
        self._header = dataset_header(self.cfg)
        for stale in Path(out).glob("*/.tmp-*"):  # left by an interrupted `write_sample`
            shutil.rmtree(stale, ignore_errors=True)

    def tasks(self, inputs: list[str], out: Path) -> list[Task]:
        tasks = []
        for item in inputs:
            split, _, span = item.partition(":")
            first, _, last = span.partition("-")
            try:
                lo, hi = int(first), int(last or first)
            except ValueError:
                lo = hi = -1
            if split not in SPLIT_SEED_BASE or lo < 0 or hi < lo:
                raise BatchError(f"--inputs {item!r}: expected SPLIT:INDEX or SPLIT:FIRST-LAST with SPLIT one of "
                                 f"{', '.join(SPLIT_SEED_BASE)} and 0 <= FIRST <= LAST")
            tasks += [Task(f"{split}/{i:06d}", f"{split}:{i}", {"split": split, "index": i}) for i in range(lo, hi + 1)]
        return tasks

    def manifest(self, task: Task, out: Path) -> RunManifest:
        return RunManifest("worlds", {}, {"dataset": self._header, "split": task.params["split"],
                                          "index": task.params["index"]})

    def complete_without_manifest(self, folder: Path) -> bool:
        return (folder / "meta.json").is_file()  # written whole by an earlier scube-sim, before manifests

    def run(self, task: Task, folder: Path, out: Path) -> dict:
        write_sample_files(make_sample(task.params["split"], task.params["index"], self.cfg), folder)
        return {}

    def describe(self) -> dict:
        return {"dataset": self.cfg.model_dump(mode="json") if self.cfg else None}


def generate_dataset(out: Path, split: str, count: int, cfg: DatasetConfig | None = None, *, start: int = 0,
                     jobs: int = 1, progress: bool = True) -> dict:
    """Write samples start..start+count-1 of `split` into `out`, skipping complete ones: the
    `worlds` batch job (`scube_sim.batch`), in this process (jobs 1) or `jobs` worker processes
    (the output does not depend on it).
    Returns {'written': n, 'skipped': n, 'seconds_per_sample': wall seconds per written sample}."""
    inputs = [f"{split}:{start}-{start + count - 1}"] if count > 0 else []
    rep = run_batch(WorldsJob(cfg), inputs, out, executor="local" if jobs > 1 else "inline", workers=jobs,
                    retries=0, progress=progress)
    if rep.failed:
        first = next(r for r in rep.records.values() if r["status"] == "failed")
        raise RuntimeError(f"{out}: {rep.failed} of {rep.total} samples failed; {first['input']}: {first['error']}")
    n = rep.completed
    return {"written": n, "skipped": rep.skipped, "seconds_per_sample": rep.seconds / n if n else 0.0}


def load_sample(folder: Path) -> dict:
    """Read a sample back: meta, images (dict name -> (H, W, 3) uint8), frames, voxels, lidar."""
    folder = Path(folder)
    meta_path = folder / "meta.json"
    if not meta_path.exists():
        raise FileNotFoundError(f"{folder}: not a complete sample (no meta.json)")
    meta = json_loads(meta_path.read_text(), meta_path, InputError)  # a key twice: refused
    if meta.get("format") != DATASET_FORMAT or meta.get("version", 0) > DATASET_VERSION:
        raise InputError(f"{meta_path}: format {meta.get('format')!r} version {meta.get('version')} is not readable "
                         f"by this scube_sim ({DATASET_FORMAT} {DATASET_VERSION})")
    images = {p.name: read_rgb(p) for p in sorted(folder.glob("rgb_*.png"))}
    with np.load(folder / "frames.npz", allow_pickle=False) as z:
        frames = {k: z[k] for k in z.files}
    with np.load(folder / "voxels.npz", allow_pickle=False) as z:
        voxels = {k: z[k] for k in z.files}
    with np.load(folder / "lidar.npz", allow_pickle=False) as z:
        lidar = z["points"]
    return {"meta": meta, "images": images, "frames": frames, "voxels": voxels, "lidar": lidar}


def sample_frames(sample: dict, frame: int | None = None) -> Frames:
    """The `Frames` (the converter's camera input) of a loaded sample at one stored instant, with
    depth, semantics and sky: `frame` an index into the sample's frames (in time order), default
    the input instant T (offset 0; the first frame before version 3). The Frames' `offset` is the
    instant's frame offset and its `log` the sample (``<split>/<index:06d>``, as the adapter names it)."""
    meta = sample["meta"]
    if frame is None:
        frame = next((i for i, f in enumerate(meta["frames"]) if f["offset"] == 0), 0)
    fm = meta["frames"][frame]
    k = fm["offset"]
    tag = frame_tag(k)
    images = []
    for cam in fm["cameras"]:
        d = cam["intrinsics"]
        intr = Intrinsics(d["width"], d["height"], d["fx"], d["fy"], d["cx"], d["cy"], d["model"], tuple(d["dist"]))
        sem = sample["frames"][f"semantic_{tag}_{cam['name']}"].astype(np.int16)
        inst = sample["frames"].get(f"instance_{tag}_{cam['name']}")  # absent before version 2
        images.append(CameraImage(cam["name"], sample["images"][f"rgb_{tag}_{cam['name']}.png"], intr,
                                  np.asarray(cam["cam_to_world"]), float(cam["timestamp"]),
                                  depth=sample["frames"][f"depth_{tag}_{cam['name']}"].astype(np.float32),
                                  semantic=sem, sky=sem == label_id("sky"),
                                  instance=None if inst is None else inst.astype(np.int32)))
    return Frames(images, np.asarray(fm["ego_pose"]), float(fm["time"]),
                  {"split": meta["split"], "index": meta["index"], "frame_offset": k},
                  log=f"{meta['split']}/{int(meta['index']):06d}", offset=int(k))
