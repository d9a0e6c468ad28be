"""Per-pixel depth of the camera images against ground truth: the yardstick a depth method (today
the geometry checkpoint's monocular head; multi-view stereo next) must beat (`scube-sim eval depth`).

Ground truth per camera image: the world's rendered depth map (`CameraImage.depth`, the worlds)
where the image has one, else the sample's LiDAR sweeps projected into the camera with occluded
returns removed (`camera.depth.lidar_depth_index`; returns nearer than `MIN_RANGE_M` to their
sensor are left out: the ego body and no-returns logged at the sensor). Pixels evaluated: ground
truth finite and in (0, `MAX_DEPTH_M`) m; those beyond are counted (``gt_beyond_max``), not scored.

Ground / not ground: the image's semantic labels where it has them (`labels.GROUND_LABEL_NAMES`:
road, lane marker, curb, other ground, walkable, sidewalk, terrain), else the LiDAR returns within
`GROUND_BAND_M` of one plane fitted to the sample's returns (`ground_returns`: RANSAC over the
lower half of the returns by height along the ego's up axis, planes tilted more than
`GROUND_MAX_TILT_DEG` from it refused, deterministic draws, inliers within `RANSAC_INLIER_M`,
then a least-squares refit on the inliers: `reconstruct.ground.fit_ground_plane`). One plane: a road that bends up or
down far ahead leaves the plane and counts as not ground there.

Metrics per range band (`RANGE_BANDS_M`, of the ground-truth depth) and part (ground, not ground,
all): ``gt_pixels``, ``predicted`` (ground-truth pixels where the method gave a finite positive
depth), ``coverage`` = predicted / gt_pixels (a ground-truth pixel without a prediction is a miss
here, never dropped from the base), and over the predicted ones ``abs_rel`` (mean |p - g| / g),
``delta_1.25`` (share with max(p/g, g/p) < 1.25), ``median_abs_err_m`` (from a histogram of
|p - g| with log-spaced bins 0.12 % wide, `ERR_BINS`: to about 0.06 % of the true median, memory
bounded over any split) and ``median_rel`` (the median of |p - g| / g, exact: `np.median` of the
scored pixels' relative errors, kept in float64 with a byte of band membership and the ground
flag: about 10 bytes per scored pixel, 19 MB for 1.9 million). Per method as well: the share of
all image pixels with a depth, seconds per image (the method's call) and the process's peak
resident memory over the calls (`memory.peak_mb`, reset before each).

A method is any `DepthMethod`: ``name`` and ``__call__(frames, index) -> (H, W)`` camera-z depth in
metres of image `index` of `frames` (NaN or inf where it gives none), so a multi-view method sees
the other cameras and the frames' context instants. `depth_method(name, ...)` builds the named ones.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F

from ...camera.depth import lidar_depth_index
from ...camera.frames import CameraImage, Frames
from ...datasets.base import frames_with_context
from ...errors import InputError
from ...labels import GROUND_LABEL_NAMES, LABEL_IDS
from ...memory import peak_mb, reset_peak
from ...model.checkpoint import load_model
from ...model.geometry.net import GeometryNet
from ...reconstruct.config import StereoConfig
from ...reconstruct.ground import RANSAC_INLIER_M, fit_ground_plane
from ...reconstruct.stereo import stereo_depth
from ..frames import network_inputs
from ..profile import PAPER_PROFILE, StageProfile, load_profile

RANGE_BANDS_M = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 80.0))
MAX_DEPTH_M = RANGE_BANDS_M[-1][1]
PARTS = ("ground", "not ground", "all")
MIN_RANGE_M = 2.5
GROUND_BAND_M = 0.2
GROUND_MAX_TILT_DEG = 15.0
ERR_BINS = np.concatenate([[0.0], np.geomspace(1e-4, 1e4, 16001), [np.inf]])
METHODS = ("mono", "stereo", "fused")
DEFAULT_STEREO_CONFIDENCE = 0.5
DEFAULT_CHECKPOINT = "geometry-coarse-cpu"
GROUND_IDS = np.array([LABEL_IDS[n] for n in GROUND_LABEL_NAMES])

__all__ = ["DEFAULT_CHECKPOINT", "GROUND_BAND_M", "MAX_DEPTH_M", "METHODS", "MIN_RANGE_M", "RANGE_BANDS_M",
           "DepthMethod", "DepthScore", "FusedDepth", "MonoDepth", "StereoDepth", "depth_method", "evaluate_depth",
           "format_table", "ground_returns", "ground_truth", "json_ready"]


class DepthMethod(Protocol):
    name: str

    def __call__(self, frames: Frames, index: int) -> np.ndarray: ...


# --- methods --------------------------------------------------------------------------------------


class MonoDepth:
    """The monocular depth head of a geometry checkpoint: each feature pixel's expected depth
    under its softmax over the depth bins (sum of probability x bin centre, metres of camera z),
    sampled bilinearly at every image pixel's centre. The image meets the network as the converter
    gives it (`converter.frames.network_inputs`: resized so its focal length is `focal_px`, default the
    `cpu` profile's geometry stage's, the shipped checkpoints' training focal length)."""

    name = "mono"

    def __init__(self, checkpoint: str = DEFAULT_CHECKPOINT, focal_px: float | None = None):
        model, _ = load_model("geometry", checkpoint)
        if not isinstance(model, GeometryNet):
            raise InputError(f"{checkpoint}: not a geometry checkpoint (the mono method reads its depth head)")
        self.checkpoint = str(checkpoint)
        self.conditioner = model.conditioner.eval()
        base = load_profile(PAPER_PROFILE).geometry
        self.stage = StageProfile(checkpoint=self.checkpoint, focal_px=focal_px or base.focal_px,
                                  max_side=base.max_side)

    @torch.no_grad()
    def __call__(self, frames: Frames, index: int) -> np.ndarray:
        im = frames.images[index]
        item = network_inputs(Frames([im], frames.ego_pose, frames.timestamp, dict(frames.metadata)), self.stage)
        cond = self.conditioner
        out = cond.head(cond.encoder(item["images"]))
        probs = out[:, cond.cfg.feature_channels:].softmax(1)
        expect = (probs.double() * cond.bin_centres.double()[None, :, None, None]).sum(1, keepdim=True)
        return sample_feature_map(expect, cond.encoder.stride, tuple(int(v) for v in item["image_size"][0]),
                                  (im.intrinsics.height, im.intrinsics.width))


class StereoDepth:
    """Plane-sweep multi-view stereo (`stereo.stereo_depth`) over the other cameras and the context
    instants of the frames: its depth where its confidence is at least `min_confidence`, NaN
    elsewhere (so `eval depth`'s coverage is the confident coverage)."""

    name = "stereo"

    def __init__(self, cfg: StereoConfig | None = None, min_confidence: float = DEFAULT_STEREO_CONFIDENCE):
        self.cfg = cfg or StereoConfig()
        self.min_confidence = float(min_confidence)

    def __call__(self, frames: Frames, index: int) -> np.ndarray:
        res = stereo_depth(frames, index, self.cfg)
        return np.where(res.confidence >= self.min_confidence, res.depth, np.float32(np.nan))


class FusedDepth:
    """Stereo where it is confident, the monocular head everywhere else: one depth per pixel (the
    fallback issue 43 asks of the fused map; the head does not yet narrow the stereo's search)."""

    name = "fused"

    def __init__(self, checkpoint: str, focal_px: float | None = None, cfg: StereoConfig | None = None,
                 min_confidence: float = DEFAULT_STEREO_CONFIDENCE):
        self.mono = MonoDepth(checkpoint, focal_px)
        self.checkpoint = checkpoint
        self.cfg = cfg or StereoConfig()
        self.min_confidence = float(min_confidence)

    def __call__(self, frames: Frames, index: int) -> np.ndarray:
        res = stereo_depth(frames, index, self.cfg)
        sure = (res.confidence >= self.min_confidence) & np.isfinite(res.depth)
        return np.where(sure, res.depth, self.mono(frames, index)).astype(np.float32)


def sample_feature_map(fmap: torch.Tensor, stride: int, resized: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """(1, 1, h, w) map of a stride-`stride` feature grid over an image resized to `resized` (rows,
    columns) -> (H, W) float32 at the original image's (`size`) pixel centres, bilinear: original
    x maps to x * resized / size, and feature pixel j covers resized pixels [stride j, stride j + stride)."""
    h, w = fmap.shape[-2:]
    (rh, rw), (oh, ow) = resized, size
    xs = (torch.arange(ow, dtype=torch.float64) + 0.5) * (rw / ow)
    ys = (torch.arange(oh, dtype=torch.float64) + 0.5) * (rh / oh)
    gx, gy = 2.0 * xs / (w * stride) - 1.0, 2.0 * ys / (h * stride) - 1.0
    grid = torch.stack(torch.meshgrid(gy, gx, indexing="ij")[::-1], -1)[None]  # (1, H, W, 2) as (x, y)
    out = F.grid_sample(fmap.double(), grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, 0].float().numpy()


def depth_method(name: str, *, checkpoint: str | None = None, focal_px: float | None = None,
                 stereo: StereoConfig | None = None, min_confidence: float = DEFAULT_STEREO_CONFIDENCE) -> DepthMethod:
    """A method by name (`METHODS`): ``mono`` (`MonoDepth` of `checkpoint`, default the shipped
    coarse geometry checkpoint), ``stereo`` (`StereoDepth` with `stereo` settings, confident pixels
    only: the frames need context instants or several cameras), ``fused`` (`FusedDepth`: stereo
    where confident, the head of `checkpoint` elsewhere)."""
    if name == "mono":
        return MonoDepth(checkpoint or DEFAULT_CHECKPOINT, focal_px)
    if name == "stereo":
        return StereoDepth(stereo, min_confidence)
    if name == "fused":
        return FusedDepth(checkpoint or DEFAULT_CHECKPOINT, focal_px, stereo, min_confidence)
    raise InputError(f"depth method {name!r}: expected one of {', '.join(METHODS)}")


# --- ground truth ---------------------------------------------------------------------------------


def ground_returns(points_world: np.ndarray, up: np.ndarray, *, seed: int = 0) -> np.ndarray:
    """(N,) bool: the returns within GROUND_BAND_M of the ground plane (`reconstruct.ground.
    fit_ground_plane`: RANSAC on the lower half of the returns by height along `up`, tilt at most
    GROUND_MAX_TILT_DEG, then a least-squares refit). All False when fewer than 3 returns or no
    plane is found."""
    p = np.asarray(points_world, np.float64)
    plane = fit_ground_plane(p, up, seed=seed, max_tilt_deg=GROUND_MAX_TILT_DEG, inlier_m=RANSAC_INLIER_M)
    if plane is None:
        return np.zeros(len(p), bool)
    return np.abs(plane.distance(p)) < GROUND_BAND_M


def _lidar_points(sample) -> tuple[np.ndarray, str]:
    pts = []
    for sw in sample.sweeps:
        r = np.linalg.norm(sw.points - sw.point_origins(), axis=1)
        keep = np.isfinite(r) & (r >= MIN_RANGE_M)
        pts.append(sw.world_points()[keep])
    return (np.concatenate(pts) if pts else np.zeros((0, 3))), "+".join(sw.sensor for sw in sample.sweeps)


def ground_truth(sample, lidar_cache: dict | None = None) -> list[tuple[np.ndarray, np.ndarray, str]]:
    """Per camera image of `sample`: (depth (H, W) float32 camera-z metres, NaN/inf where none;
    ground (H, W) bool; source: 'depth map' or 'lidar'), ground from 'semantic labels' or the
    LiDAR's ground plane (module docstring)."""
    out = []
    cache = {} if lidar_cache is None else lidar_cache
    for im in sample.frames.images:
        if im.depth is not None:
            depth = np.asarray(im.depth, np.float32)
            ground = (np.isin(im.semantic, GROUND_IDS) if im.semantic is not None
                      else _lidar_ground_in_image(sample, im, cache))
            out.append((depth, ground, "depth map"))
            continue
        if not sample.sweeps:
            raise InputError(f"sample {sample.name}: camera {im.name} has no depth map and the sample no LiDAR "
                             f"sweep: no ground truth")
        pts, ground_pts = _lidar(sample, cache)
        depth, index = lidar_depth_index(pts, im)
        out.append((depth, (index >= 0) & ground_pts[np.maximum(index, 0)], "lidar"))
    return out


def _lidar(sample, cache: dict) -> tuple[np.ndarray, np.ndarray]:
    if "points" not in cache:
        pts, _ = _lidar_points(sample)
        cache["points"], cache["ground"] = pts, ground_returns(pts, sample.ego_pose[:3, 2])
    return cache["points"], cache["ground"]


def _lidar_ground_in_image(sample, im: CameraImage, cache: dict) -> np.ndarray:
    """Ground pixels of an image with a depth map but no labels: where the LiDAR's ground returns
    land (none without a sweep)."""
    if not sample.sweeps:
        return np.zeros((im.intrinsics.height, im.intrinsics.width), bool)
    pts, ground_pts = _lidar(sample, cache)
    _, index = lidar_depth_index(pts, im)
    return (index >= 0) & ground_pts[np.maximum(index, 0)]


# --- scoring --------------------------------------------------------------------------------------


class DepthScore:
    """Running sums per (band, part) over any number of images (module docstring)."""

    def __init__(self):
        self.bands = [(f"{lo:g}-{hi:g} m", lo, hi) for lo, hi in RANGE_BANDS_M] + [(f"0-{MAX_DEPTH_M:g} m", 0.0,
                                                                                      MAX_DEPTH_M)]
        keys = [(b[0], p) for b in self.bands for p in PARTS]
        self.gt = dict.fromkeys(keys, 0)
        self.pred = dict.fromkeys(keys, 0)
        self.abs_rel = dict.fromkeys(keys, 0.0)
        self.delta = dict.fromkeys(keys, 0)
        self.hist = {k: np.zeros(len(ERR_BINS) - 1, np.int64) for k in keys}
        # the scored pixels' |p - g| / g (float64), bands (bit b: self.bands[b]) and ground flags, per
        # `add` call: the exact median relative error per (band, part) at `rows`
        if len(self.bands) > 8:
            raise InputError(f"depth: {len(self.bands)} range bands; band membership is kept in one byte (8)")
        self._rel: list[np.ndarray] = []
        self._rel_bands: list[np.ndarray] = []
        self._rel_ground: list[np.ndarray] = []
        self.pixels = 0
        self.pixels_predicted = 0
        self.gt_beyond = 0

    def add(self, pred: np.ndarray, gt: np.ndarray, ground: np.ndarray) -> None:
        pred = np.asarray(pred, np.float64)
        gt = np.asarray(gt, np.float64)
        if pred.shape != gt.shape or ground.shape != gt.shape:
            raise InputError(f"depth: prediction {pred.shape}, ground truth {gt.shape} and ground mask "
                             f"{ground.shape} must have one shape")
        has = np.isfinite(pred) & (pred > 0)
        self.pixels += pred.size
        self.pixels_predicted += int(has.sum())
        valid = np.isfinite(gt) & (gt > 0)
        self.gt_beyond += int((valid & (gt >= MAX_DEPTH_M)).sum())
        valid &= gt < MAX_DEPTH_M
        scored = valid & has
        ps, gs = pred[scored], gt[scored]
        bits = np.zeros(len(gs), np.uint8)
        for b, (_, lo, hi) in enumerate(self.bands):  # the same membership test as the sums below
            bits |= ((gs >= lo) & (gs < hi)).astype(np.uint8) << b
        self._rel.append(np.abs(ps - gs) / gs)
        self._rel_bands.append(bits)
        self._rel_ground.append(np.asarray(ground, bool)[scored])
        for name, lo, hi in self.bands:
            band = valid & (gt >= lo) & (gt < hi)
            for part, mask in (("ground", band & ground), ("not ground", band & ~ground), ("all", band)):
                key = (name, part)
                self.gt[key] += int(mask.sum())
                sel = mask & has
                p, g = pred[sel], gt[sel]
                err = np.abs(p - g)
                self.pred[key] += len(p)
                self.abs_rel[key] += float((err / g).sum())
                self.delta[key] += int((np.maximum(p / g, g / p) < 1.25).sum())
                self.hist[key] += np.histogram(err, ERR_BINS)[0]

    def rows(self) -> list[dict]:
        rel = np.concatenate(self._rel) if self._rel else np.zeros(0)
        bits = np.concatenate(self._rel_bands) if self._rel_bands else np.zeros(0, np.uint8)
        on_ground = np.concatenate(self._rel_ground) if self._rel_ground else np.zeros(0, bool)
        out = []
        for b, (name, _, _) in enumerate(self.bands):
            in_band = (bits >> b) & 1 == 1
            for part in PARTS:
                key = (name, part)
                n, gt = self.pred[key], self.gt[key]
                sel = in_band & (on_ground if part == "ground" else ~on_ground if part == "not ground" else True)
                out.append({"range": name, "part": part, "gt_pixels": gt, "predicted": n,
                            "coverage": n / gt if gt else float("nan"),
                            "abs_rel": self.abs_rel[key] / n if n else float("nan"),
                            "delta_1.25": self.delta[key] / n if n else float("nan"),
                            "median_abs_err_m": _hist_median(self.hist[key]),
                            "median_rel": float(np.median(rel[sel])) if sel.any() else float("nan")})
        return out


def _hist_median(hist: np.ndarray) -> float:
    n = int(hist.sum())
    if n == 0:
        return float("nan")
    k = int(np.searchsorted(np.cumsum(hist), (n + 1) / 2))
    lo, hi = ERR_BINS[k], ERR_BINS[k + 1]
    if lo == 0.0:
        return 0.0
    return float(math.sqrt(lo * hi)) if np.isfinite(hi) else float(lo)


def evaluate_depth(ds, indices: Sequence[int], method: DepthMethod | str, *, checkpoint: str | None = None,
                   focal_px: float | None = None, progress: Callable | None = None, context: int = 0) -> dict:
    """Score `method` (a `DepthMethod`, or a name for `depth_method` with `checkpoint` and
    `focal_px`) on the camera images of samples `indices` of the dataset adapter `ds` (module
    docstring) -> a dict of plain numbers: ``rows`` (per band and part), ``coverage_all_pixels``,
    ``coverage_gt_pixels``, ``seconds_per_image``, ``peak_mb`` and provenance. context: the method
    sees up to `context` instants before and after each sample (`datasets.frames_with_context`);
    0: the sample's frames alone."""
    if isinstance(method, str):
        method = depth_method(method, checkpoint=checkpoint, focal_px=focal_px)
    indices = list(indices)
    if not indices:
        raise InputError(f"{getattr(ds, 'root', 'dataset')}: no samples to evaluate")
    score = DepthScore()
    seconds, peaks, sources, grounds, images = [], [], {}, set(), 0
    for i in (progress(indices) if progress else indices):
        sample = ds[i]
        frames = sample.frames
        if context and frames is not None and len(frames):
            frames = frames_with_context(ds, i, context)
        if frames is None or len(frames) == 0:
            raise InputError(f"{getattr(ds, 'root', 'dataset')}: sample {i} ({sample.name}) has no camera images")
        truth = ground_truth(sample)
        for k, (gt, ground, source) in enumerate(truth):
            reset_peak()
            t0 = time.perf_counter()
            pred = np.asarray(method(frames, k), np.float64)
            seconds.append(time.perf_counter() - t0)
            peaks.append(peak_mb())
            im = frames.images[k]
            if pred.shape != gt.shape:
                raise InputError(f"method {method.name}: camera {im.name}: depth {pred.shape}, expected {gt.shape}")
            score.add(pred, gt, ground)
            sources[source] = sources.get(source, 0) + 1
            grounds.add("semantic labels" if (source == "depth map" and im.semantic is not None)
                        else "LiDAR ground plane")
            images += 1
    rows = score.rows()
    extra = {"context": int(context)} if context else {}  # context 0: the result as before, key for key
    total = next(r for r in rows if r["range"] == f"0-{MAX_DEPTH_M:g} m" and r["part"] == "all")
    return {"method": method.name, "checkpoint": getattr(method, "checkpoint", None),
            "dataset": getattr(ds, "name", type(ds).__name__), "root": str(getattr(ds, "root", "")),
            "samples": len(indices), "images": images, "ground_truth": sources, "ground_rule": sorted(grounds),
            "coverage_all_pixels": score.pixels_predicted / score.pixels if score.pixels else float("nan"),
            "coverage_gt_pixels": total["coverage"], "gt_pixels": total["gt_pixels"],
            "gt_beyond_max": score.gt_beyond,
            "seconds_per_image": float(np.mean(seconds)), "seconds_per_image_max": float(np.max(seconds)),
            "peak_mb": float(np.nanmax(peaks)) if np.isfinite(peaks).any() else float("nan"), **extra, "rows": rows}


def json_ready(res):
    """`res` with NaN replaced by None (strict JSON)."""
    if isinstance(res, dict):
        return {k: json_ready(v) for k, v in res.items()}
    if isinstance(res, (list, tuple)):
        return [json_ready(v) for v in res]
    if isinstance(res, float) and not math.isfinite(res):
        return None
    return res


def format_table(res: dict) -> list[str]:
    """The result of `evaluate_depth` as lines for a terminal (and a Markdown table)."""
    gt = ", ".join(f"{v} from {k}" for k, v in res["ground_truth"].items())
    ck = f" ({res['checkpoint']})" if res.get("checkpoint") else ""
    ctx = f" with ±{res['context']} context instants" if res.get("context") else ""
    lines = [(f"method {res['method']}{ck} on {res['dataset']}{ctx}: {res['samples']} samples, {res['images']} images "
              f"({gt}); ground: {', '.join(res['ground_rule'])}"),
             (f"coverage: {100 * res['coverage_all_pixels']:.1f} % of all pixels, "
              f"{100 * res['coverage_gt_pixels']:.1f} % of the {res['gt_pixels']} ground-truth pixels under "
              f"{MAX_DEPTH_M:g} m ({res['gt_beyond_max']} beyond); {res['seconds_per_image']:.3f} s per image "
              f"(max {res['seconds_per_image_max']:.3f}), peak {res['peak_mb']:.0f} MB"),
             "| range | part | gt pixels | coverage | abs rel | δ<1.25 | median abs err (m) | median rel err |",
             "|---|---|---|---|---|---|---|---|"]

    def f(v, fmt):
        return "–" if v is None or not math.isfinite(v) else format(v, fmt)

    for r in res["rows"]:
        lines.append(f"| {r['range']} | {r['part']} | {r['gt_pixels']} | {f(100 * r['coverage'], '.1f')} % | "
                     f"{f(r['abs_rel'], '.3f')} | {f(r['delta_1.25'], '.3f')} | {f(r['median_abs_err_m'], '.2f')} | "
                     f"{f(r.get('median_rel'), '.4f')} |")
    return lines
