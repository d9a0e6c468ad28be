"""Multi-view stereo for one reference image of a `Frames`: a plane sweep over the best source views
(other cameras at the reference instant, every camera at the context instants), a robust
aggregation across sources, winner-take-all depth and a per-pixel confidence.

Steps (`stereo_depth`; the knobs are `StereoConfig`'s):
1. Images to pinhole: OpenCV-distorted images are resampled onto a pinhole camera with the same K,
   scaled by `scale` (antialiased): a lower scale sweeps faster. Fisheye references are refused.
2. Sources: `views.select_sources` keeps the views with overlap and parallax per hypothesis step;
   a zero baseline or a camera turned away measures nothing.
3. Cost: per source and hypothesis the census cost of the warped source against the reference
   (`sweep.cost_census`), which an exposure difference between cameras does not change.
4. Moving actors: a box whose object moved between the reference's instant and a source's
   (`movers.moved_boxes`; an unmatched box counts as moved) is masked out of that source's cost at
   the reference's and at the source's pixels inside it, grown by `box_margin_m` and half the
   window: no static depth explains a moving object, so those pixels use same-instant sources only.
4b. Optional (`movers`): each such object is swept again in its own frame (each source posed where
   its camera stood relative to the object), where a rigid mover is as static as the street; its
   pixels take that answer where it is the more confident and puts the point inside the box.
5. Aggregation: per hypothesis the mean of the best k of the n sources that see the pixel,
   k = max(ceil(n / 2), min(n, 2)): one occluded or moving source does not spoil the pixel, and two
   must agree where two see it.
5b. Semi-global aggregation of that volume (`sgm_paths`, `sgm.semi_global`): neighbours on a smooth
   surface support a pixel whose own window is ambiguous.
6. Winner-take-all with the parabola (`winner.winner_take_all`): depth and peak ratio.
7. Confidence: the peak ratio over `peak_full` times the agreement, the share of the usable sources
   whose own minimum lies within `agreement_tolerance` hypotheses of the winner (moving objects and
   occlusions disagree across instants); 0 below `min_agreement` (a chance match of two of three),
   or at most `weak_cap` from `weak_agreement` up, and 0 where the winner is the first or last
   hypothesis seen. A lone source cannot be cross-checked: `lone_credit`, and `lone_peak_full` for
   its peak. Scaled down where the expected relative depth error (`match_px` over the parallax per
   step, `_parallax`) exceeds `max_rel_error`: near a forward camera's focus of expansion.
8. Back to the original image's pixels (nearest pinhole pixel of each ray); sky (`CameraImage.sky`)
   and pixels no source sees: NaN depth, confidence 0.
9. Optional gap filling (`fill_gap_deg`, `gaps.fill_gaps`): an unsure run along a row or column
   between two confident pixels whose depths agree (or lie in line with the pixels beyond them,
   `fill_coplanar`) takes the depth interpolated in inverse depth: a textureless patch of a wall.

Steps 3 and 5 (`_volume`), 5b (`sgm.semi_global`) and 6 (`winner.winner_take_all`) run in the
compiled sweep (`compiled.py`, `_sweep.cpp`: the reference's operations in its order) where it is
built; `_volume_reference`, `sgm.semi_global_reference` and `winner.winner_take_all_reference` are
their torch references (`SCUBE_SIM_CORE=reference` chooses them).

Depth: metres along the reference camera's optical axis. Deterministic: the bytes do not depend on
the thread count (`sweep`'s operations, a fixed summation order over sources; the compiled sweep
computes each output from a fixed sequence of inputs whatever its thread count).
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
from ...memory import check_fits
from ...transforms import invert_pose
from ..config import StereoConfig
from . import compiled
from .gaps import fill_gaps
from .movers import box_mask, crop, moved_boxes, mover_tracks
from .sgm import semi_global
from .sweep import cost_census, inverse_depth_hypotheses, warp_to_reference
from .views import SourceView, candidates, select_sources
from .winner import _winner_take_all

MOVER_TOLERANCE_M = 0.1  # step 4b: how far outside its box a moving object's measured point may lie
FLAT_COST = 0.02  # a source whose own cost curve varies less than this (census: share of bits) has no say
# memory per pixel of the stereo grid: per hypothesis, the float32 volume, its semi-global
# aggregation and the masks read from them; per source, its float32 minimum and maximum, int64
# argmin, and its warped image and grids
VOLUME_BYTES = 16
SOURCE_BYTES = 48
UNSEEN_COST = 0.5  # the census cost of an uncorrelated match (half the bits differ): semi-global's fill

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


def _robust_mean(costs: list[torch.Tensor]) -> torch.Tensor:
    """Sources' (D, h, w) costs (NaN: unseen) -> per entry the mean of the best k of the n sources
    that see it, k = max(ceil(n / 2), min(n, 2)); NaN where no source sees it. Summed in sorted
    order (deterministic)."""
    stack = torch.stack(costs)
    finite = torch.isfinite(stack)
    n = finite.sum(0)
    k = torch.maximum((n + 1) // 2, n.clamp(max=2))
    fill = float("inf")
    ordered = torch.where(finite, stack, torch.full_like(stack, fill)).sort(0).values
    total = torch.zeros_like(stack[0])
    for j in range(len(costs)):
        total += torch.where(j < k, ordered[j], torch.zeros_like(total))
    return torch.where(n > 0, total / k.clamp(min=1).to(total.dtype), torch.full_like(total, float("nan")))


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
            src_mask = torch.ones(img.shape[-2:], dtype=torch.bool) if inside is None else ~inside
            src_mask = src_mask[None].to(torch.float32)
        elif v.offset != ref_offset and (boxes.get(ref_offset) or boxes.get(v.offset)):
            moved_ref, moved_src = moved_boxes(boxes.get(ref_offset, []), boxes.get(v.offset, []), cfg)
            ref_mask = box_mask(moved_ref, ref.cam_to_world, k_ref, hw, cfg.box_margin_m, pad)
            src_mask = box_mask(moved_src, v.image.cam_to_world, k_src, tuple(img.shape[-2:]), cfg.box_margin_m, pad)
            src_mask = None if src_mask is None else src_mask[None].to(torch.float32)
        srcs.append((img, k_src, ref_mask, src_mask))
    return ref_img, k_ref, ref_ok, hw, srcs


def _volume(ref_img, k_ref, ref_ok, hw, srcs, views, hyps: torch.Tensor, cfg: StereoConfig, bar: str | None):
    """The aggregated cost volume (D, h, w) over hypotheses `hyps` ((D,) depths), and per source its
    own curve's minimum, its hypothesis and its maximum: the compiled sweep (`compiled.volume`)
    where it is built, unless `SCUBE_SIM_CORE=reference` (`compiled.default_core_name`), else
    `_volume_reference`."""
    if compiled.default_core_name() == "compiled":
        return compiled.volume(ref_img, k_ref, ref_ok, hw, srcs, views, hyps, cfg, bar)
    return _volume_reference(ref_img, k_ref, ref_ok, hw, srcs, views, hyps, cfg, bar)


def _volume_reference(ref_img, k_ref, ref_ok, hw, srcs, views, hyps: torch.Tensor, cfg: StereoConfig,
                      bar: str | None):
    """`_volume` in torch, the reference the compiled sweep is tested against: ref_img (C, h, w)
    float32, k_ref (3, 3), ref_ok (h, w) bool, hw (h, w), srcs per source (image, K, reference-side
    mask (h, w) bool or None, source-side mask (1, Hs, Ws) float32 or None), views (`SourceView`s),
    hyps (D,) metres. Returns the volume (D, h, w) float32 and per source best (h, w) float32, arg
    (h, w) int64 and worst (h, w) float32. bar: a bar over the hypothesis chunks."""
    inf = torch.tensor(float("inf"))
    n_src = len(srcs)
    best = [torch.full(hw, float("inf")) for _ in range(n_src)]  # each source's own minimum ...
    arg = [torch.zeros(hw, dtype=torch.int64) for _ in range(n_src)]  # ... its hypothesis ...
    worst = [torch.full(hw, -float("inf")) for _ in range(n_src)]  # ... and its curve's maximum
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
            cost = cost_census(ref_img, warped, valid, cfg.window)
            finite = torch.isfinite(cost)
            lo = torch.where(finite, cost, inf)
            m, a = lo.min(0)
            better = m < best[s]  # strict: the first minimum over the chunks, as within one
            best[s] = torch.where(better, m, best[s])
            arg[s] = torch.where(better, a + c * cfg.chunk, arg[s])
            worst[s] = torch.maximum(worst[s], torch.where(finite, cost, -inf).max(0).values)
            per.append(cost)
        agg.append(_robust_mean(per))
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


def _sweep_image(ref: CameraImage, ref_offset: int, cands: list, boxes: dict, cfg: StereoConfig,
                 progress: bool, keep: Box | None = None):
    """Steps 1-7 for `ref` (at instant `ref_offset`) against candidates `cands` ((offset, image)):
    depth, confidence, peak ratio and agreement (h, w) on the pinhole grid at `cfg.scale`, its K and
    the views; None where no view qualifies. keep: the pixels of this box only (`_prepare`)."""
    depths = inverse_depth_hypotheses(cfg.near_m, cfg.far_m, cfg.hypotheses)
    inv_step = (1.0 / cfg.near_m - 1.0 / cfg.far_m) / (cfg.hypotheses - 1)
    views = select_sources(ref, cands, cfg.sources, inv_step, min_baseline_m=cfg.min_baseline_m,
                           max_axis_angle_deg=cfg.max_axis_angle_deg, good_step_px=cfg.good_step_px / cfg.scale)
    if not views:
        return None
    ref_img, k_ref, ref_ok, hw, srcs = _prepare(ref, views, boxes, cfg, cfg.scale, ref_offset, keep)
    # the cost volume, its aggregation and their masks, and each source's extremes: refused from
    # the image's size before any of it is made
    h, w = hw
    check_fits(h * w * (len(depths) * VOLUME_BYTES + len(srcs) * SOURCE_BYTES),
               f"stereo of camera {ref.name!r} ({w}x{h} pixels at scale {cfg.scale:g}, {len(depths)} hypotheses, "
               f"{len(srcs)} sources)", InputError,
               hint="convert with fewer cameras or a profile with a smaller stereo scale or fewer hypotheses")
    bar = f"stereo {ref.name}" if progress else None
    volume, best, arg, worst = _volume(ref_img, k_ref, ref_ok, hw, srcs, views, depths, cfg, bar)
    if cfg.sgm_paths:
        volume = semi_global(volume, cfg.sgm_p1, cfg.sgm_p2, paths=cfg.sgm_paths, fill=UNSEEN_COST)
    depth, _, peak, winner = _winner_take_all(volume, depths)
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
        depth_o, conf_o = fill_gaps(depth_o, conf_o, gap_px, cfg.fill_tolerance, ~sky, sure_above,
                                    coplanar=cfg.fill_coplanar)
    return StereoResult(depth_o.astype(np.float32), conf_o.astype(np.float32), peak_o.astype(np.float32),
                        agree_o.astype(np.float32), views)

