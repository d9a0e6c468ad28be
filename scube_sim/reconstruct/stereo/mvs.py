"""Multi-view stereo for one reference image of a `Frames`: plane sweep over the best source views
(other cameras at the reference instant, every camera at the context instants), a robust
aggregation across sources, winner-take-all depth and a per-pixel confidence.

Steps (`stereo_depth`):
1. Images to pinhole: OpenCV-distorted images are resampled onto a pinhole camera with the same K
   (after scaling by `StereoConfig.scale`, antialiased; default 0.5: at half resolution a
   hypothesis step moves the image half as far, and the sweep costs a quarter — on held-in data,
   experiments/stereo_tune.py, confident object coverage 16 -> 38 % on the worlds (val) and
   21 -> 62 % on KITTI-360 (frames 16, 18) together with 192 hypotheses from 2 m, at a third of
   the time); fisheye references are refused.
2. Sources: `views.select_sources` (overlap and parallax per hypothesis step; no zero baselines).
3. Per source and hypothesis the `cost` (`sweep`; census by default: the best on KITTI-360 and on
   the worlds, experiments/results/stereo_costs_after.md).
4. Moving actors, where `Frames.boxes` exist: a box whose object moved between the reference
   instant and a source's instant (matched by `instance`, else `track_id`; unmatched boxes count
   as moved) is masked out of that source's cost twice: the reference pixels inside its box at the
   reference instant (those pixels use same-instant sources only), and the source pixels inside its
   box at the source's instant (the plane points landing there see the object, not the surface).
   Boxes grow by `box_margin_m`, masks by half the window (the window straddles the edge).
4b. Optional (`movers`): each such object seen by the reference (on at least `mover_min_px`
   pixels at `scale`) is swept again in its own frame: the part of the reference image around its
   box against the sources posed where their cameras stood relative to the object (for a source at
   instant t, box(T) x box(t)^-1 x camera(t); the other cameras at T as they are), the reference
   and every source masked to the pixels inside its box (the world around it moves in that frame).
   A rigid moving object is then as static as the street is in the first sweep, and stereo over the
   log's instants measures it; its pixels take that sweep's answer where it is the more confident,
   where the depth puts the pixel's point inside the box (grown by `MOVER_TOLERANCE_M`: a match
   elsewhere followed the world moving behind the object), and only confident ones (no weak
   pixels, `weak_agreement`: a background pixel inside the box's outline must not become a weak
   surface there).
   The planted car of tests/stereo/test_mvs.py (1.5 m a step against the cameras' 0.8 m): with the
   first sweep alone none of its 2080 pixels has a depth; swept in its frame over 80 % of its inner
   pixels are confident and right, 25 on its top edge 7-16 % too deep (the relative motion runs
   along that edge). The worlds' moving cars and pedestrians: `docs/converter.md`.
5. Aggregation per hypothesis: the mean of the best k of the n sources that see the pixel there,
   k = max(ceil(n / 2), min(n, 2)) (one occluded or moving source does not spoil the pixel; two
   must agree where two see it). `aggregation="penalty"`: k of all S sources, an unseen entry
   costing `UNSEEN_COST` (no pull towards hypotheses few sources see: +2 points of coverage on the
   worlds at the old settings, but it lets more of the planted moving object through: not the
   default).
5b. Semi-global aggregation (`sgm_paths` 4, the default, or 8; 0: off; `sgm.semi_global`) of that volume: on
   held-in data (worlds val 0-1, cameras FRONT, FRONT_RIGHT, SIDE_LEFT; KITTI-360 frames 16, 18)
   confident object coverage 35.1 -> 48.4 % on the worlds (0-10 m: 10.5 -> 21.3 %) and 62.3 ->
   75.4 % on KITTI-360 at delta<1.25 0.993 / 0.997, but the planted moving object without a box
   (tests/stereo/test_mvs.py) gets 78 of its 2080 pixels confidently wrong instead of 5: the
   paths carry a chance agreement of two of its three sources over a whole patch, which the
   per-source agreement no longer rejects. So with it, where two or more sources can cross-check a
   pixel, at least `min_agreement` (0.7) of them must agree (two of three is a chance match; a lone
   source keeps `lone_credit`): 10 wrong pixels, and on held-in data with every instant within ±4
   (worlds val 0-2, all cameras; KITTI-360 frames 16-19) coverage 54.9 -> 58.2 % on the worlds
   (0-10 m 30.6 -> 32.4 %) and 58.4 -> 69.6 % on KITTI-360, delta<1.25 0.995 / 0.996, for about
   2.5 s more per KITTI-360 image (`experiments/stereo_tune.py --worlds /work/data/ctx_val9`).
   With the aggregation, 128 hypotheses instead of 192 (before it, 192 had the finer depth): on
   the same held-in data coverage 58.2 -> 59.2 % (worlds) and 69.6 -> 71.1 % (KITTI-360), median
   error 20-40 m 0.25 -> 0.31 m (worlds), delta<1.25 0.994 / 0.995, a third less time.
6. Winner-take-all with the parabola (`sweep.winner_take_all`) -> depth and peak ratio.
7. Confidence = min(1, peak ratio / `peak_full`) x agreement (0 where the winner is the first or
   last hypothesis the pixel's sources see: no minimum there), agreement = the share of the usable
   sources (own cost curve not flat: range >= `FLAT_COST`) whose own cost minimum lies within
   `agreement_tolerance` hypotheses of the chosen one, over the usable ones (a lone source cannot
   be cross-checked: `lone_credit`, half, at most, and its peak ratio is measured against
   `lone_peak_full` 0.8: a source whose view is blocked matches by chance, and the aggregation makes
   such matches look peaked: 248 of 12288 pixels confidently wrong with 0.6, 0 with 0.8,
   tests/stereo/test_mvs.py; on held-in data lone pixels are 0.3 % of the confident ones on the
   worlds, 0 on KITTI-360, and 0.8 cuts their wrong ones (off by over 5 %) from 1161 to 350 for
   0.1 point of coverage). Moving objects and occlusions disagree across
   instants. `peak_full` 0.6 stays: lower values (0.35-0.5) add 5-12 points of coverage on the
   held-in data at delta<1.25 >= 0.986, but make the planted moving object without a box and a
   lone source's outliers confident (tests/stereo/test_mvs.py).
   Then the expected precision: per pixel, how far one hypothesis step at the chosen depth moves
   its point in the sources that agree (`_parallax`, root sum of squares: near a forward-driving
   camera's focus of expansion, little), and with a match good to `match_px` (a quarter pixel)
   the expected relative depth error `match_px` / parallax x step x depth; above `max_rel_error`
   (0.05) the confidence is scaled by `max_rel_error` / that. On held-in data (worlds val 0-2,
   KITTI-360 frames 16-19): KITTI-360's 20-40 m median error over all LiDAR pixels 1.18 -> 1.08 m
   for coverage 69.5 -> 68.9 % (20-40 m: 75.8 -> 65.8 %), the worlds' object coverage 59.1 -> 59.0 %;
   0.03 or 0.04 cut the 20-40 m coverage by a further 6-16 points for 0.03 m.
   Optional weak pixels (`weak_agreement`, off here; the `evidence` profile sets 0.25): where
   two or more sources can cross-check a pixel and fewer than `min_agreement` but at least
   `weak_agreement` of them agree, the confidence is capped at `weak_cap` (0.45) instead of set
   to 0. Stereo's confidence is conservative on near objects at grazing angles and on faint or
   repetitive texture (worlds test 35, SIDE_LEFT: 73 % of the pixels within 40 m lie within 5 %
   of the truth, 43 % are confident); the fusion takes such a pixel only where another image hits
   the same voxel (`FusionConfig.weak_confidence`), and gap filling (step 9) treats it as unsure.
7b. Optional coarse-to-fine (`coarse_scale`): the sweep of steps 3-7 at scale x coarse_scale,
   then at `scale` a per-pixel band of 2 `refine_steps` + 1 hypotheses within `refine_span`
   coarse steps of the coarse depth (`sweep.warp_to_reference` with depth maps), the winner
   refined by the parabola; confidence the coarse one, 0 where the fine winner lies at the band's
   ends or fewer than half of the usable sources agree within one fine step. Finer depth (worlds
   median error 0.043 / 0.096 m against 0.058 / 0.14 m at 10-20 / 20-40 m) for 30 % more time
   and a few points less coverage; not the default.
7c. Optional geometric consistency (`consistency_views` > 0): the best `consistency_views`
   sources are swept like the reference, each against every other image of the frames, and a
   reference depth keeps its confidence only where its point, projected into the source, takes
   the source's own depth there and comes back within `consistency_px` pixels and
   `consistency_rel` of its depth, in at least `consistency_agree` of the sources that can check
   it (`_consistent`). With semi-global aggregation, 2 views and 2 agreeing it rejects the planted
   moving object again (7 wrong pixels of 2080), but on the held-in data (worlds val 0-1 FRONT and
   FRONT_RIGHT, KITTI-360 frame 16) it costs more coverage than the aggregation gains (worlds 37.7
   % default, 50.3 % aggregated, 39.6 % aggregated and checked; KITTI-360 62.3 / 75.2 / 53.0 %)
   at 5 times the time: not the default.
8. Back to the original image's pixels (nearest pinhole pixel of each pixel's ray); sky
   (`CameraImage.sky`) and pixels no source sees: NaN depth, confidence 0.
9. Optional gap filling (`fill_gap_deg` > 0, `fill_gaps`): an unsure run of pixels along a row
   or a column, at most `fill_gap_deg` of view long, between two confident pixels whose depths
   agree within `fill_tolerance`, takes the depth interpolated between them (linear in inverse
   depth: a plane's depth along a line of pixels) and `fill_confidence` times the smaller of their
   confidences; where a row and a column both fill a pixel, their mean. A textureless patch of a
   wall or a car door between textured edges. Not sky, never across a depth step. On worlds test
   0-1 (10 images, object pixels within 60 m): 73.9 % confident (94.5 % of them within 5 %); 7
   degrees fill 10.8 % more at 92.5 % within 5 %. Through the evidence route (worlds test 0-9,
   HDL-64E at the input pose; seen-object rays median / p90 / returning): off 0.146 m / 7.32 m /
   86.6 %; 7 degrees 0.136 / 3.59 / 92.7 %; 14 degrees 0.134 / 2.96 / 93.7 % (all rays' p90 1.33
   -> 0.98 m), ground rays unchanged; KITTI-360 frame 3010's above-ground rays p90 2.22 -> 1.72 m,
   median 0.168 -> 0.184 m. Optionally (`fill_coplanar`) a run whose ends' depths differ is filled
   too where the line through its ends (in inverse depth along the row or column) meets the
   confident pixels `fill_coplanar` times the run's length beyond each end within `fill_tolerance`:
   a wall or a car's side seen obliquely, whose depth changes along the run; a corner or a depth
   step misses that line. Through the evidence route (held-in worlds val 0-7, references T, T-3
   and T+3, HDL-64E at the input pose; seen-object rays median / p90 / returning): 14 degrees,
   ends agreeing 0.148 m / 2.90 m / 94.8 %; 14 degrees, in line with half a run beyond 0.144 /
   2.10 / 95.8 %; 28 degrees 0.144 / 2.02 / 95.9 %; seen ground unchanged (0.30 m median) (the
   14-degree depth maps filled again by the rule; through stereo itself on the 40 held-out worlds
   0.152 / 2.59 / 94.8 % -> 0.151 / 2.43 / 94.9 %, docs/converter.md). Off by
   default here (the stereo evaluation's figures); `evidence-fast` sets 14
   degrees, ends agreeing; `evidence` and `evidence-complete` 28 degrees, `fill_coplanar` 0.5.

Depth: metres along the reference camera's optical axis. Deterministic: the bytes do not depend on
the thread count (`sweep`'s operations, a fixed summation order over sources).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from rich.progress import track

from ...boxes import Box, points_in_boxes
from ...camera.frames import CameraImage, Frames
from ...errors import InputError
from ...transforms import invert_pose
from ..config import StereoConfig
from .gaps import fill_gaps
from .movers import box_mask, crop, moved_boxes, mover_tracks
from .sgm import semi_global
from .sweep import cost_ad, cost_census, cost_ncc, inverse_depth_hypotheses, warp_to_reference, winner_take_all
from .views import SourceView, candidates, select_sources

MOVER_TOLERANCE_M = 0.1  # step 4b: how far outside its box a moving object's measured point may lie
FLAT_COST = 0.02  # a source whose own cost curve varies less than this (census: share of bits) has no say
_COST_FNS = {"ad": cost_ad, "ncc": cost_ncc, "census": cost_census}
# the cost of an uncorrelated match (census: half the bits differ; ncc: 1 - 0), `StereoConfig.unseen`
UNSEEN_COST = {"ad": 0.25, "ncc": 1.0, "census": 0.5}

__all__ = ["FLAT_COST", "StereoResult", "stereo_depth"]


@dataclass
class StereoResult:
    """depth (H, W) float32 metres of camera z, NaN where none; confidence (H, W) float32 in [0, 1];
    peak_ratio and agreement (H, W) float32, its two factors; sources: the views used, best first."""

    depth: np.ndarray
    confidence: np.ndarray
    peak_ratio: np.ndarray
    agreement: np.ndarray
    sources: list[SourceView] = field(default_factory=list)


# --- images -----------------------------------------------------------------------------------------


def _pinhole(im: CameraImage, scale: float) -> tuple[torch.Tensor, np.ndarray, torch.Tensor]:
    """The image on a pinhole camera with the K of its intrinsics scaled by `scale`: (3, h, w)
    float32 in [0, 1], K (3, 3), and (h, w) bool: the pixel's ray lands inside the original image."""
    intr = im.intrinsics.scaled(scale) if scale != 1.0 else im.intrinsics
    rgb = np.asarray(im.image)
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=2)
    img = torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))).to(torch.float32) / 255.0
    h, w = intr.height, intr.width
    if (h, w) != tuple(img.shape[-2:]):
        img = F.interpolate(img[None], size=(h, w), mode="bilinear", antialias=True, align_corners=False)[0]
    ok = torch.ones(h, w, dtype=torch.bool)
    if intr.model == "opencv" and any(intr.dist):
        v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
        xd, yd = intr.distort((u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy)
        px, py = intr.fx * xd + intr.cx, intr.fy * yd + intr.cy
        inside = np.isfinite(px) & np.isfinite(py) & (px >= 0) & (px <= w) & (py >= 0) & (py <= h)
        grid = np.stack([np.where(inside, 2 * px / w - 1, 0), np.where(inside, 2 * py / h - 1, 0)], -1)
        img = F.grid_sample(img[None], torch.from_numpy(grid).to(torch.float32)[None], mode="bilinear",
                            padding_mode="border", align_corners=False)[0]
        ok = torch.from_numpy(inside)
    return img, intr.K, ok


def _to_original(maps: list[np.ndarray], im: CameraImage, k: np.ndarray, fill: list[float]) -> list[np.ndarray]:
    """(h, w) maps on the pinhole grid of K -> (H, W) maps at the original image's pixels: each
    pixel takes the pinhole pixel its ray passes through (nearest), `fill` where that is outside."""
    intr = im.intrinsics
    h, w = maps[0].shape
    if (h, w) == (intr.height, intr.width) and not (intr.model == "opencv" and any(intr.dist)):
        return maps
    rays = intr.pixel_rays()
    x, y = rays[..., 0] / rays[..., 2], rays[..., 1] / rays[..., 2]
    col = np.floor(k[0, 0] * x + k[0, 2])
    row = np.floor(k[1, 1] * y + k[1, 2])
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    ci, ri = np.where(inside, col, 0).astype(np.int64), np.where(inside, row, 0).astype(np.int64)
    return [np.where(inside, m[ri, ci], f).astype(m.dtype) for m, f in zip(maps, fill)]


# --- moving actors ----------------------------------------------------------------------------------


def _mover_sweeps(ref: CameraImage, cands: list, boxes: dict, cfg: StereoConfig, progress: bool):
    """Step 4b: per moving boxed object (`mover_tracks`) seen by `ref` (at offset 0) on at least
    `mover_min_px` pixels at `cfg.scale`, the part of the image around it swept in the object's own
    frame: each source at another instant posed where its camera stood relative to the object then
    (box at T x box at the source's instant^-1 x camera), the other cameras at T as they are, and
    in the reference and every source only the pixels inside the object's box. Yields ((rows,
    cols) slices of the original image, [depth, confidence, peak ratio, agreement] there)."""
    intr = ref.intrinsics
    small = intr.scaled(cfg.scale)
    step = max(1, round(1.0 / cfg.scale))
    strict = cfg.model_copy(update={"weak_agreement": None})
    for at in mover_tracks(boxes, cfg):
        box = at[0]
        mask = box_mask([box], ref.cam_to_world, small.K, (small.height, small.width), cfg.box_margin_m, 0)
        if mask is None or int(mask.sum()) < cfg.mover_min_px:
            continue
        r, c = np.nonzero(mask.numpy())
        pad = cfg.window // 2 + 1  # the window straddles the object's outline
        rows = slice(max(0, (int(r.min()) - pad) * step), min(intr.height, (int(r.max()) + 1 + pad) * step))
        cols = slice(max(0, (int(c.min()) - pad) * step), min(intr.width, (int(c.max()) + 1 + pad) * step))
        here = box.box_to_world()
        posed = []
        for offset, im in cands:
            if offset == 0:
                posed.append((offset, im))
            elif offset in at:
                to_t = here @ invert_pose(at[offset].box_to_world())
                posed.append((offset, dataclasses.replace(im, cam_to_world=to_t @ im.cam_to_world)))
        part = crop(ref, rows, cols)
        # confident answers only: a background pixel inside the box's outline, whose world moves in
        # this frame, must not become a weak surface there
        out = _sweep_image(part, 0, posed, {}, strict, progress, keep=box)
        if out is None:
            continue
        depth, conf, peak, agreement, k_ref, _ = out
        maps = _to_original([depth.numpy(), conf.numpy(), peak.numpy(), agreement.numpy().astype(np.float32)], part,
                            k_ref, [math.nan, 0.0, 0.0, 0.0])
        # the object lies inside its box: a depth that puts the pixel's point elsewhere matched the
        # world moving behind it
        rays = part.intrinsics.pixel_rays()
        d = np.where(np.isfinite(maps[0]), maps[0], 0.0)[..., None]
        pts = (rays / rays[..., 2:3] * d).reshape(-1, 3) @ ref.cam_to_world[:3, :3].T + ref.cam_to_world[:3, 3]
        inside = (points_in_boxes(pts, [box], MOVER_TOLERANCE_M) >= 0).reshape(maps[0].shape)
        maps[1] = np.where(inside, maps[1], np.float32(0.0))
        yield (rows, cols), maps


# --- aggregation ------------------------------------------------------------------------------------


def _robust_mean(costs: list[torch.Tensor], unseen: float | None = None) -> torch.Tensor:
    """Sources' (D, h, w) costs (NaN: unseen) -> per entry the mean of the best k of them; NaN
    where no source sees it. unseen None: k of the n finite ones, k = max(ceil(n / 2), min(n, 2)).
    unseen a cost: k of all S sources (k = max(ceil(S / 2), min(S, 2))), a source that does not
    see the entry counting as that cost (module docstring: no bias towards hypotheses few sources
    see). Summed in sorted order (deterministic)."""
    stack = torch.stack(costs)
    finite = torch.isfinite(stack)
    n = finite.sum(0)
    if unseen is None:
        k = torch.maximum((n + 1) // 2, n.clamp(max=2))
        fill = float("inf")
    else:
        s = len(costs)
        k = torch.full_like(n, max((s + 1) // 2, min(s, 2)))
        fill = float(unseen)
    ordered = torch.where(finite, stack, torch.full_like(stack, fill)).sort(0).values
    total = torch.zeros_like(stack[0])
    for j in range(len(costs)):
        total += torch.where(j < k, ordered[j], torch.zeros_like(total))
    return torch.where(n > 0, total / k.clamp(min=1).to(total.dtype), torch.full_like(total, float("nan")))


def _unseen(cfg: StereoConfig) -> float | None:
    if cfg.aggregation == "seen":
        return None
    return UNSEEN_COST[cfg.cost] if cfg.unseen_cost is None else float(cfg.unseen_cost)


# --- the pipeline -----------------------------------------------------------------------------------


def _empty(im: CameraImage, sources: list[SourceView]) -> StereoResult:
    h, w = im.intrinsics.height, im.intrinsics.width
    zeros = np.zeros((h, w), np.float32)
    return StereoResult(np.full((h, w), np.nan, np.float32), zeros, zeros.copy(), zeros.copy(), sources)


def _prepare(ref: CameraImage, views: list[SourceView], boxes: dict, cfg: StereoConfig, scale: float,
             ref_offset: int = 0, keep: Box | None = None):
    """The reference (at instant `ref_offset`) and the sources on pinhole cameras at `scale`, with
    the moving-box masks; with `keep` (a box in the frame the views are posed in, step 4b) only the
    pixels inside it, in the reference and in every source."""
    ref_img, k_ref, ref_ok = _pinhole(ref, scale)
    hw = tuple(ref_img.shape[-2:])
    pad = cfg.window // 2
    srcs = []  # per source: image, K, reference-side mask, source-side mask (float32, 1 channel)
    outside = None
    if keep is not None:
        inside = box_mask([keep], ref.cam_to_world, k_ref, hw, cfg.box_margin_m, 0)
        outside = torch.ones(hw, dtype=torch.bool) if inside is None else ~inside
    for v in views:
        img, k_src, _ = _pinhole(v.image, scale)
        ref_mask = src_mask = None
        if keep is not None:
            ref_mask = outside
            inside = box_mask([keep], v.image.cam_to_world, k_src, tuple(img.shape[-2:]), cfg.box_margin_m, 0)
            src_mask = (torch.ones(img.shape[-2:], dtype=torch.bool) if inside is None else ~inside)[None].to(torch.float32)
        elif v.offset != ref_offset and (boxes.get(ref_offset) or boxes.get(v.offset)):
            moved_ref, moved_src = moved_boxes(boxes.get(ref_offset, []), boxes.get(v.offset, []), cfg)
            ref_mask = box_mask(moved_ref, ref.cam_to_world, k_ref, hw, cfg.box_margin_m, pad)
            src_mask = box_mask(moved_src, v.image.cam_to_world, k_src, tuple(img.shape[-2:]), cfg.box_margin_m, pad)
            src_mask = None if src_mask is None else src_mask[None].to(torch.float32)
        srcs.append((img, k_src, ref_mask, src_mask))
    return ref_img, k_ref, ref_ok, hw, srcs


def _volume(ref_img, k_ref, ref_ok, hw, srcs, views, hyps: torch.Tensor, cfg: StereoConfig, bar: str | None):
    """The aggregated cost volume (D, h, w) over hypotheses `hyps` ((D,) depths, or (D, h, w)
    per-pixel depth maps), and per source its own curve's minimum, its hypothesis and its maximum."""
    inf = torch.tensor(float("inf"))
    n_src = len(srcs)
    best = [torch.full(hw, float("inf")) for _ in range(n_src)]  # each source's own minimum ...
    arg = [torch.zeros(hw, dtype=torch.int64) for _ in range(n_src)]  # ... its hypothesis ...
    worst = [torch.full(hw, -float("inf")) for _ in range(n_src)]  # ... and its curve's maximum
    fn = _COST_FNS[cfg.cost]
    chunks = list(enumerate(hyps.split(cfg.chunk)))
    agg = []
    for c, d in (track(chunks, description=bar, transient=True) if bar else chunks):
        per = []
        for s, (img, k_src, ref_mask, src_mask) in enumerate(srcs):
            v = views[s]
            warped, valid = warp_to_reference(img, k_src, k_ref, v.ref_to_src, d, hw, chunk=cfg.chunk)
            valid &= ref_ok[None]
            if ref_mask is not None:
                valid &= ~ref_mask[None]
            if src_mask is not None:
                seen, _ = warp_to_reference(src_mask, k_src, k_ref, v.ref_to_src, d, hw, mode="nearest",
                                            chunk=cfg.chunk)
                valid &= seen[:, 0] < 0.5
            cost = fn(ref_img, warped, valid, cfg.window)
            finite = torch.isfinite(cost)
            lo = torch.where(finite, cost, inf)
            m, a = lo.min(0)
            better = m < best[s]  # strict: the first minimum over the chunks, as within one
            best[s] = torch.where(better, m, best[s])
            arg[s] = torch.where(better, a + c * cfg.chunk, arg[s])
            worst[s] = torch.maximum(worst[s], torch.where(finite, cost, -inf).max(0).values)
            per.append(cost)
        agg.append(_robust_mean(per, _unseen(cfg)))
    return torch.cat(agg), best, arg, worst


def _agreement(winner, best, arg, worst, tolerance: int, lone_credit: float = 0.5
               ) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    """(h, w) the share of the usable sources (own cost curve not flat) whose own minimum lies
    within `tolerance` hypotheses of the winner, `lone_credit` times that where one source alone is
    usable (it cannot be cross-checked); (h, w) bool, where that is so; per source (h, w) bool,
    where it is usable and agrees."""
    usable = torch.zeros(winner.shape)
    agrees = []
    for b, a, w in zip(best, arg, worst):
        ok = torch.isfinite(b) & (w - b >= FLAT_COST)
        usable += ok.to(torch.float32)
        agrees.append(ok & ((a - winner).abs() <= tolerance))
    agree = torch.zeros(winner.shape)
    for a in agrees:
        agree += a.to(torch.float32)
    share = agree / usable.clamp(min=1.0)
    lone = usable == 1
    return torch.where(lone, share * lone_credit, share), lone, agrees


def _parallax(depth: torch.Tensor, k_ref: np.ndarray, srcs, views, agreeing: list[torch.Tensor],
              inv_step: float) -> torch.Tensor:
    """(h, w) float32 pixels: how far one hypothesis step (`inv_step`, 1/m) at `depth` (h, w) moves
    the pixel's point in the sources that agree there (`agreeing`, per source (h, w) bool), combined
    as independent measurements (root sum of squares); 0 where none agrees. A source moving along
    the pixel's ray (the focus of expansion of a forward-driving camera) adds nothing."""
    h, w = depth.shape
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5,
                          indexing="ij")
    kr = torch.from_numpy(np.asarray(k_ref, np.float64))
    ray = torch.stack([(u - kr[0, 2]) / kr[0, 0], (v - kr[1, 2]) / kr[1, 1], torch.ones_like(u)], -1)
    inv = 1.0 / depth.to(torch.float64)
    ok = torch.isfinite(inv) & (inv > 0)
    inv = torch.where(ok, inv, torch.ones_like(inv))
    total = torch.zeros((h, w), dtype=torch.float64)
    for (_, k_src, _, _), view, agrees in zip(srcs, views, agreeing):
        ks = torch.from_numpy(np.asarray(k_src, np.float64))
        pose = torch.from_numpy(np.asarray(view.ref_to_src, np.float64))
        uv = []
        for i in (inv, inv + inv_step):
            x = (ray / i[..., None]) @ pose[:3, :3].T + pose[:3, 3]
            z = x[..., 2].clamp(min=1e-6)
            uv.append(torch.stack([ks[0, 0] * x[..., 0] / z, ks[1, 1] * x[..., 1] / z], -1))
        step = (uv[1] - uv[0]).norm(dim=-1)
        total += torch.where(agrees & ok & torch.isfinite(step), step, torch.zeros_like(step)) ** 2
    return total.sqrt().to(torch.float32)


def _refine(ref_img, k_ref, ref_ok, hw, srcs, views, depth_c, conf_c, inv_step: float, cfg: StereoConfig,
            bar: str | None):
    """Step 7b: the coarse depth (any grid, nearest-upsampled to `hw`), re-swept at this
    resolution over 2 `refine_steps` + 1 per-pixel hypotheses uniform in inverse depth, within
    `refine_span` coarse steps of it; the winner refined by the parabola. Confidence: the coarse
    one, 0 where the fine winner lies at the band's ends (the coarse depth was off) or where the
    fine sources disagree (fewer than half of the usable ones within one fine step)."""
    up = lambda x: F.interpolate(x[None, None], size=hw, mode="nearest")[0, 0]  # noqa: E731
    inv_c = 1.0 / up(depth_c).to(torch.float64)
    conf = up(conf_c)
    j_max = cfg.refine_steps
    fine = cfg.refine_span * inv_step / j_max
    offsets = torch.arange(-j_max, j_max + 1, dtype=torch.float64)
    inv = inv_c[None] + offsets[:, None, None] * fine
    inv = torch.where(conf[None] > 0, inv, torch.full_like(inv, float("nan")))  # no work where no confidence
    volume, best, arg, worst = _volume(ref_img, k_ref, ref_ok, hw, srcs, views, 1.0 / inv, cfg, bar)
    c = torch.where(torch.isnan(volume), torch.tensor(float("inf")), volume)
    j = c.argmin(0)
    cb = c.gather(0, j[None])[0]
    n = len(offsets)
    cm, cp = c.gather(0, (j - 1).clamp(min=0)[None])[0], c.gather(0, (j + 1).clamp(max=n - 1)[None])[0]
    inside = torch.isfinite(cb) & (j > 0) & (j < n - 1) & torch.isfinite(cm) & torch.isfinite(cp)
    curv = cm - 2.0 * cb + cp
    fit = inside & (curv > 0)
    off = torch.where(fit, 0.5 * (cm - cp) / torch.where(fit, curv, torch.ones_like(curv)), torch.zeros_like(curv))
    off = off.clamp(-0.5, 0.5).to(torch.float64)
    inv_f = inv_c + ((j - j_max).to(torch.float64) + off) * fine
    depth = torch.where(inside & (inv_f > 0), 1.0 / inv_f, torch.full_like(inv_f, float("nan"))).to(torch.float32)
    agreement, _, _ = _agreement(j, best, arg, worst, 1, cfg.lone_credit)
    conf = torch.where(inside & (agreement >= 0.5), conf, torch.zeros_like(conf))
    return depth, conf


def _consistent(depth: torch.Tensor, k_ref: np.ndarray, src_depth: torch.Tensor, k_src: np.ndarray,
                ref_to_src: np.ndarray, px_tol: float, rel_tol: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The reference's depth (h, w) (pinhole K k_ref) against a source's own depth map (hs, ws) (K
    k_src): each reference pixel's point, projected into the source, takes the source's depth at
    that pixel (nearest), and that point goes back into the reference. -> (checked, consistent), (h,
    w) bool: checked where the point lands in the source with a finite depth there; consistent where,
    besides, it comes back within `px_tol` pixels and `rel_tol` of the depth."""
    h, w = depth.shape
    hs, ws = src_depth.shape
    d = depth.to(torch.float64)
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5,
                          indexing="ij")
    kr, ks = torch.from_numpy(np.asarray(k_ref, np.float64)), torch.from_numpy(np.asarray(k_src, np.float64))
    pose = torch.from_numpy(np.asarray(ref_to_src, np.float64))
    x = torch.stack([(u - kr[0, 2]) / kr[0, 0] * d, (v - kr[1, 2]) / kr[1, 1] * d, d], -1)
    xs = x @ pose[:3, :3].T + pose[:3, 3]
    zs = xs[..., 2]
    front = torch.isfinite(zs) & (zs > 1e-6)
    zs_safe = torch.where(front, zs, torch.ones_like(zs))
    us, vs = ks[0, 0] * xs[..., 0] / zs_safe + ks[0, 2], ks[1, 1] * xs[..., 1] / zs_safe + ks[1, 2]
    inside = front & (us >= 0) & (us < ws) & (vs >= 0) & (vs < hs)
    ci = torch.where(inside, us, torch.zeros_like(us)).floor().long().clamp(0, ws - 1)
    ri = torch.where(inside, vs, torch.zeros_like(vs)).floor().long().clamp(0, hs - 1)
    ds = src_depth.to(torch.float64)[ri, ci]
    checked = inside & torch.isfinite(ds) & torch.isfinite(d)
    # the source's point at (us, vs) with its own depth, back in the reference
    y = torch.stack([(us - ks[0, 2]) / ks[0, 0] * ds, (vs - ks[1, 2]) / ks[1, 1] * ds, ds], -1)
    yr = (y - pose[:3, 3]) @ pose[:3, :3]
    zr = yr[..., 2]
    ok = checked & (zr > 1e-6)
    zr_safe = torch.where(ok, zr, torch.ones_like(zr))
    ur, vr = kr[0, 0] * yr[..., 0] / zr_safe + kr[0, 2], kr[1, 1] * yr[..., 1] / zr_safe + kr[1, 2]
    err = torch.hypot(ur - u, vr - v)
    consistent = ok & (err <= px_tol) & ((zr - d).abs() <= rel_tol * d)
    return checked, consistent


def _sweep_image(ref: CameraImage, ref_offset: int, cands: list, boxes: dict, cfg: StereoConfig,
                 progress: bool, keep: Box | None = None):
    """Steps 1-7b for `ref` (at instant `ref_offset`) against candidates `cands` ((offset, image)):
    depth, confidence, peak ratio and agreement (h, w) on the pinhole grid at `cfg.scale`, its K and
    the views; None where no view qualifies. keep: the pixels of this box only (`_prepare`)."""
    depths = inverse_depth_hypotheses(cfg.near_m, cfg.far_m, cfg.hypotheses)
    inv_step = (1.0 / cfg.near_m - 1.0 / cfg.far_m) / (cfg.hypotheses - 1)
    views = select_sources(ref, cands, cfg.sources, inv_step, min_baseline_m=cfg.min_baseline_m,
                           max_axis_angle_deg=cfg.max_axis_angle_deg, good_step_px=cfg.good_step_px / cfg.scale)
    if not views:
        return None
    sweep_scale = cfg.scale * (cfg.coarse_scale or 1.0)
    ref_img, k_ref, ref_ok, hw, srcs = _prepare(ref, views, boxes, cfg, sweep_scale, ref_offset, keep)
    bar = f"stereo {ref.name}" if progress else None
    volume, best, arg, worst = _volume(ref_img, k_ref, ref_ok, hw, srcs, views, depths, cfg, bar)
    if cfg.sgm_paths:
        volume = semi_global(volume, cfg.sgm_p1, cfg.sgm_p2, paths=cfg.sgm_paths, fill=UNSEEN_COST[cfg.cost],
                             image=ref_img, gradient_scale=cfg.sgm_gradient)
    inf = torch.tensor(float("inf"))
    depth, _, peak = winner_take_all(volume, depths)
    winner = torch.where(torch.isnan(volume), inf, volume).argmin(0)
    agreement, lone, agrees = _agreement(winner, best, arg, worst, cfg.agreement_tolerance, cfg.lone_credit)
    # a lone source needs the sharper peak: nothing can contradict a chance match of it (a source
    # whose view is blocked), and the aggregation makes such matches look peaked
    peak_full = torch.where(lone, torch.tensor(cfg.lone_peak_full), torch.tensor(cfg.peak_full))
    conf = (peak / peak_full).clamp(0.0, 1.0) * agreement
    # where several sources can cross-check a pixel, a chance match of two of three is no agreement
    low = (agreement < cfg.min_agreement) & ~lone
    if cfg.weak_agreement is None:
        conf = torch.where(low, torch.zeros_like(conf), conf)
    else:  # kept below the fusion's threshold: a voxel needs several such views (`FusionConfig.weak_confidence`)
        weak = low & (agreement >= cfg.weak_agreement)
        conf = torch.where(low, torch.where(weak, conf.clamp(max=cfg.weak_cap), torch.zeros_like(conf)), conf)
    # a winner at either end of the pixel's seen hypotheses is no minimum (the curve may go on
    # falling beyond: a point outside the source's image or beyond the depth range)
    seen = torch.isfinite(volume)
    below = seen.gather(0, (winner - 1).clamp(min=0)[None])[0] & (winner > 0)
    above = seen.gather(0, (winner + 1).clamp(max=len(depths) - 1)[None])[0] & (winner < len(depths) - 1)
    found = torch.isfinite(depth) & below & above
    conf = torch.where(found, conf, torch.zeros_like(conf))
    # the depth's expected precision: the sub-pixel match (`match_px`) over the motion per step
    parallax = _parallax(depth, k_ref, srcs, views, agrees, inv_step)
    if cfg.max_rel_error is not None:
        rel = cfg.match_px / parallax.clamp(min=1e-6) * inv_step * depth.nan_to_num(0.0)
        conf = conf * (cfg.max_rel_error / rel.clamp(min=1e-9)).clamp(max=1.0)
    del volume
    if cfg.coarse_scale is not None and cfg.coarse_scale < 1.0:
        peak_c, agree_c = peak, agreement
        ref_img, k_ref, ref_ok, hw, srcs = _prepare(ref, views, boxes, cfg, cfg.scale, ref_offset, keep)
        depth, conf = _refine(ref_img, k_ref, ref_ok, hw, srcs, views, depth, conf, inv_step, cfg,
                              f"refine {ref.name}" if progress else None)
        up = lambda x: F.interpolate(x[None, None].to(torch.float32), size=hw, mode="nearest")[0, 0]  # noqa: E731
        peak, agreement = up(peak_c), up(agree_c)
    return depth, conf, peak, agreement, k_ref, views


def stereo_depth(frames: Frames, index: int, cfg: StereoConfig | None = None, *,
                 progress: bool = False, movers: bool | None = None) -> StereoResult:
    """Depth and confidence of image `index` of `frames` from the other images of its instant and
    of its context instants (module docstring). progress: show a bar over the hypothesis chunks.
    movers: sweep the moving boxed objects in their own frames (step 4b; default `cfg.movers`)."""
    cfg = cfg or StereoConfig()
    if not cfg.near_m < cfg.far_m:
        raise InputError(f"stereo: near_m ({cfg.near_m}) must be below far_m ({cfg.far_m})")
    if cfg.sgm_paths and cfg.sgm_p1 > cfg.sgm_p2:
        raise InputError(f"stereo: sgm_p1 ({cfg.sgm_p1}) must not exceed sgm_p2 ({cfg.sgm_p2})")
    if cfg.window % 2 == 0:
        raise InputError(f"stereo: window must be odd, got {cfg.window}")
    ref = frames.images[index]
    if ref.intrinsics.model == "fisheye":
        raise InputError(f"stereo: camera {ref.name!r} is a fisheye camera; the plane sweep supports pinhole and "
                         f"opencv (undistorted to pinhole) cameras only")
    boxes = {f.offset: f.boxes for f in frames.instants()}
    out = _sweep_image(ref, 0, candidates(frames, index), boxes, cfg, progress)
    if out is None:
        return _empty(ref, [])
    depth, conf, peak, agreement, k_ref, views = out
    if cfg.consistency_views:
        conf = conf * _geometric_check(frames, depth, k_ref, views, boxes, cfg, progress)

    depth_o, conf_o, peak_o, agree_o = _to_original(
        [depth.numpy(), conf.numpy(), peak.numpy(), agreement.numpy().astype(np.float32)], ref, k_ref,
        [math.nan, 0.0, 0.0, 0.0])
    if cfg.movers if movers is None else movers:
        for (rows, cols), maps in _mover_sweeps(ref, candidates(frames, index), boxes, cfg, progress):
            better = maps[1] > conf_o[rows, cols]
            for full, part in zip((depth_o, conf_o, peak_o, agree_o), maps):
                full[rows, cols] = np.where(better, part, full[rows, cols])
    sky = np.zeros(depth_o.shape, bool) if ref.sky is None else np.asarray(ref.sky, bool)
    depth_o, conf_o = np.where(sky, np.float32(np.nan), depth_o), np.where(sky, np.float32(0), conf_o)
    if cfg.fill_gap_deg > 0:
        gap_px = int(math.radians(cfg.fill_gap_deg) * float(ref.intrinsics.K[0, 0]))
        sure_above = 0.0 if cfg.weak_agreement is None else cfg.weak_cap
        depth_o, conf_o = fill_gaps(depth_o, conf_o, gap_px, cfg.fill_tolerance, cfg.fill_confidence, ~sky, sure_above,
                                    coplanar=cfg.fill_coplanar)
    return StereoResult(depth_o.astype(np.float32), conf_o.astype(np.float32), peak_o.astype(np.float32),
                        agree_o.astype(np.float32), views)


def _geometric_check(frames: Frames, depth: torch.Tensor, k_ref: np.ndarray, views: list[SourceView], boxes: dict,
                     cfg: StereoConfig, progress: bool) -> torch.Tensor:
    """Step 7c: (h, w) float32, 1 where the reference's depth agrees with the own depth map of at
    least one of its best `consistency_views` sources (each swept like the reference, against every
    other image of the frames: `_consistent`) or where none of them can check it, else 0."""
    sub = cfg.model_copy(update={"consistency_views": 0})
    every = [(f.offset, im) for f in frames.instants() for im in f.images]
    n_checked = torch.zeros(depth.shape, dtype=torch.int64)
    n_consistent = torch.zeros(depth.shape, dtype=torch.int64)
    for v in views[: cfg.consistency_views]:
        out = _sweep_image(v.image, v.offset, [(o, im) for o, im in every if im is not v.image], boxes, sub, progress)
        if out is None:
            continue
        checked, consistent = _consistent(depth, k_ref, out[0], out[4], v.ref_to_src, cfg.consistency_px,
                                          cfg.consistency_rel)
        n_checked += checked
        n_consistent += consistent
    return (n_consistent >= n_checked.clamp(max=cfg.consistency_agree)).to(torch.float32)
