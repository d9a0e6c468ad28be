"""The paper's route (SCube section 3): posed camera frames -> a VoxSplat through two networks.

The geometry stage (`model.geometry.GeometryNet`, coarse level, and where the profile names one,
the fine level conditioned on the coarse prediction: XCube's cascade) predicts semantic voxels from
the images; the appearance stage (`model.appearance.AppearanceNet`) puts M Gaussians in each
predicted voxel and decodes a sky panorama.

Frames: the chunk frame is the frames' ego frame at their reference instant (x forward, y left,
z up, metres), as the worlds define it: ``Frames.ego_pose`` is chunk_to_world, moved down to the
road by ``Frames.metadata["ego_height_m"]`` where an adapter's ego frame is above it (KITTI's). The
VoxSplat lives in that frame (origin CHUNK_CORNER) with ``chunk_to_world`` in its metadata, as
`worlds.groundtruth.gt_voxsplat` writes the ground truth, so the simulator places both the same
way. Poses are composed in float64 before anything is cast to float32, so frames 10^6 m from the
world origin convert as they do at the origin.

Images are resized so that each camera's focal length in pixels is the one its stage was trained
at (`StageProfile.focal_px`): a depth estimate learns how large things look at a distance, in
pixels; any input resolution then meets the network at its training scale, and memory is bounded
by the field of view, not by the sensor's pixel count.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from ..camera.frames import Frames
from ..errors import InputError
from ..labels import NUM_LABELS
from ..memory import peak_mb, reset_peak
from ..model.appearance.fit import fit_input_views
from ..model.appearance.net import AppearanceNet, first_hit_voxels
from ..model.checkpoint import load_model, resolve_checkpoint
from ..model.geometry.data import GeometryDataConfig
from ..model.geometry.net import GeometryNet, flat_keys, observed_voxels
from ..voxsplat import SCALE, VoxSplat
from ..worlds.groundtruth import CHUNK_CORNER
from .conversion import Conversion, checkpoint_hashes, context_metadata, one_torch_thread
from .frames import network_inputs
from .profile import ConverterProfile

__all__ = ["TRACE_MODE", "PaperPipeline"]

# How a converted scene is traced (metadata ``trace_mode``, which `scube-sim lidar --mode auto`
# and the demo read): its Gaussians are camera-trained blobs about half a voxel wide whose opacity
# matters; at hard opacity their 3-sigma shells are slabs metres thick.
TRACE_MODE = "soft"


def _quiet(line: str) -> None:
    """A `status` that shows nothing."""


class PaperPipeline:
    """The paper's route of a profile (route `scube`): its networks loaded once."""

    OPTIONS = ("steps", "confidence", "confidence_samples", "sky", "fit_steps", "progress")

    def __init__(self, profile: ConverterProfile):
        self.profile = p = profile
        self.paths = {"geometry": resolve_checkpoint(p.geometry.checkpoint),
                       "appearance": resolve_checkpoint(p.appearance.checkpoint)}
        self.geometry, run = load_model("geometry", self.paths["geometry"])
        if not isinstance(self.geometry, GeometryNet) or self.geometry.cfg.level != "coarse":
            raise InputError(f"{self.paths['geometry']}: the converter needs a coarse-level geometry checkpoint")
        self.data = GeometryDataConfig(**run.data)
        self.fine = None
        if p.fine is not None:
            self.paths["fine"] = resolve_checkpoint(p.fine.checkpoint)
            self.fine, frun = load_model("geometry", self.paths["fine"])
            if not isinstance(self.fine, GeometryNet) or self.fine.cfg.level != "fine":
                raise InputError(f"{self.paths['fine']}: profile key fine needs a fine-level geometry checkpoint")
            # the whole region at once, as the coarse level (a training crop is not an inference box)
            self.fine_data = GeometryDataConfig(**{**frun.data, "crop": None, "region": self.data.region})
            if abs(self.fine_data.lift_voxel_size - self.data.voxel_size) > 1e-9:
                raise InputError(f"{self.paths['fine']}: its sites are {self.fine_data.lift_voxel_size} m voxels; "
                                 f"the coarse checkpoint predicts {self.data.voxel_size} m")
            self.output_voxel_size = self._output_voxel_size(p.fine.output_voxel_size)
        self.appearance, _ = load_model("appearance", self.paths["appearance"])
        if not isinstance(self.appearance, AppearanceNet):
            raise InputError(f"{self.paths['appearance']}: not an appearance checkpoint")

    def _output_voxel_size(self, size: float | None) -> float:
        fine, coarse = self.fine_data.voxel_size, self.data.voxel_size
        if size is None:
            return float(fine)
        group, per_coarse = size / fine, coarse / size
        if abs(group - round(group)) > 1e-6 or abs(per_coarse - round(per_coarse)) > 1e-6:
            raise InputError(f"profile fine.output_voxel_size {size}: expected a multiple of the fine level's "
                             f"{fine} m that divides the coarse level's {coarse} m")
        return float(size)

    @torch.no_grad()
    def predict_voxels(self, frames: Frames, *, steps: int | None = None, seed: int = 0, samples: int = 1):
        """The geometry stage: -> (ijk (V, 3) int64 chunk voxels from CHUNK_CORNER, labels (V,),
        confidence (V,) float32 (the share of `samples` draws holding the voxel; 1 for one draw),
        observed (V,) bool, voxel_size metres)."""
        item = network_inputs(frames, self.profile.geometry)
        cfg = self.data
        item["lift_grid"], item["gt_grid"], item["level"] = cfg.grid(), cfg.grid(cfg.voxel_size), "coarse"
        steps = steps or self.profile.geometry.sample_steps
        # a fine level traces `observed` through its own grid: the coarse trace would be discarded
        ijk, labels, conf, observed = self.geometry.predict_with_confidence(item, samples, steps, seed,
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
        item = network_inputs(frames, self.profile.fine)
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
        item = network_inputs(frames, self.profile.appearance, with_sky=True)
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
        sky_size = tuple(self.profile.appearance.sky_size) if sky else None
        scene = self.appearance.to_voxsplat(out, item, sky_size=sky_size)
        cap = self.profile.appearance.max_scale_voxels
        if cap is not None:
            scale = scene.params[..., SCALE]
            scene.params[..., SCALE] = np.minimum(scale, np.float32(np.log(cap * voxel_size)))
        if self.profile.appearance.gaussians_per_voxel is not None:
            scene = scene.keep_slots(self.profile.appearance.gaussians_per_voxel)
        return scene

    @torch.no_grad()
    def convert(self, frames: Frames, *, seed: int = 0, max_range: float | None = None, steps: int | None = None,
                confidence: bool = False, confidence_samples: int | None = None,
                sky: bool = True, fit_steps: int | None = None,
                progress=None, status: Callable[[str], None] | None = None) -> Conversion:
        """Frames -> the scene (chunk frame, module docstring) with labels, reflectance, the sky
        panorama (unless `sky` is False: a LiDAR-only run) and per voxel ``observed`` (an input
        camera's ray enters it first) and ``confidence``. confidence: draw K geometry samples
        (`confidence_samples`, default the profile's) and store each voxel's share of them;
        otherwise one sample is drawn and confidence is 1. A single-step predictor's geometry
        draws no samples: its confidence is the decoder's occupancy probability either way
        (``confidence_kind`` in the metadata says which). max_range: keep only the voxels whose
        centre lies within this many metres (horizontally) of the ego origin before the
        appearance stage (its cost grows with the voxels). steps: DDIM steps of a diffusion
        geometry (default the profile's); fit_steps: a test-time fit of the appearance on the input
        views (default the profile's `appearance.fit_steps`); progress(step, total) after each of
        its steps; status: called with one line as each stage starts. Timings: geometry_s,
        appearance_s. Same frames and seed, same bytes."""
        if fit_steps is not None and (isinstance(fit_steps, bool) or not isinstance(fit_steps, (int, np.integer))
                                         or fit_steps < 0):
            raise InputError(f"fit_steps: expected an integer >= 0, got {fit_steps!r}")
        with one_torch_thread():
            return self._convert(frames, seed=seed, max_range=max_range, steps=steps, confidence=confidence,
                                 confidence_samples=confidence_samples,
                                 sky=sky, fit_steps=fit_steps, progress=progress, status=status or _quiet)

    def _convert(self, frames: Frames, *, seed, max_range, steps, confidence, confidence_samples, sky,
                 fit_steps, progress, status) -> Conversion:
        fit_steps = self.profile.appearance.fit_steps if fit_steps is None else int(fit_steps)
        if confidence_samples is not None and confidence_samples < 1:
            raise InputError(f"confidence_samples: expected at least one geometry sample, got {confidence_samples}")
        samples = (confidence_samples or self.profile.confidence_samples) if confidence else 1
        reset_peak()
        t0 = time.perf_counter()
        status(f"geometry: {samples} sample(s) of the voxels")
        ijk, labels, conf, observed, vs = self.predict_voxels(frames, steps=steps, seed=int(seed), samples=samples)
        if max_range is not None:
            centres = torch.as_tensor(CHUNK_CORNER[:2]) + (ijk[:, :2].double() + 0.5) * vs
            keep = centres.norm(dim=1) <= max_range
            ijk, labels, conf, observed = ijk[keep], labels[keep], conf[keep], observed[keep]
        t1 = time.perf_counter()
        status(f"appearance: the Gaussians of {len(ijk)} voxels")
        scene = self.gaussians(frames, ijk, labels, vs, sky=sky, fit_steps=fit_steps, progress=progress)
        t2 = time.perf_counter()
        timings = {"geometry_s": t1 - t0, "appearance_s": t2 - t1, "peak_mb": peak_mb()}
        scene.set_channel("observed", observed.numpy())
        scene.set_channel("confidence", conf.numpy().astype(np.float32))
        hashes = checkpoint_hashes(self.paths)
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
            "confidence_samples": int(samples),
            "geometry_mode": self.geometry.cfg.mode,
            "trace_mode": TRACE_MODE,
            "confidence_kind": ("decoder occupancy probability" if self.geometry.cfg.mode == "predictor"
                                else f"share of {samples} geometry samples"),
            "cameras": list(frames.names),
            "timestamp": float(frames.timestamp),
            "frames": {str(key): str(v) for key, v in frames.metadata.items()},
        })
        scene.metadata.update(context_metadata(frames, "reference only (the profile's stages read one instant)"))
        return Conversion(scene, timings)
