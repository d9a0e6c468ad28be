"""The evidence-first route from camera frames to a VoxSplat, with no learning: depth measured by
multi-view stereo for every camera of the reference instant (`stereo.stereo_depth`, over the
other cameras and the context instants), fused into a sparse occupancy grid with free space
carved (`geometry.fusion`), surfels fitted to what the cameras saw, and a ground height field
(`geometry.ground`) under what they did not, labelled and marked unobserved.

Labels come from the geometry: a point within `ground_band_m` of the height field on a surface
tilted at most `ground_max_slope_deg` (its pixel's footprint normal) is `road` (the
surface a drive sees most; its reflectance default), any other `undefined` (whose reflectance
default is the measured mean of unlabelled returns above the ground). With `ground_snap_m`, the
road's points within it of the height field are moved onto it (`snap_ground`) and the field's
samples laid under them too. With `min_width_share`, the observed surfels off the road and above
the ground are at least that share of a voxel wide (`widen_surfels`). With `fill_boxes`, the
frames' boxed objects at T (a log's tracked or annotated boxes) get surfels where no camera saw
them (`box_samples`): a car its silhouette, anything else its box, labelled by the box, unobserved,
never in a voxel an observed point holds nor where an image saw through: a car waiting beside the
ego, behind the side cameras, takes a third of a 360-degree sweep's rays. The scene traces at hard
opacity (`entry`): its Gaussians are flat surfels on measured surfaces.

References (`references`, offsets from T; default T and T-3): each instant's images are stereo
references in turn (`Frames.around`), each against all the other images, and every depth map is
fused. A forward-driving camera sees the parked cars and hedges beside it at T at grazing angles
from close by, where stereo's sources disagree (KITTI-360 frame 3010: 89 % of the object pixels
within 8 m get no confidence, though 77 % of their depths are right); 3 frames back it saw them less
obliquely, farther off. Pixels whose object moved between that instant and T (boxes,
`stereo.moved_pixels`) are left out. With `stereo.movers`, each boxed object that moved is also
swept in its own frame in T's images (`stereo.mvs` step 4b: its depth at T, which the instants
around T cannot give otherwise), and the images of the other references carve nothing inside the
boxes where those objects stand at T (`DepthObservation.uncarved`). Measured on KITTI-360 frame 3010
(context 4, `scube-sim fidelity --regions`, replayed real rays above the ground in the camera's
view: median |dr|, p90, hit agreement; geometry time beside another job): [0] 1.87 m, 81 %, 26 s;
[0, -3] 0.168 m, 2.22 m, 94.6 %, 47 s; [0, -4] 0.178 m, 3.06 m, 93.2 %, 30 s; [0, -2, -4] 0.163 m,
1.58 m, 94.9 %, 78 s. Each reference costs one more stereo pass per camera. A later instant serves
too (the `evidence` profile's [0, -3, 3]): 3 instants on, the cameras see what lies ahead of T
nearer and the sides of what T passes less obliquely (held-in worlds val 0-7, HDL-64E at the input
pose, seen-object rays median / p90 / returning: [0, -3] 0.150 m / 4.25 m / 93.2 %; [0, -3, 3] 0.164
/ 2.80 / 94.9; [0, -3, 2] 0.169 / 2.91 / 94.7; [0, 3] 0.146 / 3.63 / 92.7; [0, -3, 2, 3] 0.181 /
2.71 / 95.3). Every view adds its depth noise to the road (seen ground median 0.292 -> 0.328 m with
[0, -3, 3]), which the profile's thinner surfels (`max_normal_share` 0.03) take back to 0.298 m.

Frame: the output is in the chunk frame `to_chunk` maps the world into (the converter's chunk:
x forward, z up from the road under the ego), voxels anchored at `CHUNK_CORNER` (the paper's
chunk, 10 m behind to 92 m ahead) or, for a rig with a camera looking back (nuScenes' six), on a
chunk of the same size centred on the ego (`grid_corner`): what the rear cameras saw is kept, and
the ground under it filled. The scene's `origin` is the corner either way.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from pydantic import Field, field_validator

from ..boxes import Box, points_in_boxes
from ..camera.depth import project_to_pixels
from ..camera.frames import Frames
from ..config import StrictModel, unique_names
from ..errors import InputError
from ..labels import LABEL_IDS
from ..memory import peak_mb, reset_peak
from ..splat_params import SCALE
from ..stereo import StereoConfig, moved_boxes, moved_pixels, stereo_depth
from ..voxsplat import VoxSplat, voxel_keys
from ..worlds.groundtruth import CHUNK_CORNER, CHUNK_SIZE
from .geometry.fusion import (DepthObservation, FusedGrid, FusionConfig, SurfaceSamples, carve_band,
                              evidence_voxsplat, fuse_depth)
from .geometry.ground import HeightField, fit_height_field, flat_height_field

__all__ = ["Evidence", "EvidenceConfig", "box_samples", "evidence_scene", "fuse_evidence", "measure_evidence",
           "scene_from_evidence", "snap_ground", "widen_surfels"]

TRACE_MODE = "entry"
GROUND_LABEL = LABEL_IDS["road"]
OTHER_LABEL = LABEL_IDS["undefined"]
CHUNK_HEIGHT_SHARE = 0.25  # the chunk's z extent, a share of its size (as the worlds' grids)


class EvidenceConfig(StrictModel):
    """The route's settings (module docstring)."""

    stereo: StereoConfig = Field(default_factory=StereoConfig)
    fusion: FusionConfig = Field(default_factory=FusionConfig)
    ground_cell_m: float = Field(default=1.0, ge=0.05, le=100)  # the height field's cells
    ground_band_m: float = Field(default=0.2, gt=0)  # a point this close to the height field is ground ...
    ground_max_slope_deg: float = Field(default=30.0, gt=0, le=90)  # ... if its surface tilts at most this
    ground_confidence: float = Field(default=0.5, ge=0, le=1)  # confidence of ground voxels no camera saw
    # beyond the measured ground the height field's rise over its plane decays with this length
    # (`geometry.ground.fit_height_field`; None: carried unchanged, as before 2026-12-05)
    ground_fill_decay_m: float | None = Field(default=8.0, gt=0, le=10_000)
    fill_ground: bool = True  # ground surfels under the columns no observed ground voxel covers
    # surfels on the frames' boxed objects at T where no camera saw them (a car beside the ego,
    # behind the side cameras; the far side of a car ahead): a car its silhouette, anything else its
    # box's sides and top, labelled by the box, marked unobserved at `ground_confidence`; never in a
    # voxel an observed point holds nor where an image saw through (`box_samples`)
    fill_boxes: bool = False
    gaussians_per_voxel: int = Field(default=4, ge=1, le=16)
    # the instants (offsets from T) whose images are stereo references, each against the others
    # (those the frames lack are skipped): a forward-driving camera saw the objects beside it at T
    # from farther back, less obliquely (module docstring: the trade)
    references: list[int] = Field(default_factory=lambda: [0, -3], min_length=1)
    _references_once = field_validator("references")(classmethod(lambda cls, v: unique_names(v)))
    # the surfels' thickness, a share of the voxel: depth noise spreads a voxel's points across the
    # surface, and at hard opacity a thick surfel is hit early by 3 sigma / sin(incidence) (a
    # grazing ray along the road); the build flattens LiDAR surfels the same way. Thinner gives
    # the road back its range and lets a grazing ray slip between neighbouring surfels (held-in
    # worlds val 0-7, references [0, -3, 3]: 0.1 / 0.03 / 0.01 -> seen ground median 0.328 / 0.298
    # / 0.283 m, seen-object rays p90 2.80 / 2.90 / 2.99 m; the `evidence` profile takes 0.03)
    max_normal_share: float = Field(default=0.1, gt=0)
    # an observed ground point within this of the height field is moved onto it, its footprint laid
    # flat (None: left where stereo put it). Stereo scatters the road's points about the surface
    # (worlds: seen ground median |dr| 0.3 m at hard opacity); the field, a median over 1 m cells,
    # is steadier. A step taller than this (a kerb) keeps its points (`snap_ground`)
    ground_snap_m: float | None = Field(default=None, gt=0, le=1)
    # an observed surfel off the road, its centre more than `min_width_above_m` over the height
    # field, is at least this share of the voxel wide (standard deviation along both tangents;
    # None: as fitted). Stereo is confident at texture edges, so a voxel of a car's door holds
    # points on a few centimetres of it, its surfels as small, and a ray through the rest of the
    # voxel slips between them to what lies behind; a voxel the fusion holds occupied is crossed by
    # its surface. 0.144 = 1 / (2 sqrt 12): each of the 2 x 2 Gaussians of a voxel spans its quarter
    # of the face (`widen_surfels`). Surfels near the ground keep their size: a wall's widened foot
    # meets the rays to the road before it (the `evidence` profile's comment has the trade)
    min_width_share: float | None = Field(default=None, gt=0, le=1)
    min_width_above_m: float = Field(default=0.3, ge=0, le=100)


