"""The sensor-to-sensor converter (SCube section 3): posed camera frames -> a VoxSplat.

The geometry stage (`geometry.GeometryNet`, coarse level, and where the profile names one, the
fine level conditioned on the coarse prediction: XCube's cascade) predicts semantic voxels from
the images; the appearance stage (`appearance.AppearanceNet`) puts M Gaussians in each predicted voxel
and decodes a sky panorama. A *profile* names both stages' checkpoints and their settings: the
shipped ones are `profiles/<name>.yaml` in this package (`cpu` is the default), a user's own is a
YAML file given by path (`ConverterProfile`).

Frames: the chunk frame is the frames' ego frame at their reference instant (x forward, y left,
z up, metres), as the worlds define it: ``Frames.ego_pose`` is chunk_to_world, moved down to the
road by ``Frames.metadata["ego_height_m"]`` where an adapter's ego frame is above it (KITTI's). The VoxSplat lives
in that frame (origin CHUNK_CORNER) with ``chunk_to_world`` in its metadata, as
`worlds.groundtruth.gt_voxsplat` writes the ground truth, so the simulator places both the same
way. Poses are composed in float64 before anything is cast to float32, so frames 10^6 m from the
world origin convert as they do at the origin.

Images are resized so that each camera's focal length in pixels is the one its stage was trained
at (`StageProfile.focal_px`): a depth estimate learns how large things look at a distance, in
pixels; any input resolution then meets the network at its training scale, and memory is bounded
by the field of view, not by the sensor's pixel count.
"""

from __future__ import annotations

import contextlib
import hashlib
import time
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import torch
import torch.nn.functional as F
import yaml
from pydantic import Field, ValidationError, model_validator

from ..camera.frames import Frames, chunk_to_world, ego_poses_in_chunk
from ..config import CONTEXT_INSTANTS, DDIM_STEPS, FIT_STEPS, StrictModel, format_validation_error, load_yaml
from ..datasets import open_dataset
from ..datasets.base import frames_with_context
from ..datasets.worlds import DATASET_FILE as WORLDS_HEADER
from ..datasets.worlds import META_FILE as WORLDS_SAMPLE_META
from ..errors import InputError
from ..labels import NUM_LABELS
from ..memory import check_fits, peak_mb, reset_peak
from ..transforms import invert_pose
from ..voxsplat import SCALE, VoxSplat
from ..worlds.groundtruth import CHUNK_CORNER
from .appearance.fit import fit_input_views
from .appearance.net import AppearanceNet, first_hit_voxels
from .checkpoint import load_model, resolve_checkpoint
from .data.worlds import camera_distortion, resize_bilinear, resize_nearest, scale_intrinsics
from .completion.diffusion import CompletionDiffusionNet
from .completion.features import completion_input
from .completion.merge import CompletionConfig, merge_completion
from .completion.net import CompletionNet
from .evidence import Evidence, EvidenceConfig, fusion_config, measure_evidence, scene_from_evidence
from .geometry.data import GeometryDataConfig
from .geometry.net import GeometryNet, flat_keys, observed_voxels

PROFILE_DIR = Path(__file__).resolve().parent / "profiles"
# How a converted scene is traced (metadata ``trace_mode``, which `scube-sim lidar --mode auto`
# and the demo read): its Gaussians are camera-trained blobs about half a voxel wide whose opacity
# matters; at hard opacity their 3-sigma shells are slabs metres thick.
TRACE_MODE = "soft"
# the profile `convert` and the demo use unless told: measured geometry with the learned completion
# (docs/converter.md, "The evidence profile", "The learned completion"); PAPER_PROFILE: the paper's
# route, whose networks the depth evaluation reads
DEFAULT_PROFILE = "evidence-complete"
PAPER_PROFILE = "cpu"


class StageProfile(StrictModel):
    """One stage: its checkpoint (path or shipped name) and the focal length, in pixels, each input
    image is resized to (the training images'); `max_side` caps the resized image's longer side
    (a camera with a very long focal length over a wide image)."""

    checkpoint: str
    focal_px: float = Field(gt=0, le=100_000)
    max_side: int = Field(default=1024, ge=16, le=8192)


class GeometryProfile(StageProfile):
    """sample_steps: DDIM steps (None: the checkpoint's own)."""

    sample_steps: int | None = DDIM_STEPS.field(None)


