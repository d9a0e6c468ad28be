"""Evaluation metrics of the converter's geometry stage (camera images -> sparse semantic voxels).

What the paper reports for it: the fine grid's IoU and semantic mIoU, and the 'voxel Chamfer
distance' (in voxels) with its quantiles 0.5 .. 0.9 over the test samples; here each also split
by voxels visible / invisible from the input cameras (the paper notes ~80% of the ground-truth
voxels are occluded, so the two halves tell different stories).

Grids: ``ijk`` (V, 3) int voxel indices of one grid (voxel (i, j, k) spans origin + [ijk, ijk + 1)
* voxel_size in the chunk frame: x forward, y left, z up, metres), ``labels`` (V,) int label ids
(0 <= label < num_labels, `scube_sim.labels`). numpy arrays or torch tensors; all the work is in
numpy (float64). A grid is a set: IoU and Chamfer see a repeated voxel once; the semantic
confusion refuses one (its label would be ambiguous).

    cams = {k: item[k] for k in ("intrinsics", "distortion", "cam_to_chunk", "depth", "image_size")}
    per = [geometry_sample_metrics(p_ijk, p_lab, g_ijk, g_lab, NUM_LABELS,
                                   visible_voxels(p_ijk, vs, origin, **cams),
                                   visible_voxels(g_ijk, vs, origin, **cams)) for ...]
    metrics = summarise(per)        # flat {name: float}: 'iou', 'miou', 'chamfer_q50', ...

The same visibility rule (`visible_voxels`) on both grids makes the split a partition of space: a
voxel in both grids is on the same side of it in both.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from ...camera.model import Intrinsics
from ...errors import InputError
from ...labels import LABEL_NAMES, NUM_LABELS

__all__ = ["QUANTILES", "SPLITS", "chamfer_voxels", "geometry_sample_metrics", "semantic_confusion",
           "semantic_iou", "summarise", "visible_voxels", "voxel_iou"]

QUANTILES = (0.5, 0.6, 0.7, 0.8, 0.9)  # the paper's Chamfer table
# Key suffixes of the three voxel sets: all, visible from the input cameras, invisible.
SPLITS = ("", "_visible", "_invisible")
_CHUNK = 1 << 20  # voxels projected at a time in `visible_voxels` (bounds its memory)


# --- inputs ----------------------------------------------------------------------------------------


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _ijk(x, name: str) -> np.ndarray:
    """(V, 3) int64; an empty array of any shape is an empty grid."""
    a = _np(x)
    if a.size == 0:
        return np.zeros((0, 3), np.int64)
    if a.ndim != 2 or a.shape[1] != 3 or not np.issubdtype(a.dtype, np.integer):
        raise InputError(f"{name}: expected (V, 3) integer voxel indices, got {a.dtype} {a.shape}")
    return a.astype(np.int64)


def _labels(x, n: int, num_labels: int, name: str) -> np.ndarray:
    a = _np(x)
    a = a.reshape(0) if a.size == 0 else a
    if a.shape != (n,) or (n and not np.issubdtype(a.dtype, np.integer)):
        raise InputError(f"{name}: expected ({n},) integer label ids, got {a.dtype} {a.shape}")
    a = a.astype(np.int64)
    if n and (a.min() < 0 or a.max() >= num_labels):
        raise InputError(f"{name}: label ids must lie in [0, {num_labels}), got [{a.min()}, {a.max()}]")
    return a


def _mask(x, n: int, name: str) -> np.ndarray:
    a = _np(x)
    if a.shape != (n,) or a.dtype != bool:
        raise InputError(f"{name}: expected a ({n},) bool mask, got {a.dtype} {a.shape}")
    return a


def _keys(*grids: np.ndarray) -> list[np.ndarray]:
    """One int64 key per voxel, the same voxel the same key across `grids` (a shared base)."""
    nonempty = [g for g in grids if len(g)]
    if not nonempty:
        return [np.zeros(0, np.int64) for _ in grids]
    both = np.concatenate(nonempty)
    lo = both.min(0)
    span = both.max(0) - lo + 1
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0**62:
        raise InputError(f"voxel indices span {span.tolist()}: too large to key in int64")
    return [((g[:, 0] - lo[0]) * span[1] + (g[:, 1] - lo[1])) * span[2] + (g[:, 2] - lo[2]) for g in grids]


def _restrict(pred: np.ndarray, gt: np.ndarray, region) -> tuple[np.ndarray, np.ndarray]:
    """Both grids cut to `region`: None (everything), a predicate ijk (V, 3) int64 -> (V,) bool
    applied to each grid, or a pair (pred mask (P,) bool, gt mask (G,) bool)."""
    if region is None:
        return pred, gt
    if callable(region):
        pm, gm = _np(region(pred)), _np(region(gt))
    else:
        if len(region) != 2:
            raise InputError("region: expected a predicate or a (pred mask, gt mask) pair")
        pm, gm = region
    return pred[_mask(pm, len(pred), "region (pred)")], gt[_mask(gm, len(gt), "region (gt)")]


# --- occupancy ---------------------------------------------------------------------------------------


def voxel_iou(pred_ijk, gt_ijk, region: Callable | Sequence | None = None) -> float:
    """|P ∩ G| / |P ∪ G| over the unique voxels of the two grids, both first cut to `region`
    (see `_restrict`: a predicate on ijk, or a (pred mask, gt mask) pair). nan when the union is
    empty (both grids empty in the region): no evidence either way, so means skip it; 0 when
    only one side is empty."""
    p, g = _restrict(_ijk(pred_ijk, "pred_ijk"), _ijk(gt_ijk, "gt_ijk"), region)
    kp, kg = (np.unique(k) for k in _keys(p, g))
    inter = np.intersect1d(kp, kg, assume_unique=True).size
    union = kp.size + kg.size - inter
    return inter / union if union else math.nan


def chamfer_voxels(pred_ijk, gt_ijk) -> float:
    """Symmetric voxel Chamfer distance, in voxels: 0.5 * (mean over the voxels p of P of
    min_g |c(p) - c(g)| + mean over G of min_p |c(g) - c(p)|), c the voxel centre, |.| the L2
    norm, unique voxels. The paper's 'L2-Chamfer distance ... divided by the voxel size' (so a
    one-voxel-thick wall predicted one voxel off scores 1). inf when exactly one grid is empty,
    0 when both are."""
    p, g = _ijk(pred_ijk, "pred_ijk"), _ijk(gt_ijk, "gt_ijk")
    if len(p) == 0 or len(g) == 0:
        return 0.0 if len(p) == len(g) else math.inf
    (kp, ip), (kg, ig) = (np.unique(k, return_index=True) for k in _keys(p, g))
    p, g = p[ip], g[ig]
    # A voxel in both grids is 0 from the other: only the rest are queried (most of a good prediction
    # is shared, so this is a fraction of the queries).
    far_p, far_g = ~np.isin(kp, kg, assume_unique=True), ~np.isin(kg, kp, assume_unique=True)
    d_pg = _nearest_distance_sum(g, p[far_p])
    d_gp = _nearest_distance_sum(p, g[far_g])
    return float(0.5 * (d_pg / len(p) + d_gp / len(g)))


_EDT_MAX_BOX = 1 << 25  # voxels: a dense distance transform's float64 output stays under 256 MB
_NEAR = 4.0  # voxels: the k-d tree answers queries this close to a site quickly
_EDT_MIN_FAR = 20_000  # queries farther than _NEAR that make the dense transform worth its cost


def _nearest_distance_sum(sites: np.ndarray, queries: np.ndarray, method: str = "auto") -> float:
    """Sum over the (Q, 3) int64 voxels `queries` of the Euclidean distance (in voxels) to the nearest
    of the (S, 3) `sites` (S > 0). Both methods are exact: a k-d tree, or a dense Euclidean distance
    transform over the two sets' bounding box (scipy.ndimage), whose cost does not grow with the
    distances. A tree's does, on a voxel lattice's many equidistant neighbours: far queries take it
    minutes where the transform takes seconds. 'auto' asks the tree for every query within `_NEAR`
    voxels (cheap: few equidistant neighbours there) and the transform for the rest
    where they are many and the box fits `_EDT_MAX_BOX`."""
    if not len(queries):
        return 0.0
    lo = np.minimum(sites.min(0), queries.min(0))
    shape = np.maximum(sites.max(0), queries.max(0)) - lo + 1
    fits = float(np.prod(shape.astype(np.float64))) <= _EDT_MAX_BOX
    if method == "edt" or (method == "auto" and fits and len(queries) >= _EDT_MIN_FAR and len(sites) >= _EDT_MIN_FAR):
        total, far = 0.0, queries
        if method == "auto":
            # Centres are ijk + 0.5 on both sides: the offset cancels, the indices are the centres.
            d = cKDTree(sites.astype(np.float64)).query(queries.astype(np.float64), k=1, distance_upper_bound=_NEAR)[0]
            near = np.isfinite(d)
            total, far = float(d[near].sum()), queries[~near]
            if len(far) < _EDT_MIN_FAR:
                return total + _nearest_distance_sum(sites, far, "tree")
        free = np.ones(tuple(int(v) for v in shape), bool)
        free[tuple((sites - lo).T)] = False
        return total + float(ndimage.distance_transform_edt(free)[tuple((far - lo).T)].sum())
    return float(cKDTree(sites.astype(np.float64)).query(queries.astype(np.float64), k=1)[0].sum())


# --- semantics -------------------------------------------------------------------------------------


def semantic_confusion(pred_ijk, pred_labels, gt_ijk, gt_labels, num_labels: int = NUM_LABELS) -> np.ndarray:
    """(L + 1, L + 1) int64 counts conf[true, predicted] over the union of the two grids, L =
    num_labels; index L is 'empty': a voxel only in the prediction counts in row L (a false
    positive of its label), one only in the ground truth in column L (a false negative);
    conf[L, L] stays 0 (free space is not enumerated). The semantic scene completion convention
    (SemanticKITTI, XCube). Sum over samples, then `semantic_iou`, for a dataset mIoU. Each grid
    must list a voxel at most once (its label would be ambiguous)."""
    p, g = _ijk(pred_ijk, "pred_ijk"), _ijk(gt_ijk, "gt_ijk")
    lp = _labels(pred_labels, len(p), num_labels, "pred_labels")
    lg = _labels(gt_labels, len(g), num_labels, "gt_labels")
    kp, kg = _keys(p, g)
    for k, name in ((kp, "pred_ijk"), (kg, "gt_ijk")):
        if np.unique(k).size != k.size:
            raise InputError(f"{name}: a voxel is listed more than once")
    _, ip, ig = np.intersect1d(kp, kg, assume_unique=True, return_indices=True)
    only_p = np.ones(len(p), bool)
    only_p[ip] = False
    only_g = np.ones(len(g), bool)
    only_g[ig] = False
    e, n = num_labels, num_labels + 1
    true = np.concatenate([lg[ig], np.full(only_p.sum(), e), lg[only_g]])
    pred = np.concatenate([lp[ip], lp[only_p], np.full(only_g.sum(), e)])
    return np.bincount(true * n + pred, minlength=n * n).reshape(n, n).astype(np.int64)


def _label_name(i: int) -> str:
    return LABEL_NAMES[i] if i < len(LABEL_NAMES) else f"label_{i}"


def semantic_iou(conf) -> tuple[float, dict[str, float]]:
    """A `semantic_confusion` (or a sum of them) -> (mIoU, {label name: IoU}). IoU_c = TP / (TP +
    FP + FN) per label c (empty excluded); mIoU = their mean over the labels present in either
    side (TP + FP + FN > 0), those the dict lists; nan when no label is present."""
    c = _np(conf).astype(np.float64)
    num_labels = c.shape[0] - 1
    tp = np.diag(c)[:num_labels]
    union = (c.sum(0) + c.sum(1))[:num_labels] - tp  # TP + FP + FN
    present = np.flatnonzero(union > 0)
    per = {_label_name(int(i)): float(tp[i] / union[i]) for i in present}
    return (float(np.mean(list(per.values()))) if per else math.nan), per


# --- visibility ------------------------------------------------------------------------------------


def visible_voxels(ijk, voxel_size: float, origin, intrinsics, distortion, cam_to_chunk, depth, image_size,
                   margin: float | None = None) -> np.ndarray:
    """(V,) bool: voxels seen by the input cameras. A voxel is visible when, for some camera, its
    centre (origin + (ijk + 0.5) * voxel_size, chunk frame) lies in front of it, projects (with
    the lens distortion, `camera.model.Intrinsics.project`) inside its image, 0 <= u < width and
    0 <= v < height, and its camera-z depth is at most the depth map at that pixel (floor(u),
    floor(v)) + `margin` (metres; default half the voxel diagonal, sqrt(3)/2 * voxel_size, so a
    voxel the surface passes through counts). Sky pixels (depth inf) see everything along them;
    padding pixels (depth 0) never count. One sample per voxel keeps it cheap; it is a rule of
    space, so it splits predicted and ground-truth voxels alike.

    Cameras as the torch items of `model.data`: intrinsics (N, 3, 3) K in pixels (pixel (u, v)
    spans [u, u + 1), centre at + 0.5), distortion (N, 5) OpenCV [k1, k2, p1, p2, k3],
    cam_to_chunk (N, 4, 4) OpenCV camera (x right, y down, z forward) to chunk, depth (N, H, W)
    metres along the optical axis, image_size (N, 2) (height, width) <= (H, W)."""
    g = _ijk(ijk, "ijk")
    k_all, dist, pose = (_np(x).astype(np.float64) for x in (intrinsics, distortion, cam_to_chunk))
    depth, size = _np(depth), _np(image_size).astype(np.int64)
    n = len(k_all)
    if (k_all.shape != (n, 3, 3) or dist.shape != (n, 5) or pose.shape != (n, 4, 4) or depth.ndim != 3
            or len(depth) != n or size.shape != (n, 2)):
        raise InputError(f"cameras: expected intrinsics (N, 3, 3), distortion (N, 5), cam_to_chunk (N, 4, 4), "
                         f"depth (N, H, W), image_size (N, 2); got {k_all.shape}, {dist.shape}, {pose.shape}, "
                         f"{depth.shape}, {size.shape}")
    if np.any(size < 1) or np.any(size > np.array(depth.shape[1:])):
        raise InputError(f"image_size: each (height, width) must lie in [1, {depth.shape[1:]}], got {size.tolist()}")
    if not voxel_size > 0:
        raise InputError(f"voxel_size: expected > 0, got {voxel_size}")
    margin = math.sqrt(3) / 2 * voxel_size if margin is None else float(margin)
    origin = _np(origin).astype(np.float64).reshape(3)
    seen = np.zeros(len(g), bool)
    for c in range(n):
        (h, w), kc = size[c], k_all[c]
        intr = Intrinsics(int(w), int(h), kc[0, 0], kc[1, 1], kc[0, 2], kc[1, 2],
                          "opencv" if np.any(dist[c]) else "pinhole", dist[c] if np.any(dist[c]) else ())
        r, t = pose[c, :3, :3], pose[c, :3, 3]
        dmap = depth[c].astype(np.float64)
        for s in range(0, len(g), _CHUNK):
            centres = origin + (g[s:s + _CHUNK] + 0.5) * voxel_size
            uv, z = intr.project((centres - t) @ r)  # rows: R^T (p - t), chunk -> camera
            with np.errstate(invalid="ignore"):  # NaN pixels: behind the camera or past the fold
                inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            idx = np.flatnonzero(inside)
            u, v = np.floor(uv[idx]).astype(np.int64).T
            d = dmap[v, u]
            ok = (d > 0) & (z[idx] <= d + margin)  # NaN depth fails both: never seen
            seen[s + idx[ok]] = True
    return seen


# --- per sample and over the set -------------------------------------------------------------------


def geometry_sample_metrics(pred_ijk, pred_labels, gt_ijk, gt_labels, num_labels: int, pred_visible,
                            gt_visible) -> dict:
    """One test sample's metrics, on all voxels and on the visible / invisible ones (masks (P,)
    and (G,) bool, e.g. `visible_voxels` of each grid). Per split suffix s of `SPLITS`: 'iou{s}'
    (`voxel_iou`, nan on an empty union), 'chamfer{s}' (`chamfer_voxels`), 'miou{s}' (this sample
    alone), 'confusion{s}' ((L + 1, L + 1) int64 `semantic_confusion`, to sum over the set);
    counts 'num_pred', 'num_gt', 'num_pred_visible', 'num_gt_visible' (int)."""
    p, g = _ijk(pred_ijk, "pred_ijk"), _ijk(gt_ijk, "gt_ijk")
    lp = _labels(pred_labels, len(p), num_labels, "pred_labels")
    lg = _labels(gt_labels, len(g), num_labels, "gt_labels")
    pv, gv = _mask(pred_visible, len(p), "pred_visible"), _mask(gt_visible, len(g), "gt_visible")
    out: dict = {"num_pred": len(p), "num_gt": len(g), "num_pred_visible": int(pv.sum()),
                 "num_gt_visible": int(gv.sum())}
    for s, (mp, mg) in zip(SPLITS, ((slice(None), slice(None)), (pv, gv), (~pv, ~gv))):
        conf = semantic_confusion(p[mp], lp[mp], g[mg], lg[mg], num_labels)
        # the union is every counted voxel, the intersection those in neither the empty row nor
        # column: `voxel_iou` without keying and sorting the grids again
        union = int(conf.sum())
        out[f"iou{s}"] = int(conf[:num_labels, :num_labels].sum()) / union if union else math.nan
        out[f"chamfer{s}"] = chamfer_voxels(p[mp], g[mg])
        out[f"miou{s}"] = semantic_iou(conf)[0]
        out[f"confusion{s}"] = conf
    return out


def _quantile(values: np.ndarray, q: float) -> float:
    """numpy's default ('linear') quantile, but inf-safe: a quantile that interpolates towards an
    inf sample (an empty prediction's Chamfer) is inf, not the nan of inf - inf."""
    x = np.sort(values)
    h = (len(x) - 1) * q
    lo = int(math.floor(h))
    frac = h - lo
    if frac == 0:
        return float(x[lo])
    hi = x[lo + 1]
    return math.inf if math.isinf(hi) else float(x[lo] + frac * (hi - x[lo]))


def summarise(samples: list[dict], quantiles: Sequence[float] = QUANTILES) -> dict[str, float]:
    """`geometry_sample_metrics` of the test samples -> flat {name: float} for a metrics file.

    Per split suffix s of `SPLITS` ('', '_visible', '_invisible'): 'iou{s}' the mean sample IoU
    (samples with an empty union skipped; nan if all are); 'miou{s}' the mIoU of the summed
    confusion (the dataset mIoU, not a mean of per-sample ones); 'chamfer{s}_mean' and
    'chamfer{s}_q50', 'chamfer{s}_q60', ... the Chamfer quantiles over samples (numpy's linear
    method; inf where an empty prediction reaches them). Also 'label_iou_<name>' per label present
    (all voxels), 'gt_visible_fraction' (visible ground-truth voxels over all of them) and
    'num_samples'. nan / inf values are written by `json.dumps` as NaN / Infinity."""
    if not samples:
        raise InputError("summarise: no samples")
    if any(not 0 <= q <= 1 for q in quantiles):
        raise InputError(f"quantiles: expected values in [0, 1], got {list(quantiles)}")
    out = {"num_samples": float(len(samples))}
    for s in SPLITS:
        ious = np.array([x[f"iou{s}"] for x in samples], np.float64)
        out[f"iou{s}"] = float(ious[~np.isnan(ious)].mean()) if np.any(~np.isnan(ious)) else math.nan
        miou, per = semantic_iou(sum(np.asarray(x[f"confusion{s}"], np.int64) for x in samples))
        out[f"miou{s}"] = miou
        if s == "":
            out.update({f"label_iou_{name}": v for name, v in per.items()})
        ch = np.array([x[f"chamfer{s}"] for x in samples], np.float64)
        out[f"chamfer{s}_mean"] = float(ch.mean())
        for q in quantiles:
            out[f"chamfer{s}_q{round(100 * q, 6):g}"] = _quantile(ch, q)
    num_gt = sum(x["num_gt"] for x in samples)
    out["gt_visible_fraction"] = sum(x["num_gt_visible"] for x in samples) / num_gt if num_gt else math.nan
    return out
