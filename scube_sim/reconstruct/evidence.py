"""The evidence-first route from camera frames to a VoxSplat, with no learning: depth measured by
multi-view stereo for every camera of the reference instant (`stereo.stereo_depth`, over the
other cameras and the context instants), fused into a sparse occupancy grid with free space
carved (`fusion`), surfels fitted to what the cameras saw, and a ground height field
(`ground`) under what they did not, labelled and marked unobserved.

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
ego, behind the side cameras, fills much of a 360-degree sweep. The scene traces at hard
opacity (`entry`): its Gaussians are flat surfels on measured surfaces.

References (`references`, offsets from T; default T and T-3): each instant's images are stereo
references in turn (`Frames.around`), each against all the other images, and every depth map is
fused. A forward-driving camera sees the parked cars and hedges beside it at T at grazing angles
from close by, where stereo's sources disagree and most depths get no confidence, right or not;
3 frames back it saw them less obliquely, farther off. A later instant serves too (the `evidence`
profile's [0, -3, 3]): 3 instants on, the cameras see what lies ahead of T nearer and the sides
of what T passes less obliquely. Each reference costs one more stereo pass per camera, and every
view adds its depth noise to the road, which thinner surfels (`max_normal_share`) take back.
Pixels whose object moved between that instant and T (boxes, `stereo.moved_pixels`) are left out.
With `stereo.movers`, each boxed object that moved is also swept in its own frame in T's images
(`reconstruct.stereo.mvs` step 4b: its depth at T, which the instants around T cannot give
otherwise), and the images of the other references carve nothing inside the boxes where those
objects stand at T (`DepthObservation.uncarved`).

Frame: the output is in the chunk frame `to_chunk` maps the world into (the converter's chunk:
x forward, z up from the road under the ego), voxels anchored at `CHUNK_CORNER` (the paper's
chunk, 10 m behind to 92 m ahead) or, for a rig with a camera looking back (nuScenes' six), on a
chunk of the same size centred on the ego (`grid_corner`): what the rear cameras saw is kept, and
the ground under it filled. The scene's `origin` is the corner either way.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable

import numpy as np

from ..boxes import Box, points_in_boxes
from ..camera.frames import Frames
from ..errors import InputError
from ..worlds.groundtruth import CHUNK_CORNER, CHUNK_SIZE
from .config import CHUNK_HEIGHT_SHARE, GROUND_LABEL, OTHER_LABEL, EvidenceConfig
from .fusion import DepthObservation, FusedGrid, fuse_depth
from .ground import HeightField, fit_height_field, flat_height_field
from .stereo import moved_boxes, moved_pixels, stereo_depth

__all__ = ["Evidence", "chunk_bounds", "fuse_evidence", "grid_corner", "measure_evidence"]


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


def chunk_bounds(voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """The chunk's voxel index range [0, hi) per axis."""
    size = np.array([CHUNK_SIZE, CHUNK_SIZE, CHUNK_SIZE * CHUNK_HEIGHT_SHARE])
    return np.zeros(3, np.int64), np.floor(size / voxel_size + 1e-9).astype(np.int64)


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
                     status: Callable[[str], None] | None = None, timings: dict | None = None) -> Evidence:
    """Frames -> the `Evidence` in the chunk frame (`to_chunk` (4, 4): world -> chunk): stereo per
    reference image, fusion, the ground height field and the points' labels (module docstring).
    `timings`, if given, receives stereo_s and fusion_s (seconds); `status`, if given, is called
    with one line as each reference image's stereo and then the fusion starts."""
    cfg = cfg or EvidenceConfig()
    to_chunk = np.asarray(to_chunk, np.float64)
    if to_chunk.shape != (4, 4) or not np.all(np.isfinite(to_chunk)):
        raise InputError(f"measure_evidence: to_chunk must be a finite (4, 4) pose, got shape {to_chunk.shape}")
    t0 = time.perf_counter()
    observations = []
    have = {f.offset - frames.offset for f in frames.instants()}
    # a log's first or last instants give fewer references; stereo refuses fisheye images
    todo = [(offset, k) for offset in dict.fromkeys(cfg.references) if offset in have
            for k, im in enumerate(frames.around(offset).images) if im.intrinsics.model != "fisheye"]
    for i, (offset, k) in enumerate(todo, 1):
        at = frames.around(offset)
        im = at.images[k]
        if status:
            status(f"stereo {i}/{len(todo)}: {im.name} at instant {offset:+d}")
        # a moving object's own-frame depth is kept at T only (below: elsewhere it is not where seen)
        res = stereo_depth(at, k, cfg.stereo, movers=cfg.stereo.movers and offset == 0)
        conf = res.confidence
        uncarved = ()
        if offset != 0 and (at.boxes or frames.boxes):
            # an object that moved between this instant and T is not where this image saw it
            conf = np.where(moved_pixels(im, at.boxes, frames.boxes, cfg.stereo), np.float32(0), conf)
            if cfg.stereo.movers:
                # nor is the space where it stands at T free because this image saw through it
                uncarved = tuple(box_in_frame(b, to_chunk, cfg.stereo.box_margin_m)
                                 for b in moved_boxes(at.boxes, frames.boxes, cfg.stereo)[1])
        moved = dataclasses.replace(im, cam_to_world=to_chunk @ im.cam_to_world)
        observations.append(DepthObservation(moved, res.depth, conf, uncarved))
    t1 = time.perf_counter()
    if status:
        status(f"fusion of {len(observations)} depth maps, the ground and the surfels")
    movers = ()
    if cfg.stereo.movers:  # their surfaces at T, measured: a car's hood is no road
        here = {id(b): b for f in frames.context for b in moved_boxes(frames.boxes, f.boxes, cfg.stereo)[0]}
        movers = tuple(box_in_frame(b, to_chunk, cfg.stereo.box_margin_m) for b in here.values())
    ev = fuse_evidence(observations, grid_corner(frames, to_chunk), to_chunk, cfg, objects=movers,
                       boxes=tuple(box_in_frame(b, to_chunk, 0.0) for b in frames.boxes))
    if timings is not None:
        timings.update({"stereo_s": t1 - t0, "fusion_s": time.perf_counter() - t1})
    return ev


def box_in_frame(box: Box, pose: np.ndarray, margin_m: float) -> Box:
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
    fusion = cfg.fusion_at_stereo_scale()
    grid = fuse_depth(observations, fusion, origin=corner)
    lo, hi = chunk_bounds(cfg.fusion.voxel_size)
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


def _select(grid, keep: np.ndarray):
    """The grid with only the occupied voxels `keep` (V,) bool and their points."""
    new_index = np.cumsum(keep) - 1
    pk = keep[grid.voxel]
    return dataclasses.replace(grid, ijk=grid.ijk[keep], logodds=grid.logodds[keep], hits=grid.hits[keep],
                               misses=grid.misses[keep], points=grid.points[pk], weights=grid.weights[pk],
                               colors=grid.colors[pk], patch=grid.patch[pk], normals=grid.normals[pk],
                               voxel=new_index[grid.voxel[pk]])