class FineProfile(StageProfile):
    """The fine geometry level, run on the coarse level's prediction (each coarse voxel
    subdivided and pruned by the fine checkpoint). output_voxel_size: the voxels handed to the
    appearance stage, metres; a multiple of the fine level's that divides the coarse level's
    (the fine voxels grouped into it: a voxel where any child is, its children's most common
    label); None: the fine level's own."""

    output_voxel_size: float | None = Field(default=None, gt=0)


class AppearanceProfile(StageProfile):
    """sky_size: (rows, columns) of the sky panorama channel. gaussians_per_voxel: keep only the
    M most opaque Gaussians of each voxel (`VoxSplat.keep_slots`; None: all the checkpoint's).
    max_scale_voxels: each Gaussian's
    standard deviations are capped at this many voxels (None: as predicted). The camera loss
    tolerates a few wide, faint Gaussians that fill background; a LiDAR tracing at hard opacity
    sees each as a wall k standard deviations out, and one around the sensor hides everything.
    fit_steps: Adam steps of a test-time fit after the network (`appearance.fit_input_views`: the
    Gaussians and the panorama fitted to the input views themselves; about 3 s per step for a
    5-camera 0.4 m grid on 2 cores; 0: the network's prediction as it is, the paper's method)."""

    sky_size: tuple[Annotated[int, Field(ge=8, le=8192)], Annotated[int, Field(ge=8, le=16384)]] = (128, 256)
    fit_steps: int = FIT_STEPS.field(0)  # a test-time fit on the input views (`appearance.fit_input_views`)
    max_scale_voxels: float | None = Field(default=1.0, gt=0, le=100)
    gaussians_per_voxel: int | None = Field(default=None, ge=1, le=64)  # keep the M most opaque (None: all)

    @model_validator(mode="after")
    def _sky_fits_in_memory(self):
        rows, cols = self.sky_size
        check_fits(rows * cols * SKY_BYTES_PER_PIXEL, f"sky_size [{rows}, {cols}] = {rows * cols:,} panorama pixels "
                   f"(~{SKY_BYTES_PER_PIXEL} bytes each while decoded)")
        return self


# The sky decoder's working memory per panorama pixel: directions (float64), sampled features,
# the decoder's layers and the colours (float32); measured order of magnitude, rounded up.
SKY_BYTES_PER_PIXEL = 384


class ConverterProfile(StrictModel):
    """A route and its settings. route `scube` (the paper's): both stages' checkpoints and
    settings (module docstring); confidence_samples: K, the geometry samples per-voxel confidence
    is counted over when a caller asks for confidence. route `evidence` (`model.evidence`: stereo
    depth fused into a grid, no learning): its `evidence` settings (default `EvidenceConfig()`),
    no checkpoints; per-voxel confidence is the fused occupancy probability whatever K; with a
    `completion` section, the completion network's checkpoint and merge (`model.completion`) fill
    what no camera saw. context: the instants before and after the sample the route reads when
    the caller names none."""

    name: str
    description: str = ""
    route: Literal["scube", "evidence"] = "scube"
    geometry: GeometryProfile | None = None
    fine: FineProfile | None = None
    appearance: AppearanceProfile | None = None
    evidence: EvidenceConfig | None = None
    completion: CompletionConfig | None = None
    context: int = CONTEXT_INSTANTS.field(0)
    confidence_samples: int = Field(default=4, ge=2, le=64)

    @model_validator(mode="after")
    def _route_keys(self):
        if self.route == "scube":
            missing = [k for k in ("geometry", "appearance") if getattr(self, k) is None]
            if missing or self.evidence is not None or self.completion is not None:
                raise ValueError(f"route scube needs geometry and appearance (missing: {', '.join(missing) or 'none'}) "
                                 f"and takes no evidence or completion key")
        else:
            given = [k for k in ("geometry", "fine", "appearance") if getattr(self, k) is not None]
            if given:
                raise ValueError(f"route evidence uses no checkpoints: remove {', '.join(given)}")
            if self.evidence is None:
                self.evidence = EvidenceConfig()
        return self


def shipped_profiles() -> list[str]:
    return sorted(p.stem for p in PROFILE_DIR.glob("*.yaml"))


