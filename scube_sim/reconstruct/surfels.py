"""Surfels: Gaussians fitted to measured surface points (`evidence_voxsplat`), and the samples that
stand for surfaces no camera measured: the ground height field under the columns no observed
ground covers, and the outsides of boxed objects (`box_samples`). `scene_from_evidence` turns an
`Evidence` into the route's VoxSplat (chunk frame, metres); the scene traces at hard opacity
(`entry`): its Gaussians are flat surfels on measured surfaces.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..boxes import Box, points_in_boxes
from ..camera.depth import project_to_pixels
from ..errors import InputError
from ..fit import FitOptions, fit_voxsplat
from ..labels import LABEL_IDS
from ..splat_params import SCALE
from ..voxsplat import VoxSplat, voxel_keys
from .config import GROUND_LABEL, OTHER_LABEL, EvidenceConfig, FusionConfig
from .evidence import Evidence, chunk_bounds
from .fusion import DepthObservation, FusedGrid, carve_band, voxel_of
from .ground import HeightField

__all__ = ["SurfaceSamples", "box_samples", "evidence_voxsplat", "scene_from_evidence", "snap_ground",
           "widen_surfels"]


@dataclass
class SurfaceSamples:
    """Points on a surface no camera saw (e.g. the ground's height field), to be fitted with the
    observed ones: points (N, 3) float64 in the grid's frame (world), patch (N, 6) footprint
    covariances, colors (N, 3) in [0, 1], labels (N,) label ids, and the `confidence` of the voxels
    they alone make."""

    points: np.ndarray
    patch: np.ndarray
    colors: np.ndarray
    labels: np.ndarray
    confidence: float


def evidence_voxsplat(grid: FusedGrid, *, gaussians_per_voxel: int = 4, max_normal_scale: float | None = None,
                      labels: np.ndarray | None = None, unobserved: SurfaceSamples | None = None) -> VoxSplat:
    """Surfels on the observed surfaces: `fit.fit_voxsplat` (the fit `scube-sim build` applies to
    LiDAR points) on the grid's points, weighted by their confidence, each standing for its pixel's
    footprint, coloured by its pixel; in the grid's frame (local = world - origin). labels: per
    point label ids (N,) (a voxel takes the weighted majority; default none). unobserved: surface
    samples fitted with them (weight 1). Channels `observed` (a voxel holding an observed point)
    and `confidence` (the occupancy probability; `unobserved.confidence` where only samples)."""
    if len(grid.points) == 0 and (unobserved is None or len(unobserved.points) == 0):
        raise InputError("evidence_voxsplat: nothing to fit (no confident depth and no surface samples)")
    pts, patch, cols, w = grid.points, grid.patch.astype(np.float64), grid.colors, grid.weights.astype(np.float64)
    lab = labels
    seen = np.ones(len(pts), bool)
    if unobserved is not None and len(unobserved.points):
        n = len(unobserved.points)
        pts = np.concatenate([pts, unobserved.points])
        patch = np.concatenate([patch, np.asarray(unobserved.patch, np.float64)])
        cols = np.concatenate([cols, np.asarray(unobserved.colors, np.float32)])
        w = np.concatenate([w, np.ones(n)])
        lab = None if labels is None else np.concatenate([labels, unobserved.labels])
        seen = np.concatenate([seen, np.zeros(n, bool)])
    out = fit_voxsplat(pts - grid.origin, grid.voxel_size, colors=cols, labels=lab, weights=w,
                       patch_cov=(patch, np.arange(len(pts))), origin=grid.origin,
                       fit=FitOptions(gaussians_per_voxel=gaussians_per_voxel, max_normal_scale=max_normal_scale))
    keys = voxel_keys(out.ijk)
    observed = np.zeros(out.num_voxels, bool)
    conf = np.full(out.num_voxels, np.nan if unobserved is None else unobserved.confidence, np.float32)
    if len(grid.points):
        # a voxel is observed where an observed point lies, with the most probable occupancy among
        # its points' voxels (a point moved onto a fitted surface may have left its own)
        pos = np.searchsorted(keys, voxel_keys(voxel_of(grid.points, grid.origin, grid.voxel_size)))
        best = np.full(out.num_voxels, -np.inf)
        np.maximum.at(best, pos, grid.probability[grid.voxel])
        observed[pos] = True
        conf[observed] = best[observed]
    out.set_channel("observed", observed)
    out.set_channel("confidence", conf)
    return out


TRACE_MODE = "entry"


def _ground_samples(field: HeightField, grid, labels: np.ndarray, cfg: EvidenceConfig,
                    snapped: np.ndarray | None = None) -> SurfaceSamples:
    """Points on the height field every half voxel, in the voxel columns whose ground no observed
    voxel holds, each standing for its half-voxel square; coloured by the observed ground's mean.
    snapped: (N,) bool, the ground points moved onto the field (`snap_ground`): their columns take
    samples too, on the same surface, closing the holes between their surfels (flat at the same
    height, they leave none of the overlap that noisy heights gave a grazing ray)."""
    vs = grid.voxel_size
    step = vs / 2
    lo, hi = chunk_bounds(vs)
    n = hi[:2] * 2
    ii, jj = np.meshgrid(np.arange(n[0]), np.arange(n[1]), indexing="ij")
    xy = grid.origin[:2] + (np.stack([ii, jj], -1).reshape(-1, 2) + 0.5) * step
    z = field.height_at(xy)
    pts = np.column_stack([xy, z])
    col = np.floor((xy - grid.origin[:2]) / vs).astype(np.int64)
    covered = np.zeros(tuple(hi[:2]), bool)
    if len(grid.points):
        g = labels == GROUND_LABEL
        if snapped is not None:
            g &= ~snapped
        gij = np.floor((grid.points[g, :2] - grid.origin[:2]) / vs).astype(np.int64)
        ok = np.all((gij >= 0) & (gij < hi[:2]), 1)
        covered[gij[ok, 0], gij[ok, 1]] = True
    keep = ~covered[col[:, 0], col[:, 1]]
    keep &= (z - grid.origin[2] >= 0) & (z - grid.origin[2] < hi[2] * vs)
    pts = pts[keep]
    patch = np.zeros((len(pts), 6))
    patch[:, 0] = patch[:, 3] = step ** 2 / 12.0  # a flat square of side `step`
    ground = labels == GROUND_LABEL
    mean = grid.colors[ground].mean(0) if ground.any() else np.full(3, 0.5, np.float32)
    return SurfaceSamples(pts, patch, np.tile(mean, (len(pts), 1)).astype(np.float32),
                          np.full(len(pts), GROUND_LABEL, np.int64), cfg.ground_confidence)


# a car's silhouette inside its box (`_object_faces`): the body over the whole footprint up to this
# share of the box's height, the cabin above it on the middle half of the length (its centre this
# share of the length behind the box's), narrower by this share
CAR_BODY_HEIGHT_SHARE = 0.65


CAR_CABIN_LENGTH_SHARE = 0.5


CAR_CABIN_BACK_SHARE = 0.12


CAR_CABIN_WIDTH_SHARE = 0.88


def _cuboid_faces(center: np.ndarray, half: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The four sides and the top (no floor) of an axis-aligned cuboid, each face cut into cells at
    most `step` metres on a side: (M, 3) cell centres, (M, 3) the two tangent axes' indices and the
    normal's (per cell: a, b, k), in the cuboid's frame."""
    pts, axes = [], []
    for k, signs in ((0, (-1, 1)), (1, (-1, 1)), (2, (1,))):
        a, b = [i for i in range(3) if i != k]
        na, nb = (max(1, int(np.ceil(2 * half[i] / step))) for i in (a, b))
        u = ((np.arange(na) + 0.5) / na - 0.5) * 2 * half[a]
        v = ((np.arange(nb) + 0.5) / nb - 0.5) * 2 * half[b]
        uu, vv = np.meshgrid(u, v, indexing="ij")
        for sign in signs:
            q = np.zeros((uu.size, 3))
            q[:, a], q[:, b], q[:, k] = uu.reshape(-1), vv.reshape(-1), sign * half[k]
            pts.append(center + q)
            axes.append(np.tile([a, b, k], (uu.size, 1)))
    return np.concatenate(pts), np.concatenate(axes)


def _object_faces(box: Box, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points on the outside of the object in `box` (no floor), every `step` metres at most: a
    car's silhouette (body and cabin, `CAR_*`), any other object its box. (M, 3) points in the
    box's parent frame, (M, 6) each point's footprint covariance (xx xy xz yy yz zz; flat in its
    face, a square of side `step`)."""
    half = 0.5 * np.asarray(box.size, np.float64)
    if box.label == LABEL_IDS["car"]:
        body_top = -half[2] + 2 * half[2] * CAR_BODY_HEIGHT_SHARE
        body_c = np.array([0.0, 0.0, 0.5 * (body_top - half[2])])
        body_h = np.array([half[0], half[1], 0.5 * (body_top + half[2])])
        cab_h = np.array([half[0] * CAR_CABIN_LENGTH_SHARE, half[1] * CAR_CABIN_WIDTH_SHARE,
                          0.5 * (half[2] - body_top)])
        cab_c = np.array([-2 * half[0] * CAR_CABIN_BACK_SHARE, 0.0, body_top + cab_h[2]])
        p1, a1 = _cuboid_faces(body_c, body_h, step)
        under = (a1[:, 2] == 2) & np.all(np.abs(p1[:, :2] - cab_c[:2]) < cab_h[:2], 1)  # the body's top under the cabin
        p2, a2 = _cuboid_faces(cab_c, cab_h, step)
        local, axes = np.concatenate([p1[~under], p2]), np.concatenate([a1[~under], a2])
    else:
        local, axes = _cuboid_faces(np.zeros(3), half, step)
    rot = np.asarray(box.rotation, np.float64)
    ta, tb = rot[:, axes[:, 0]].T, rot[:, axes[:, 1]].T
    cov = (step ** 2 / 12.0) * (ta[:, :, None] * ta[:, None, :] + tb[:, :, None] * tb[:, None, :])
    return local @ rot.T + box.center, cov[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]


def box_samples(boxes: tuple[Box, ...], grid: FusedGrid, observations: list[DepthObservation], fusion: FusionConfig,
                confidence: float) -> SurfaceSamples:
    """Points on the outside of the objects in `boxes` (the grid's frame; `_object_faces`) every
    half voxel where no camera saw: none in a voxel that holds an observed point (the observation's
    surfel stands there), none in front of an image's confident depth by more than the fusion's
    carving band (the image saw through it: the box is loose there, or wrong), an image whose
    `uncarved` boxes hold the point not asked (it saw that space at another instant). Each stands
    for its half-voxel square of the face; labelled by its box, coloured by the observed points
    inside the box (grey without); `confidence` that of the voxels they alone make."""
    vs = grid.voxel_size
    parts = [_object_faces(b, vs / 2) for b in boxes]
    owner = np.concatenate([np.full(len(p), i, np.int64) for i, (p, _) in enumerate(parts)])
    pts = np.concatenate([p for p, _ in parts])
    patch = np.concatenate([c for _, c in parts])
    lo, hi = chunk_bounds(vs)
    ijk = np.floor((pts - grid.origin) / vs).astype(np.int64)
    keep = np.all((ijk >= lo) & (ijk < hi), 1)
    if len(grid.points):
        held = np.unique(voxel_keys(np.floor((grid.points - grid.origin) / vs).astype(np.int64)))
        keys = voxel_keys(ijk)
        pos = np.minimum(np.searchsorted(held, keys), len(held) - 1)
        keep &= held[pos] != keys
    for obs in observations:
        idx, flat, z = project_to_pixels(pts, obs.image)
        depth, conf = obs.depth.reshape(-1)[flat], obs.confidence.reshape(-1)[flat]
        with np.errstate(invalid="ignore"):
            through = ((conf >= fusion.min_confidence) & (depth <= fusion.max_depth_m)
                       & (depth > z + carve_band(depth, fusion)))
        if obs.uncarved:
            through &= points_in_boxes(pts[idx], list(obs.uncarved)) < 0
        keep[idx[through]] = False
    colors = np.full((len(boxes), 3), 0.5, np.float32)
    if len(grid.points):
        inside = points_in_boxes(grid.points, list(boxes))
        for i in np.unique(inside[inside >= 0]):
            colors[i] = grid.colors[inside == i].mean(0)
    labels = np.array([b.label if b.label else OTHER_LABEL for b in boxes], np.int64)
    return SurfaceSamples(pts[keep], patch[keep], colors[owner[keep]], labels[owner[keep]], confidence)


def _joined(a: SurfaceSamples, b: SurfaceSamples) -> SurfaceSamples:
    """`a` and `b` as one set of samples, at `a`'s confidence."""
    return SurfaceSamples(np.concatenate([a.points, b.points]), np.concatenate([a.patch, b.patch]),
                          np.concatenate([a.colors, b.colors]), np.concatenate([a.labels, b.labels]), a.confidence)


def scene_from_evidence(ev: Evidence, cfg: EvidenceConfig | None = None) -> VoxSplat:
    """The evidence's VoxSplat in the chunk frame: surfels on the observed points, ground surfels
    under the columns no observed ground covers, channels `observed` and `confidence`, metadata
    `trace_mode` entry (module docstring)."""
    cfg = cfg or EvidenceConfig()
    field, grid, labels = ev.field, ev.grid, ev.labels
    snapped = None
    if field is not None and cfg.ground_snap_m is not None:
        grid, snapped = snap_ground(grid, labels, field, cfg.ground_snap_m)
    samples = (_ground_samples(field, grid, labels, cfg, snapped) if (field is not None and cfg.fill_ground)
               else None)
    boxed = 0
    if cfg.fill_boxes and ev.boxes:
        extra = box_samples(ev.boxes, grid, ev.observations, cfg.fusion_at_stereo_scale(), cfg.ground_confidence)
        boxed = len(extra.points)
        samples = extra if samples is None else _joined(samples, extra)
    scene = evidence_voxsplat(grid, gaussians_per_voxel=cfg.gaussians_per_voxel, labels=labels, unobserved=samples,
                              max_normal_scale=cfg.max_normal_share * cfg.fusion.voxel_size)
    widened = (widen_surfels(scene, field, cfg.min_width_share, cfg.min_width_above_m)
               if cfg.min_width_share is not None else 0)
    scene.metadata.update({
        "source": "scube_sim.evidence",
        "frame": "chunk",
        "chunk_to_world": np.linalg.inv(ev.to_chunk).tolist(),
        "trace_mode": TRACE_MODE,
        "confidence_kind": "fused occupancy probability (unobserved ground: a constant)",
        "widened_surfels": widened,
        "box_samples": boxed,
        "ground_field": None if field is None else {"cell_m": field.cell, "measured": ev.measured,
                                                    "observed_share": float(field.observed.mean())},
    })
    return scene


def widen_surfels(scene: VoxSplat, field: HeightField | None, share: float, above_m: float) -> int:
    """Raise, in place, both tangent standard deviations of the observed Gaussians off the road whose
    centre lies more than `above_m` metres over `field` (all of them where there is no field) to at
    least `share` of the voxel (`EvidenceConfig.min_width_share`); the normal's is kept, so a surfel
    stays as flat. Returns the number of Gaussians widened."""
    vi, si = np.nonzero(scene.valid)
    off_road = scene.channels["observed"].data[vi] & (scene.labels[vi] != GROUND_LABEL)
    vi, si = vi[off_road], si[off_road]
    if field is not None and len(vi):
        mean = scene.means()[vi, si] + scene.origin
        up = mean[:, 2] - field.height_at(mean[:, :2]) > above_m
        vi, si = vi[up], si[up]
    # scales are stored as logs, the normal's first (`fit.fit_voxsplat`: ascending spread)
    log_scale = scene.params[vi, si, SCALE]
    floor = np.float32(np.log(share * scene.voxel_size))
    widened = np.maximum(log_scale[:, 1:], floor)
    changed = np.any(widened != log_scale[:, 1:], axis=1)
    log_scale[:, 1:] = widened
    scene.params[vi, si, SCALE] = log_scale
    return int(changed.sum())


def snap_ground(grid: FusedGrid, labels: np.ndarray, field: HeightField,
                band_m: float) -> tuple[FusedGrid, np.ndarray]:
    """The grid with its ground points (`labels` (N,) == road) within `band_m` metres of the height
    field moved onto it (z := the field's height at their x, y) and their footprints laid flat (no
    z in the covariance: a horizontal patch of the same trace); the voxels, their evidence and the
    other points unchanged; and the (N,) bool of the points moved. A moved point may leave its
    voxel: `evidence_voxsplat` places each point by its position."""
    z = field.height_at(grid.points[:, :2])
    move = (labels == GROUND_LABEL) & (np.abs(grid.points[:, 2] - z) <= band_m)
    points = grid.points.copy()
    points[move, 2] = z[move]
    patch = grid.patch.astype(np.float64)
    # laid flat keeping its size: the noise tilting a footprint shortened its horizontal extent,
    # and at hard opacity a surfel too small leaves a hole a ray slips through
    m = patch[move]
    flat = m[:, 0] + m[:, 3]
    scale = np.where(flat > 0, (flat + m[:, 5]) / np.where(flat > 0, flat, 1.0), 1.0)
    m[:, [0, 1, 3]] *= scale[:, None]
    m[:, [2, 4, 5]] = 0  # xz, yz, zz
    patch[move] = m
    return dataclasses.replace(grid, points=points, patch=patch.astype(grid.patch.dtype)), move