REAR_AXIS_X = -0.5  # a camera looks back when its optical axis' forward component (chunk frame) is below this


def grid_corner(frames: Frames, to_chunk: np.ndarray) -> np.ndarray:
    """(3,) metres, chunk frame: `CHUNK_CORNER`, or the corner of a chunk of the same size centred
    on the ego where a camera of the reference instant looks back (its axis over 120 degrees from
    forward)."""
    for im in frames.images:
        axis = (np.asarray(to_chunk) @ im.cam_to_world)[:3, 2]
        if axis[0] < REAR_AXIS_X:
            return np.array([-CHUNK_SIZE / 2, -CHUNK_SIZE / 2, CHUNK_CORNER[2]])
    return np.asarray(CHUNK_CORNER, np.float64).copy()


def _chunk_bounds(voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """The chunk's voxel index range [0, hi) per axis."""
    size = np.array([CHUNK_SIZE, CHUNK_SIZE, CHUNK_SIZE * CHUNK_HEIGHT_SHARE])
    return np.zeros(3, np.int64), np.floor(size / voxel_size + 1e-9).astype(np.int64)


def _ground_samples(field: HeightField, grid, labels: np.ndarray, cfg: EvidenceConfig,
                    snapped: np.ndarray | None = None) -> SurfaceSamples:
    """Points on the height field every half voxel, in the voxel columns whose ground no observed
    voxel holds, each standing for its half-voxel square; coloured by the observed ground's mean.
    snapped: (N,) bool, the ground points moved onto the field (`snap_ground`): their columns take
    samples too, on the same surface, closing the holes between their surfels (flat at the same
    height, they leave none of the overlap that noisy heights gave a grazing ray)."""
    vs = grid.voxel_size
    step = vs / 2
    lo, hi = _chunk_bounds(vs)
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
    lo, hi = _chunk_bounds(vs)
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


@dataclasses.dataclass
class Evidence:
    """What the cameras measured, before surfels: the fused `grid` (chunk frame, cut to the chunk),
    per-point `labels` (N,) (ground / other), the ground height `field` (None: none measured and
    `fill_ground` off) and whether it was `measured`, every reference image's depth (`observations`,
    cam_to_world in the chunk frame), the chunk's `corner` (3,) metres, `to_chunk` (4, 4) and the
    frames' `boxes` at T (chunk frame)."""

    grid: FusedGrid
    labels: np.ndarray
    field: HeightField | None
    measured: bool
    observations: list[DepthObservation]
    corner: np.ndarray
    to_chunk: np.ndarray
    boxes: tuple[Box, ...] = ()  # the frames' boxed objects at T, chunk frame (`EvidenceConfig.fill_boxes`)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x0, x1, y0, y1) metres, chunk frame: the chunk's footprint."""
        c = self.corner
        return (c[0], c[0] + CHUNK_SIZE, c[1], c[1] + CHUNK_SIZE)


def measure_evidence(frames: Frames, to_chunk: np.ndarray, cfg: EvidenceConfig | None = None, *,
                     progress: bool = False, timings: dict | None = None) -> Evidence:
    """Frames -> the `Evidence` in the chunk frame (`to_chunk` (4, 4): world -> chunk): stereo per
    reference image, fusion, the ground height field and the points' labels (module docstring).
    `timings`, if given, receives stereo_s and fusion_s (seconds)."""
    cfg = cfg or EvidenceConfig()
    to_chunk = np.asarray(to_chunk, np.float64)
    if to_chunk.shape != (4, 4) or not np.all(np.isfinite(to_chunk)):
        raise InputError(f"evidence_scene: to_chunk must be a finite (4, 4) pose, got shape {to_chunk.shape}")
    t0 = time.perf_counter()
    observations = []
    have = {f.offset - frames.offset for f in frames.instants()}
    for offset in dict.fromkeys(cfg.references):
        if offset not in have:  # a log's first or last instants: fewer references
            continue
        at = frames.around(offset)
        for k, im in enumerate(at.images):
            if im.intrinsics.model == "fisheye":  # stereo refuses it; the others still measure
                continue
            # a moving object's own-frame depth is kept at T only (below: elsewhere it is not where seen)
            res = stereo_depth(at, k, cfg.stereo, progress=progress, movers=cfg.stereo.movers and offset == 0)
            conf = res.confidence
            uncarved = ()
            if offset != 0 and (at.boxes or frames.boxes):
                # an object that moved between this instant and T is not where this image saw it
                conf = np.where(moved_pixels(im, at.boxes, frames.boxes, cfg.stereo), np.float32(0), conf)
                if cfg.stereo.movers:
                    # nor is the space where it stands at T free because this image saw through it
                    uncarved = tuple(_in_frame(b, to_chunk, cfg.stereo.box_margin_m)
                                     for b in moved_boxes(at.boxes, frames.boxes, cfg.stereo)[1])
            moved = dataclasses.replace(im, cam_to_world=to_chunk @ im.cam_to_world)
            observations.append(DepthObservation(moved, res.depth, conf, uncarved))
    t1 = time.perf_counter()
    movers = ()
    if cfg.stereo.movers:  # their surfaces at T, measured: a car's hood is no road
        here = {id(b): b for f in frames.context for b in moved_boxes(frames.boxes, f.boxes, cfg.stereo)[0]}
        movers = tuple(_in_frame(b, to_chunk, cfg.stereo.box_margin_m) for b in here.values())
    ev = fuse_evidence(observations, grid_corner(frames, to_chunk), to_chunk, cfg, objects=movers,
                       boxes=tuple(_in_frame(b, to_chunk, 0.0) for b in frames.boxes))
    if timings is not None:
        timings.update({"stereo_s": t1 - t0, "fusion_s": time.perf_counter() - t1})
    return ev


def _in_frame(box: Box, pose: np.ndarray, margin_m: float) -> Box:
    """`box` moved by `pose` (4, 4) into another frame, `margin_m` larger on every side (its label,
    instance and ids kept)."""
    return dataclasses.replace(box, center=pose[:3, :3] @ box.center + pose[:3, 3], size=box.size + 2 * margin_m,
                               rotation=pose[:3, :3] @ box.rotation, velocity=pose[:3, :3] @ box.velocity, yaw=None)


def fuse_evidence(observations: list[DepthObservation], corner: np.ndarray, to_chunk: np.ndarray,
                  cfg: EvidenceConfig | None = None, *, objects: tuple[Box, ...] = (),
                  boxes: tuple[Box, ...] = ()) -> Evidence:
    """The depth maps (cam_to_world in the chunk frame) -> the `Evidence`: fusion on the chunk whose
    corner is `corner` (3,) metres, the ground height field and the points' labels (the part of
    `measure_evidence` after stereo: fusion settings can be compared on the same depth maps).
    objects: boxes (chunk frame) whose points are no ground (neither fit the field nor get its label).
    boxes: the boxed objects at T (chunk frame), kept in the `Evidence` (`fill_boxes`)."""
    cfg = cfg or EvidenceConfig()
    # the depth maps hold one measurement per 1 / scale pixels (`FusionConfig.pixel_stride`)
    fusion = fusion_config(cfg)
    grid = fuse_depth(observations, fusion, origin=corner)
    lo, hi = _chunk_bounds(cfg.fusion.voxel_size)
    inside = np.all((grid.ijk >= lo) & (grid.ijk < hi), 1)
    if not inside.all():  # evidence beyond the chunk: dropped with its points
        grid = _select(grid, inside)
    extent = (corner[0], corner[0] + CHUNK_SIZE, corner[1], corner[1] + CHUNK_SIZE)
    # the ground: points on surfaces facing up (a wall's foot is within a kerb's height of the road)
    flat = np.abs(grid.normals[:, 2]) >= np.cos(np.radians(cfg.ground_max_slope_deg))
    if objects:
        flat &= points_in_boxes(grid.points, list(objects)) < 0
    field = (fit_height_field(grid.points[flat], extent, cell=cfg.ground_cell_m, fill_decay_m=cfg.ground_fill_decay_m)
             if flat.sum() >= 3 else None)
    measured = field is not None
    if field is None and cfg.fill_ground:
        # no ground measured (no confident depth, or none facing up): the road the ego stands on
        field = flat_height_field(extent, cell=cfg.ground_cell_m)
    if field is not None:
        near = np.abs(grid.points[:, 2] - field.height_at(grid.points[:, :2])) <= cfg.ground_band_m
        labels = np.where(near & flat, GROUND_LABEL, OTHER_LABEL).astype(np.int64)
    else:
        labels = np.full(len(grid.points), OTHER_LABEL, np.int64)
    return Evidence(grid, labels, field, measured, observations, corner, np.asarray(to_chunk, np.float64),
                    tuple(boxes))


def fusion_config(cfg: EvidenceConfig) -> FusionConfig:
    """The fusion settings the route uses: `cfg.fusion` with the depth maps' pixel stride (a depth
    map at stereo scale s holds one measurement per 1 / s pixels)."""
    return cfg.fusion.model_copy(update={"pixel_stride": max(1, round(1.0 / cfg.stereo.scale))})


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
        extra = box_samples(ev.boxes, grid, ev.observations, fusion_config(cfg), cfg.ground_confidence)
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


def evidence_scene(frames: Frames, to_chunk: np.ndarray, cfg: EvidenceConfig | None = None, *,
                   progress: bool = False, timings: dict | None = None) -> VoxSplat:
    """Frames -> VoxSplat in the chunk frame (`to_chunk` (4, 4): world -> chunk) (module docstring),
    labels from the geometry, channels `observed` and `confidence`, metadata `trace_mode` entry.
    Same frames, same bytes, whatever the thread count (no timings in the file); `timings`, if
    given, receives stereo_s, fusion_s (seconds) and peak_mb."""
    cfg = cfg or EvidenceConfig()
    reset_peak()
    parts: dict = {}
    t0 = time.perf_counter()
    ev = measure_evidence(frames, to_chunk, cfg, progress=progress, timings=parts)
    scene = scene_from_evidence(ev, cfg)
    scene.metadata.update({"cameras": list(frames.names), "timestamp": float(frames.timestamp)})
    if timings is not None:
        # fusion_s: fusion, ground and surfels (everything after stereo)
        timings.update({"stereo_s": parts["stereo_s"], "fusion_s": time.perf_counter() - t0 - parts["stereo_s"],
                        "peak_mb": peak_mb()})
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


def _select(grid, keep: np.ndarray):
    """The grid with only the occupied voxels `keep` (V,) bool and their points."""
    new_index = np.cumsum(keep) - 1
    pk = keep[grid.voxel]
    return dataclasses.replace(grid, ijk=grid.ijk[keep], logodds=grid.logodds[keep], hits=grid.hits[keep],
                               misses=grid.misses[keep], points=grid.points[pk], weights=grid.weights[pk],
                               colors=grid.colors[pk], patch=grid.patch[pk], normals=grid.normals[pk],
                               voxel=new_index[grid.voxel[pk]])