def load_profile(profile: str | Path | ConverterProfile = DEFAULT_PROFILE) -> ConverterProfile:
    """A profile: a `ConverterProfile`, a YAML file's path, or a shipped profile's name."""
    if isinstance(profile, ConverterProfile):
        return profile
    path = Path(profile)
    if not path.is_file():
        if str(profile) not in shipped_profiles():
            raise InputError(f"profile {str(profile)!r}: no such file, nor a shipped profile "
                             f"(shipped: {', '.join(shipped_profiles())})")
        path = PROFILE_DIR / f"{profile}.yaml"
    try:
        data = load_yaml(path, error=InputError)  # a duplicate key: file, line and key path
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not YAML ({exc})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping of profile keys, got {type(data).__name__}")
    data.setdefault("name", path.stem)
    try:
        return ConverterProfile(**data)
    except ValidationError as exc:  # each key at fault: `p.yaml: appearance.sky_size[0]: Input should be ...`
        raise InputError(format_validation_error(exc, str(path), ConverterProfile)) from None


def open_frames(path: str | Path, dataset: str | None = None, sample: int = 0, context: int = 0) -> Frames:
    """The camera frames of one sample: `path` a worlds sample folder (DIR/<split>/NNNNNN) or, with
    `dataset`, any adapter's folder (`datasets.open_dataset`) and its sample index `sample`.
    context: with it, the frames of up to `context` instants before and after the sample in the
    same log (`datasets.frames_with_context`: the source's instants, never across a scene)."""
    if isinstance(context, bool) or not isinstance(context, (int, np.integer)) or context < 0:
        raise InputError(f"context: expected a number of instants >= 0, got {context!r}")
    path = Path(path)
    if dataset is None:
        if (path / WORLDS_SAMPLE_META).is_file() and (path.parent.parent / WORLDS_HEADER).is_file():
            ds = open_dataset("worlds", path.parent.parent, split=path.parent.name, eval_frames=False)
            names = [d.name for d in ds.sample_dirs]
            dataset, sample = "worlds", names.index(path.name)
        else:
            raise InputError(f"{path}: not a worlds sample folder (DIR/<split>/NNNNNN with {WORLDS_SAMPLE_META}); "
                             f"name the format of other folders with --dataset (nuscenes, kitti_raw, waymo, folder, "
                             f"worlds with DIR/<split> ...)")
    else:
        options = {}
        if dataset == "worlds":  # DIR/<split>
            options = {"split": path.name, "eval_frames": False}
            path = path.parent
        ds = open_dataset(dataset, path, **options)
    s = ds[sample]
    if s.frames is None or len(s.frames) == 0:
        raise InputError(f"{path}: sample {sample} ({s.name}) of the {ds.name} dataset has no camera images "
                         f"(Argoverse 2 here is LiDAR only); the converter needs posed camera frames")
    frames = frames_with_context(ds, sample, int(context)) if context else s.frames
    frames.metadata.setdefault("sample", s.name)
    frames.metadata.setdefault("dataset", ds.name)
    return frames


