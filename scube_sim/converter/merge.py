"""The completion's merge: the network's coarse occupancy and labels joined with the evidence
VoxSplat, the observation winning wherever the two disagree.

Per coarse cell (`features` grid) the network gives an occupancy probability p and a label:

- **added**: a cell gets one round Gaussian at its centre, labelled by the network, `observed` 0,
  `confidence` p, when all of these hold:
  - p >= `add_threshold` (0.9): lower, the network's unsure cells are often empty in the truth,
    and their blobs stand on the road a LiDAR ahead sees;
  - it holds no observed voxel, and fewer than `free_veto_samples` free-space rays crossed it (the
    cameras saw through it: it stays empty whatever the network says);
  - it borders a cell below the threshold (a surface, not the inside of a building);
  - its label is not a ground class (the height field already holds the ground no camera saw);
  - its Gaussian would not reach into the ego's body at any instant given (`ego_box`, grown by the
    sphere's radius), nor is it joined (26-neighbours, among the cells to add) to one that would: no
    camera sees the space the ego filled, and a network that learnt that a hole in the road is a
    car puts one there, inside the LiDAR's minimum range;
  - with `footprint_height_m` set (off by default), a cell whose centre lies under that height over
    the ground height field has a body standing on it (the cell above occupied and not seen through,
    or observed): a ground cell with nothing above is the ground labelled as an object or a
    building's floor, which no sensor outside sees; off, because those floors also stand for the
    foot of walls nobody saw;
  - with `objects_in_boxes`, where the frames carry boxes, a vehicle, rider or pedestrian cell lies
    inside one of them (`BOXED_IDS`: the boxes say where those stand).
  The sphere's 3-sigma radius is `blob_radius` (0.75 of the cell, so that four neighbours' spheres
  close the gap between them at hard opacity): where in the cell the surface lies, nobody measured.
  With a network's sub-cell head, one Gaussian on each sub-cell it holds occupied instead
  (`subcell_threshold`, its sphere the same share of the sub-cell); or, `subcell_mode` centroid, the
  cell's one sphere moved to its sub-cells' centres weighted by their probabilities. The centred
  sphere is the default: smaller or moved spheres open gaps between neighbours that rays slip through.
- **removed**: an observed voxel above the ground (not labelled a ground class) whose fused
  probability is below `keep_confidence` (one view's unsure stereo) in a cell with p <
  `remove_threshold` is dropped as noise; ground voxels are spared, since dropping them opens holes
  in the road. A voxel at or above `keep_confidence` is never removed, whatever p.
- **labelled**: an observed voxel in a cell with p >= `add_threshold` takes the network's label
  there (the geometry alone knows only ground and not ground); the rest keep theirs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field, model_validator
from scipy import ndimage

from .. import splat_params as sp
from ..boxes import Box, points_in_boxes
from ..config import StrictModel
from ..labels import GROUND_LABEL_NAMES, LABEL_IDS
from ..model.completion.features import FEATURES, FREE_RAYS_FULL, HEIGHT_SCALE_M
from ..voxsplat import Channel, Gaussians, VoxSplat, voxel_keys

__all__ = ["CompletionConfig", "in_ego_box", "merge_completion"]

GROUND_IDS = np.array(sorted(LABEL_IDS[n] for n in GROUND_LABEL_NAMES), np.int64)
# the classes a log's boxes hold (`CompletionConfig.objects_in_boxes`)
BOXED_IDS = np.array(sorted(LABEL_IDS[n] for n in ("car", "truck", "bus", "other_vehicle", "motorcyclist", "bicyclist",
                                                  "pedestrian", "bicycle", "motorcycle")), np.int64)
_FREE_RAYS = FEATURES.index("free_rays")
_HEIGHT = FEATURES.index("height")


class CompletionConfig(StrictModel):
    """A profile's `completion:` section (module docstring for the merge's rules)."""

    checkpoint: str  # a shipped name or a path
    # the occupancy a cell needs to be added or to relabel observed voxels: lower adds the network's
    # unsure cells, often empty in the truth (module docstring)
    add_threshold: float = Field(default=0.9, gt=0, lt=1)
    remove_threshold: float = Field(default=0.1, ge=0, lt=1)
    keep_confidence: float = Field(default=0.65, ge=0, le=1)
    free_veto_samples: int = Field(default=3, ge=1, le=10_000)
    blob_radius: float = Field(default=0.75, gt=0, le=2)  # an added cell's 3-sigma sphere, a share of the cell
    # with a sub-cell head: an added cell's sub-cells at or above this get a Gaussian each (its most
    # probable one always), the sphere then a share of the sub-cell
    subcell_threshold: float = Field(default=0.5, gt=0, le=1)
    # "spheres": one Gaussian a chosen sub-cell (subcell_threshold); "centroid": the cell's one
    # sphere, as without sub-cells, moved to its sub-cells' centres weighted by their probabilities
    subcell_mode: Literal["spheres", "centroid"] = "spheres"
    relabel: bool = True
    # where the frames carry boxes (a log's tracked or annotated objects), a cell the network labels
    # as a class such boxes hold (`BOXED_IDS`: vehicles, riders, pedestrians) is added only where its
    # centre lies in one of them: the boxes say where those objects stand, and the evidence route
    # already fills the boxed ones no camera saw (`EvidenceConfig.fill_boxes`). Turn on where the
    # boxes are complete (as the default profile does): it drops blobs of objects drawn where none
    # stand; off by default, since a log whose boxes miss objects loses their blobs
    objects_in_boxes: bool = False
    # an added cell whose centre lies under this height over the ground height field needs an
    # occupied cell above it (0: off, the default; 0.4, half a 0.8 m cell: the cell that holds the
    # ground). On, it spares the unseen ground but drops the foot of walls and objects nobody saw
    footprint_height_m: float = Field(default=0.0, ge=0, le=25.6)
    # the ego car's body, ego frame on the road (x forward, metres): wide enough for a frame whose
    # origin is the rear axle (nuScenes, Waymo: about 1 m of car behind it and 4 ahead) and for one
    # at the car's centre (2.5 behind); 2.2 m wide, 2 m high
    ego_box_min: tuple[float, float, float] = (-2.5, -1.1, 0.0)
    ego_box_max: tuple[float, float, float] = (4.0, 1.1, 2.0)

    @model_validator(mode="after")
    def _box_order(self):
        if any(a >= b for a, b in zip(self.ego_box_min, self.ego_box_max)):
            raise ValueError(f"ego_box_min must be below ego_box_max on each axis, got {self.ego_box_min} "
                             f"and {self.ego_box_max}")
        return self



@dataclass
class CompletionGrid:
    """The completion network's coarse grid, for scoring (`eval sensor-to-sensor`): occupancy (X, Y, Z)
    float64 probabilities, labels (X, Y, Z) int64, the input features (C, X, Y, Z) float32, the grid's
    corner (3,) metres in the chunk frame and its voxel_size, metres."""

    occupancy: np.ndarray
    labels: np.ndarray
    features: np.ndarray
    corner: np.ndarray
    voxel_size: float


def _free_samples(features: np.ndarray) -> np.ndarray:
    """The ray samples per cell, back from the `free_rays` channel (features docstring)."""
    v = features[_FREE_RAYS].astype(np.float64)
    return np.where(v >= 1.0, np.inf, np.expm1(v * np.log1p(FREE_RAYS_FULL)))


def in_ego_box(points: np.ndarray, ego_poses: np.ndarray, cfg: CompletionConfig, grow: float = 0.0) -> np.ndarray:
    """(N,) bool: which chunk-frame points (N, 3) lie inside the ego's box (`cfg.ego_box_min` /
    `max`, grown by `grow` metres on every side) at any of the instants whose ego-to-chunk poses
    `ego_poses` (K, 4, 4) are given."""
    lo = np.asarray(cfg.ego_box_min, np.float64) - grow
    hi = np.asarray(cfg.ego_box_max, np.float64) + grow
    inside = np.zeros(len(points), bool)
    for pose in np.asarray(ego_poses, np.float64).reshape(-1, 4, 4):
        local = (points - pose[:3, 3]) @ pose[:3, :3]  # chunk -> that instant's ego frame
        inside |= np.all((local >= lo) & (local <= hi), axis=1)
    return inside


def _subcells_per_side(sub_shape: tuple, dims: np.ndarray) -> int:
    """s: the sub-cells per cell side of a sub-cell grid `sub_shape` (sX, sY, sZ) over cells `dims`."""
    s = sub_shape[0] // int(dims[0])
    if s < 1 or tuple(sub_shape) != tuple(int(d) * s for d in dims):
        raise ValueError(f"merge_completion: sub-cells {tuple(sub_shape)} are not a whole multiple of the "
                         f"cells {tuple(int(d) for d in dims)}")
    return s


def _subcells_of(ai: np.ndarray, subcells: np.ndarray, s: int) -> tuple[np.ndarray, np.ndarray]:
    """The s^3 sub-cells of each cell `ai` (A, 3): their indices (A, s^3, 3) in `subcells` (sX, sY,
    sZ) and their probabilities (A, s^3)."""
    offsets = np.stack(np.meshgrid(*[np.arange(s)] * 3, indexing="ij"), -1).reshape(-1, 3)
    sub_ijk = ai[:, None, :] * s + offsets[None]
    return sub_ijk, subcells[sub_ijk[..., 0], sub_ijk[..., 1], sub_ijk[..., 2]]


def _subcell_centres(ai: np.ndarray, subcells: np.ndarray, s: int, corner: np.ndarray, voxel_size: float,
                     threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Where the Gaussians of the added cells `ai` (A, 3) go: their sub-cells (s per side; their
    probabilities `subcells` (sX, sY, sZ)) at or above `threshold`, and each cell's most probable
    one whatever it holds (the cell is added: its surface lies somewhere in it). Returns (each
    Gaussian's index into `ai` (G,), its centre (G, 3), chunk frame, metres)."""
    sub_ijk, p = _subcells_of(ai, subcells, s)
    chosen = p >= threshold
    chosen[np.arange(len(ai)), np.argmax(p, 1)] = True
    cell, k = np.nonzero(chosen)
    return cell, corner + (sub_ijk[cell, k] + 0.5) * (voxel_size / s)