def context_record(frames: Frames) -> list[dict]:
    """What the converter was given over time, for a scene's metadata: one entry per instant
    (offset, timestamp, cameras), the reference's offset 0 among them."""
    return [{"offset": int(f.offset), "timestamp": float(f.timestamp), "cameras": list(f.names)}
            for f in frames.instants()]


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def frames_item(frames: Frames, stage: StageProfile, *, with_sky: bool = False) -> dict:
    """The item a stage's network reads, from `frames` (module docstring): ``images`` (N, 3, H, W)
    float32 in [0, 1], zero-padded to the largest; ``intrinsics`` (N, 3, 3) of the resized
    images; ``distortion`` (N, 5) OpenCV; ``image_size`` (N, 2) (rows, columns); ``valid`` (N, H, W)
    bool; ``cam_to_chunk`` (N, 4, 4) float32; ``chunk_to_world`` (4, 4) float64;
    ``camera_names``; and with_sky ``sky`` (N, H, W) bool from the frames' sky masks where every
    camera has one (otherwise the caller derives it)."""
    if not isinstance(frames, Frames):
        raise InputError(f"frames: expected a scube_sim.camera.Frames, got {type(frames).__name__}")
    if len(frames) == 0:
        raise InputError("frames: no images (the converter needs at least one posed camera image)")
    names = frames.names
    if len(set(names)) != len(names):
        raise InputError(f"frames: camera names must be unique, got {names}")
    to_chunk = invert_pose(chunk_to_world(frames))
    cams = []
    for im in frames.images:
        intr = im.intrinsics
        if im.image.ndim != 3 or im.image.shape[2] != 3 or im.image.dtype != np.uint8:
            raise InputError(f"camera {im.name!r}: image: expected (H, W, 3) uint8 RGB, got "
                             f"{im.image.shape} {im.image.dtype}")
        scale = stage.focal_px / float(intr.K[0, 0])
        scale = min(scale, stage.max_side / max(intr.width, intr.height))
        size = (intr.height, intr.width)
        new = (max(8, round(intr.height * scale)), max(8, round(intr.width * scale)))
        rgb = torch.from_numpy(np.array(im.image, np.uint8)).permute(2, 0, 1).to(torch.float32) / 255.0
        cam = {"images": resize_bilinear(rgb, new).clamp(0.0, 1.0),
               "intrinsics": torch.from_numpy(scale_intrinsics(intr.K, size, new).astype(np.float32)),
               "distortion": torch.from_numpy(camera_distortion(im).astype(np.float32)),
               "image_size": torch.tensor(new, dtype=torch.int64),
               # composed in float64: the world's coordinates may be large, the chunk's are small
               "cam_to_chunk": torch.from_numpy((to_chunk @ im.cam_to_world).astype(np.float32))}
        if with_sky and im.sky is not None:
            cam["sky"] = torch.from_numpy(resize_nearest(np.asarray(im.sky, bool), new))
        cams.append(cam)
    h = max(int(c["image_size"][0]) for c in cams)
    w = max(int(c["image_size"][1]) for c in cams)
    n = len(cams)
    item = {"images": torch.zeros(n, 3, h, w), "valid": torch.zeros(n, h, w, dtype=torch.bool),
            "camera_names": names, "chunk_to_world": torch.from_numpy(chunk_to_world(frames)),
            "sample": str(frames.metadata.get("sample", frames.metadata.get("name", "frames")))}
    for key in ("intrinsics", "distortion", "image_size", "cam_to_chunk"):
        item[key] = torch.stack([c[key] for c in cams])
    for i, c in enumerate(cams):
        ch, cw = (int(v) for v in c["image_size"])
        item["images"][i, :, :ch, :cw] = c["images"]
        item["valid"][i, :ch, :cw] = True
    if with_sky and all("sky" in c for c in cams):
        item["sky"] = torch.zeros(n, h, w, dtype=torch.bool)
        for i, c in enumerate(cams):
            ch, cw = (int(v) for v in c["image_size"])
            item["sky"][i, :ch, :cw] = c["sky"]
    return item


class Converter:
    """Both stages of a profile, loaded once; `convert` turns frames into a VoxSplat."""

    def __init__(self, profile: str | Path | ConverterProfile = DEFAULT_PROFILE):
        self.profile = load_profile(profile)
        p = self.profile
        self._hashes: dict[str, str] = {}
        self.timings: dict[str, float] = {}
        if p.route == "evidence":  # no weights to load, but the completion's
            self._paths, self.geometry, self.fine, self.appearance = {}, None, None, None
            self.completion = self.uncompleted = self.completion_grid = None
            if p.completion is not None:
                self._paths["completion"] = resolve_checkpoint(p.completion.checkpoint)
                self.completion, run = load_model("completion", self._paths["completion"])
                if not isinstance(self.completion, (CompletionNet, CompletionDiffusionNet)):
                    raise InputError(f"{self._paths['completion']}: not a completion checkpoint")
                self.completion_voxel_size = float(run.data.get("voxel_size", 0.8))
            return
        self._paths = {"geometry": resolve_checkpoint(p.geometry.checkpoint),
                       "appearance": resolve_checkpoint(p.appearance.checkpoint)}
        self.geometry, run = load_model("geometry", self._paths["geometry"])
        if not isinstance(self.geometry, GeometryNet) or self.geometry.cfg.level != "coarse":
            raise InputError(f"{self._paths['geometry']}: the converter needs a coarse-level geometry checkpoint")
        self.data = GeometryDataConfig(**run.data)
        self.fine = None
        if p.fine is not None:
            self._paths["fine"] = resolve_checkpoint(p.fine.checkpoint)
            self.fine, frun = load_model("geometry", self._paths["fine"])
            if not isinstance(self.fine, GeometryNet) or self.fine.cfg.level != "fine":
                raise InputError(f"{self._paths['fine']}: profile key fine needs a fine-level geometry checkpoint")
            # the whole region at once, as the coarse level (a training crop is not an inference box)
            self.fine_data = GeometryDataConfig(**{**frun.data, "crop": None, "region": self.data.region})
            if abs(self.fine_data.lift_voxel_size - self.data.voxel_size) > 1e-9:
                raise InputError(f"{self._paths['fine']}: its sites are {self.fine_data.lift_voxel_size} m voxels; "
                                 f"the coarse checkpoint predicts {self.data.voxel_size} m")
            self.output_voxel_size = self._output_voxel_size(p.fine.output_voxel_size)
        self.appearance, _ = load_model("appearance", self._paths["appearance"])
        if not isinstance(self.appearance, AppearanceNet):
            raise InputError(f"{self._paths['appearance']}: not an appearance checkpoint")

    def _output_voxel_size(self, size: float | None) -> float:
        fine, coarse = self.fine_data.voxel_size, self.data.voxel_size
        if size is None:
            return float(fine)
        group, per_coarse = size / fine, coarse / size
        if abs(group - round(group)) > 1e-6 or abs(per_coarse - round(per_coarse)) > 1e-6:
            raise InputError(f"profile fine.output_voxel_size {size}: expected a multiple of the fine level's "
                             f"{fine} m that divides the coarse level's {coarse} m")
        return float(size)

    def checkpoint_hashes(self) -> dict[str, str]:
        """sha256 of each stage's checkpoint file (provenance), computed once."""
        if not self._hashes:
            self._hashes = {k: _sha256(v) for k, v in self._paths.items()}
        return self._hashes

    @torch.no_grad()
    def predict_voxels(self, frames: Frames, *, steps: int | None = None, seed: int = 0, k: int = 1):
        """The geometry stage: -> (ijk (V, 3) int64 chunk voxels from CHUNK_CORNER, labels (V,),
        confidence (V,) float32 (the share of k samples holding the voxel; 1 when k = 1),
        observed (V,) bool, voxel_size metres)."""
        item = frames_item(frames, self.profile.geometry)
        cfg = self.data
        item["lift_grid"], item["gt_grid"], item["level"] = cfg.grid(), cfg.grid(cfg.voxel_size), "coarse"
        steps = steps or self.profile.geometry.sample_steps
        # a fine level traces `observed` through its own grid: the coarse trace would be discarded
        ijk, labels, conf, observed = self.geometry.predict_with_confidence(item, k, steps, seed,
                                                                            observed=self.fine is None)
        size = float(cfg.voxel_size)
        if self.fine is not None:
            ijk, labels, conf, observed, size = self._refine(frames, ijk, labels, conf, seed)
        shift = torch.round((torch.tensor(cfg.region[:3], dtype=torch.float64) - torch.as_tensor(CHUNK_CORNER))
                            / size).to(torch.int64)
        return ijk + shift, labels, conf, observed, size

    def _refine(self, frames: Frames, ijk: torch.Tensor, labels: torch.Tensor, conf: torch.Tensor, seed: int):
        """The fine level on the coarse prediction (box voxels of the coarse grid) -> the same
        tuple as `predict_voxels` in box voxels of the output size (`FineProfile`): each voxel's
        confidence is its coarse parent's (the fine predictor draws no samples); observed is
        traced through the output grid itself (`observed_voxels`)."""
        fcfg = self.fine_data
        item = frames_item(frames, self.profile.fine)
        item["lift_grid"], item["gt_grid"], item["level"] = fcfg.grid(), fcfg.grid(fcfg.voxel_size), "fine"
        fijk, flabels = self.fine.predict(item, seed=seed, coarse=(ijk, labels))
        # every fine voxel lies in a coarse site (the decoder only subdivides): its parent's confidence
        per = round(self.data.voxel_size / fcfg.voxel_size)
        coarse_dims = self.data.grid(self.data.voxel_size).dims
        parent_keys = flat_keys(fijk // per, coarse_dims)
        keys = flat_keys(ijk, coarse_dims)
        order = torch.argsort(keys)
        pos = torch.searchsorted(keys[order], parent_keys).clamp(max=max(len(keys) - 1, 0))
        fconf = conf[order][pos] if len(keys) else torch.zeros(len(fijk))
        group = round(self.output_voxel_size / fcfg.voxel_size)
        out_grid = fcfg.grid(self.output_voxel_size)
        if group > 1:
            gkeys, inverse = torch.unique(flat_keys(fijk // group, out_grid.dims), return_inverse=True)
            g = len(gkeys)
            counts = torch.zeros(g * NUM_LABELS, dtype=torch.int64).index_add_(
                0, inverse * NUM_LABELS + flabels, torch.ones(len(flabels), dtype=torch.int64))
            flabels = counts.view(g, NUM_LABELS).argmax(1)  # ties: the lowest label id
            # children of one output voxel share their coarse parent, so any child's confidence is it
            fconf = torch.zeros(g).index_put_((inverse,), fconf)
            _, y, z = out_grid.dims
            fijk = torch.stack([gkeys // (y * z), (gkeys // z) % y, gkeys % z], 1)
        # traced through the output grid itself: its cost grows with the distance in voxels
        return fijk, flabels, fconf, observed_voxels(fijk, out_grid, item), self.output_voxel_size

    @torch.no_grad()
    def gaussians(self, frames: Frames, ijk: torch.Tensor, labels: torch.Tensor, voxel_size: float,
                  sky: bool = True, fit_steps: int | None = None, progress=None) -> VoxSplat:
        """The appearance stage on given voxels -> a VoxSplat in the chunk frame (with its sky
        panorama channel when `sky`). Sky pixels are the frames' sky masks where every camera
        has one, otherwise the pixels whose ray enters no voxel. fit_steps: test-time
        fit (default: the profile's); progress(step, total) is called after each."""
        steps = self.profile.appearance.fit_steps if fit_steps is None else fit_steps
        item = frames_item(frames, self.profile.appearance, with_sky=True)
        item.update(ijk=ijk, labels=labels, voxel_size=voxel_size)
        item["hits"] = first_hit_voxels(item, ijk, voxel_size)
        if "sky" not in item:
            n, _, h, w = item["images"].shape
            miss = (item["hits"] < 0).to(torch.float32)[:, None]
            item["sky"] = (F.interpolate(miss, scale_factor=2, mode="nearest")[:, 0, :h, :w] > 0.5) & item["valid"]
        out = self.appearance(item, sky=sky or steps > 0)  # the fit's loss composites the sky
        if steps:
            hook = None if progress is None else (lambda step, _: progress(step, steps))
            out = fit_input_views(self.appearance, out, item, steps, on_step=hook)
        scene = self.appearance.to_voxsplat(out, item, sky_size=tuple(self.profile.appearance.sky_size) if sky else None)
        cap = self.profile.appearance.max_scale_voxels
        if cap is not None:
            scale = scene.params[..., SCALE]
            scene.params[..., SCALE] = np.minimum(scale, np.float32(np.log(cap * voxel_size)))
        if self.profile.appearance.gaussians_per_voxel is not None:
            scene = scene.keep_slots(self.profile.appearance.gaussians_per_voxel)
        return scene

    @torch.no_grad()
    def convert(self, frames: Frames, *, steps: int | None = None, seed: int = 0, confidence: bool = False,
                k: int | None = None, sky: bool = True, max_range: float | None = None,
                fit_steps: int | None = None, progress=None, evidence: Evidence | None = None) -> VoxSplat:
        """Frames -> VoxSplat (chunk frame, module docstring) with labels, reflectance, the sky
        panorama (unless `sky` is False: a LiDAR-only run) and per voxel ``observed`` (an input
        camera's ray enters it first) and ``confidence``. confidence: draw K geometry samples
        (`k`, default the profile's confidence_samples) and store each voxel's share of them;
        otherwise one sample is drawn and confidence is 1. A single-step predictor's geometry
        draws no samples: its confidence is the decoder's occupancy probability either way
        (``confidence_kind`` in the metadata says which). max_range: keep only the voxels whose
        centre lies within this many metres (horizontally) of the ego origin before the
        appearance stage (a LiDAR's range: the appearance stage's cost grows with the voxels).
        fit_steps: a test-time fit of the appearance on the input views (default: the
        profile's `appearance.fit_steps`); progress(step, total) after each of its steps.
        evidence (the evidence route): these frames' `Evidence`, measured with this profile's
        settings (`model.evidence.measure_evidence`), used instead of measuring it again (several
        completions compared on one measurement); the scene is the one `convert` would build.
        Same frames and seed, same bytes."""
        if fit_steps is not None and (isinstance(fit_steps, bool) or not isinstance(fit_steps, (int, np.integer))
                                         or fit_steps < 0):
            raise InputError(f"fit_steps: expected an integer >= 0, got {fit_steps!r}")
        if max_range is not None and not (np.isfinite(max_range) and max_range > 0):
            raise InputError(f"max_range: expected a positive number of metres, got {max_range}")
        if self.profile.route == "evidence":
            return self._convert_evidence(frames, max_range, evidence)
        if evidence is not None:
            raise InputError(f"evidence: profile {self.profile.name!r} is route {self.profile.route!r}, which "
                             f"measures none")
        with _one_torch_thread():
            return self._convert_networks(frames, steps=steps, seed=seed, confidence=confidence, k=k, sky=sky,
                                          max_range=max_range, fit_steps=fit_steps, progress=progress)

    def _convert_networks(self, frames: Frames, *, steps, seed, confidence, k, sky, max_range, fit_steps,
                          progress) -> VoxSplat:
        """The paper's route (`convert`'s arguments, checked there)."""
        fit_steps = self.profile.appearance.fit_steps if fit_steps is None else int(fit_steps)
        if k is not None and k < 1:
            raise InputError(f"k: expected at least one geometry sample, got {k}")
        k = (k or self.profile.confidence_samples) if confidence else 1
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise InputError(f"seed: expected an integer >= 0, got {seed!r}")
        reset_peak()
        t0 = time.perf_counter()
        ijk, labels, conf, observed, vs = self.predict_voxels(frames, steps=steps, seed=int(seed), k=k)
        if max_range is not None:
            centres = torch.as_tensor(CHUNK_CORNER[:2]) + (ijk[:, :2].double() + 0.5) * vs
            keep = centres.norm(dim=1) <= max_range
            ijk, labels, conf, observed = ijk[keep], labels[keep], conf[keep], observed[keep]
        t1 = time.perf_counter()
        scene = self.gaussians(frames, ijk, labels, vs, sky=sky, fit_steps=fit_steps, progress=progress)
        t2 = time.perf_counter()
        self.timings = {"geometry_s": t1 - t0, "appearance_s": t2 - t1, "peak_mb": peak_mb()}
        scene.set_channel("observed", observed.numpy())
        scene.set_channel("confidence", conf.numpy().astype(np.float32))
        hashes = self.checkpoint_hashes()
        scene.metadata.update({
            "source": "scube_sim.convert",
            "profile": self.profile.name,
            "geometry_checkpoint": {"path": self.profile.geometry.checkpoint, "sha256": hashes["geometry"]},
            "appearance_checkpoint": {"path": self.profile.appearance.checkpoint, "sha256": hashes["appearance"]},
            "fine_checkpoint": (None if self.fine is None else
                                {"path": self.profile.fine.checkpoint, "sha256": hashes["fine"]}),
            "sample_steps": int(steps or self.profile.geometry.sample_steps or self.geometry.cfg.sample_steps),
            "max_range_m": None if max_range is None else float(max_range),
            "fit_steps": fit_steps,
            "seed": int(seed),
            "confidence_samples": int(k),
            "geometry_mode": self.geometry.cfg.mode,
            "trace_mode": TRACE_MODE,
            "confidence_kind": ("decoder occupancy probability" if self.geometry.cfg.mode == "predictor"
                                else f"share of {k} geometry samples"),
            "cameras": list(frames.names),
            "timestamp": float(frames.timestamp),
            "frames": {str(key): str(v) for key, v in frames.metadata.items()},
        })
        if frames.context:  # recorded only with context: a single instant's output stays as it was
            scene.metadata["instants"] = context_record(frames)
            scene.metadata["instants_used"] = "reference only (the profile's stages read one instant)"
        return scene


    def _convert_evidence(self, frames: Frames, max_range: float | None, ev: Evidence | None = None) -> VoxSplat:
        """The evidence route (`model.evidence`), with the completion where the profile names one:
        steps, seed, K, sky and fit steps do not apply. `ev`: the frames' evidence, measured before
        (stereo_s then 0)."""
        reset_peak()
        t0 = time.perf_counter()
        parts: dict[str, float] = {"stereo_s": 0.0}
        cfg = self.profile.evidence
        if ev is None:
            ev = measure_evidence(frames, invert_pose(chunk_to_world(frames)), cfg, timings=parts)
        scene = scene_from_evidence(ev, cfg)
        scene.metadata.update({"cameras": list(frames.names), "timestamp": float(frames.timestamp)})
        t1 = time.perf_counter()
        parts["fusion_s"] = t1 - t0 - parts["stereo_s"]
        completed = None
        self.uncompleted = self.completion_grid = None
        if self.completion is not None:
            self.uncompleted = scene  # the evidence alone (`eval sensor-to-sensor` scores both)
            feats = completion_input(ev, self.completion_voxel_size, min_confidence=cfg.fusion.min_confidence,
                                     pixel_stride=fusion_config(cfg).pixel_stride, max_depth_m=cfg.fusion.max_depth_m)
            sub = None
            with _one_torch_thread():
                if isinstance(self.completion, CompletionNet):
                    occ_logit, lab_logit, sub_logit = self.completion.forward_with_subcells(torch.from_numpy(feats)[None])
                    if sub_logit is not None:
                        sub = torch.sigmoid(sub_logit[0]).double().numpy()
                else:
                    occ_logit, lab_logit = self.completion(torch.from_numpy(feats)[None])
            occ = torch.sigmoid(occ_logit[0]).double().numpy()
            lab = lab_logit[0].argmax(0).numpy()
            # the coarse grid, for scoring (`eval sensor-to-sensor`): probabilities, labels, the input
            self.completion_grid = {"occupancy": occ, "labels": lab, "features": feats, "corner": ev.corner,
                                    "voxel_size": self.completion_voxel_size}
            scene, completed = merge_completion(scene, feats, occ, lab, ev.corner, self.completion_voxel_size,
                                                self.profile.completion, ego_poses=ego_poses_in_chunk(frames),
                                                subcells=sub, boxes=ev.boxes)
            parts["completion_s"] = time.perf_counter() - t1
        if max_range is not None:
            centres = scene.origin[:2] + (scene.ijk[:, :2] + 0.5) * scene.voxel_size
            scene = scene.select_voxels(np.linalg.norm(centres, axis=1) <= max_range)
        self.timings = {"geometry_s": time.perf_counter() - t0, "appearance_s": 0.0, "peak_mb": peak_mb(), **parts}
        scene.metadata.update({
            "source": "scube_sim.convert",
            "profile": self.profile.name,
            "route": "evidence",
            "max_range_m": None if max_range is None else float(max_range),
            "frames": {str(key): str(v) for key, v in frames.metadata.items()},
            "evidence": self.profile.evidence.model_dump(mode="json"),
        })
        if completed is not None:
            scene.metadata["completion"] = {**self.profile.completion.model_dump(mode="json"),
                                            "checkpoint_sha256": self.checkpoint_hashes()["completion"],
                                            "voxel_size": self.completion_voxel_size, **completed}
            scene.metadata["confidence_kind"] = ("fused occupancy probability; unobserved ground: a constant; "
                                                 "completed: the network's occupancy probability")
        if frames.context:
            scene.metadata["instants"] = context_record(frames)
            scene.metadata["instants_used"] = "all: stereo over every camera of every instant given"
        return scene


@contextlib.contextmanager
def _one_torch_thread():
    """torch on one intra-op thread for the block, restored afterwards. The networks' convolutions
    and matrix products split their sums by thread count, so their float results (1e-6 apart) and
    the file's bytes would depend on it; `convert` and a batch worker must write the same file.
    Costs about 1.4x on 2 cores (cpu profile: 1.6 s -> 2.2 s); a batch runs samples side by side."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


_CACHE: dict[str, Converter] = {}


def is_loaded(profile: str | Path | ConverterProfile) -> bool:
    """Whether `convert` already holds this profile's converter in this process."""
    return (profile.model_dump_json() if isinstance(profile, ConverterProfile) else str(profile)) in _CACHE


def convert(frames: Frames, *, profile: str | Path | ConverterProfile = DEFAULT_PROFILE, steps: int | None = None,
            seed: int = 0, confidence: bool = False, k: int | None = None, sky: bool = True,
            max_range: float | None = None, fit_steps: int | None = None) -> VoxSplat:
    """`Converter(profile).convert(frames, ...)`, with the loaded converter kept per profile name
    or path for the next call."""
    key = profile.model_dump_json() if isinstance(profile, ConverterProfile) else str(profile)
    if key not in _CACHE:
        _CACHE[key] = Converter(profile)
    return _CACHE[key].convert(frames, steps=steps, seed=seed, confidence=confidence, k=k, sky=sky,
                               max_range=max_range, fit_steps=fit_steps)


__all__ = ["Converter", "ConverterProfile", "DEFAULT_PROFILE", "FineProfile", "PAPER_PROFILE", "convert", "frames_item", "is_loaded", "load_profile",
           "open_frames", "shipped_profiles"]