def _subcell_centroids(ai: np.ndarray, subcells: np.ndarray, s: int, corner: np.ndarray,
                       voxel_size: float) -> np.ndarray:
    """(A, 3) the added cells' `ai` (A, 3) sub-cell centres weighted by their probabilities
    `subcells` (sX, sY, sZ), chunk frame, metres: where the cell's one sphere goes."""
    sub_ijk, p = _subcells_of(ai, subcells, s)
    w = p / np.maximum(p.sum(1, keepdims=True), 1e-12)
    return corner + (np.einsum("ak,akd->ad", w, sub_ijk.astype(np.float64)) + 0.5) * (voxel_size / s)


def merge_completion(scene: VoxSplat, grid: CompletionGrid, cfg: CompletionConfig, *,
                     ego_poses: np.ndarray | None = None,
                     subcells: np.ndarray | None = None, boxes: tuple[Box, ...] = ()) -> tuple[VoxSplat, dict]:
    """The evidence `scene` (chunk frame; channels `observed`, `confidence`) with the network's
    coarse `grid` merged (module docstring): its occupancy probabilities and label ids on the cells
    of `grid.voxel_size` metres from `grid.corner`, whose input was `grid.features`.
    ego_poses: (K, 4, 4) ego-to-chunk poses (on the road) of the instants the evidence came from,
    whose ego boxes nothing is added into (default: the chunk origin's alone). boxes: the frames'
    boxed objects at T (chunk frame; `cfg.objects_in_boxes`). Returns (the scene, counts: cells
    added, ground cells left out for want of a body above, cells kept out of the ego's box (or
    joined to it), object cells left out for lying in no box, observed voxels removed, relabelled,
    and the observed voxels before)."""
    features, occupancy, labels, corner = grid.features, grid.occupancy, grid.labels, grid.corner
    dims = np.array(occupancy.shape)
    vs = float(grid.voxel_size)
    observed = scene.channel("observed").astype(bool)
    conf = scene.channel("confidence").astype(np.float32)  # compared as stored
    centres = scene.origin + scene.voxel_centers()
    cell = np.floor((centres - corner) / vs).astype(np.int64)
    inside = np.all((cell >= 0) & (cell < dims), 1)
    c = np.where(inside[:, None], cell, 0)
    p_vox = np.where(inside, occupancy[c[:, 0], c[:, 1], c[:, 2]], 1.0)
    lab_vox = labels[c[:, 0], c[:, 1], c[:, 2]]

    # removed: unsure observations above the ground the network finds empty (the ground's voxels
    # stay: the road lies a few cm from a coarse cell's floor, and a cell the network holds empty
    # under it would open holes the height field does not fill, as those columns hold observed ground)
    ground = np.isin(scene.labels.astype(np.int64), GROUND_IDS)
    drop = observed & ~ground & (conf < np.float32(cfg.keep_confidence)) & (p_vox < cfg.remove_threshold) & inside
    # labelled: observed voxels in cells the network holds occupied
    relabel = observed & ~drop & inside & (p_vox >= cfg.add_threshold) if cfg.relabel else np.zeros_like(drop)
    new_labels = scene.labels.copy()
    new_labels[relabel] = lab_vox[relabel]

    # added: confident cells nothing observed, not seen through, on a surface, not ground
    occ = occupancy >= cfg.add_threshold
    held = np.zeros(dims, bool)
    oc = c[observed & inside]
    held[oc[:, 0], oc[:, 1], oc[:, 2]] = True
    pad = np.pad(occupancy, 1, constant_values=0.0)
    border = np.zeros(dims, bool)
    for axis in range(3):
        for sign in (-1, 1):
            sl = [slice(1, -1)] * 3
            sl[axis] = slice(1 + sign, dims[axis] + 1 + sign)
            border |= pad[tuple(sl)] < cfg.add_threshold
    unseen = _free_samples(features) < cfg.free_veto_samples
    add = occ & ~held & border & unseen & ~np.isin(labels, GROUND_IDS)
    footprint = np.zeros(dims, bool)
    if cfg.footprint_height_m > 0:
        on_ground = features[_HEIGHT].astype(np.float64) * HEIGHT_SCALE_M < cfg.footprint_height_m
        body = (occ & unseen) | held
        body_above = np.zeros(dims, bool)
        body_above[:, :, :-1] = body[:, :, 1:]
        footprint = add & on_ground & ~body_above
        add &= ~footprint
    ai = np.argwhere(add)
    a_centres = corner + (ai + 0.5) * vs
    # the ego's box: no cell whose sphere reaches into it, nor any cell joined to one (a car the
    # network puts where the ego stands is wider than the box: the ring of cells around it would
    # stay and swallow the LiDAR's near rays)
    ego = in_ego_box(a_centres, np.eye(4)[None] if ego_poses is None else ego_poses, cfg, grow=cfg.blob_radius * vs)
    if ego.any():
        parts, _ = ndimage.label(add, structure=np.ones((3, 3, 3), bool))
        part = parts[ai[:, 0], ai[:, 1], ai[:, 2]]
        ego = np.isin(part, np.unique(part[ego]))
    ai, a_centres = ai[~ego], a_centres[~ego]
    unboxed = np.zeros(len(ai), bool)
    if cfg.objects_in_boxes and boxes and len(ai):
        unboxed = (np.isin(labels[ai[:, 0], ai[:, 1], ai[:, 2]], BOXED_IDS)
                   & (points_in_boxes(a_centres, list(boxes)) < 0))
        ai, a_centres = ai[~unboxed], a_centres[~unboxed]
    # the Gaussians: one at each added cell's centre, or at its chosen sub-cells' centres
    g_cell, g_centres, g_size = np.arange(len(ai)), a_centres, np.full(len(ai), vs)
    if subcells is not None and len(ai):
        n_sub = _subcells_per_side(subcells.shape, dims)
        if cfg.subcell_mode == "centroid":
            g_centres = _subcell_centroids(ai, subcells, n_sub, corner, vs)
        else:
            g_cell, g_centres = _subcell_centres(ai, subcells, n_sub, corner, vs, cfg.subcell_threshold)
            g_size = np.full(len(g_cell), vs / n_sub)
    a_local = g_centres - scene.origin
    a_keys = voxel_keys(np.floor(a_local / scene.voxel_size).astype(np.int64))
    keys = voxel_keys(scene.ijk.astype(np.int64))
    _, first = np.unique(a_keys, return_index=True)
    once = np.zeros(len(a_keys), bool)
    once[first] = True  # sub-cells finer than the scene's voxels: one Gaussian a voxel
    clash = np.isin(a_keys, keys[~drop]) | ~once  # a fine voxel the scene holds (ground fill): keep the scene's
    g_cell, a_local, a_keys, g_size = g_cell[~clash], a_local[~clash], a_keys[~clash], g_size[~clash]
    ai_g = ai[g_cell]
    ai = np.unique(ai_g, axis=0) if len(ai_g) else ai_g
    p_add = occupancy[ai_g[:, 0], ai_g[:, 1], ai_g[:, 2]] if len(ai_g) else np.zeros(0)
    l_add = labels[ai_g[:, 0], ai_g[:, 1], ai_g[:, 2]] if len(ai_g) else np.zeros(0, np.int64)

    base = scene.select_voxels(~drop)
    n_add = len(a_local)
    if n_add:
        m = scene.gaussians_per_voxel
        sigma = cfg.blob_radius * g_size / 3.0  # traced at hard opacity: the 3-sigma sphere
        g = Gaussians(means=a_local, scales=np.repeat(sigma[:, None], 3, 1), quats=np.tile([1.0, 0, 0, 0], (n_add, 1)),
                      opacities=np.ones(n_add),
                      sh_dc=np.zeros((n_add, 3), np.float32), origin=scene.origin)
        extra = VoxSplat.from_gaussians(g, scene.voxel_size, labels=l_add, offset_range=scene.offset_range,
                                        origin=scene.origin)
        # each added Gaussian has a fine voxel of its own (at its cell's or sub-cell's centre)
        sorted_keys = np.sort(a_keys)
        where = np.searchsorted(sorted_keys, voxel_keys(extra.ijk.astype(np.int64)))
        p_extra = p_add[np.argsort(a_keys, kind="stable")][where]
        params = np.zeros((extra.num_voxels, m, extra.params.shape[2]), np.float32)
        params[:, :, 3] = sp.EMPTY_OPACITY_RAW
        params[:, :, 7] = 1.0  # identity quaternion in the empty slots
        params[:, :1] = extra.params[:, :1]
        valid = np.zeros((extra.num_voxels, m), bool)
        valid[:, 0] = True
        channels = {}
        for name, ch in base.channels.items():
            if ch.per == "scene":
                channels[name] = ch
            elif name == "observed":
                channels[name] = Channel(ch.per, np.concatenate([ch.data, np.zeros(extra.num_voxels, ch.data.dtype)]))
            elif name == "confidence":
                channels[name] = Channel(ch.per, np.concatenate([ch.data, p_extra.astype(ch.data.dtype)]))
            else:
                raise ValueError(f"merge_completion: no value for channel {name!r} on added voxels")
        merged = VoxSplat(np.concatenate([base.ijk, extra.ijk]), np.concatenate([base.params, params]),
                          base.voxel_size, base.origin, np.concatenate([base.valid, valid]),
                          np.concatenate([new_labels[~drop], extra.labels]), None, base.offset_range,
                          dict(base.metadata), channels)
    else:
        merged = base
        merged.labels = new_labels[~drop].astype(np.int16)
    merged = merged.select_voxels(np.argsort(voxel_keys(merged.ijk.astype(np.int64)), kind="stable"))
    counts = {"added_cells": int(len(ai)), "added_gaussians": int(n_add), "footprint_cells": int(footprint.sum()),
              "ego_box_cells": int(ego.sum()), "unboxed_cells": int(unboxed.sum()), "removed_voxels": int(drop.sum()),
              "relabelled_voxels": int(relabel.sum()), "observed_voxels": int(observed.sum())}
    return merged, counts
