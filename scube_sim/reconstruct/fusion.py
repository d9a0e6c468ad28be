"""Evidence fusion: per-image depth and confidence maps (stereo, `stereo.stereo_depth`) integrated
into a sparse voxel grid as occupancy log-odds, free space carved along each pixel's ray.

Occupancy follows OctoMap (Hornung et al. 2013): per image, a voxel that holds a pixel's point is
a hit, a voxel its ray passes through before the point (short of a band for the depth's error) is
a miss, a hit winning over a miss of the same image; an update adds `hit_logodds` or
`miss_logodds` times the mean confidence of the pixels behind it, once per image (a near surface
covering thousands of pixels counts once per view, not a thousand times). A voxel is occupied
where its log-odds reach `occupied_logodds`.

Sparse: only voxels that some pixel's point falls in (the candidates) are tracked; a miss
elsewhere is dropped (nothing there to carve). The walk along the rays (`_misses`, each ray
sampled every half voxel) runs in the compiled trace core where it is built (`compiled.carve_misses`,
the same bytes as the NumPy walk it is tested against, and faster: `python -m bench.bench_fusion`
compares them). So a wall seen at 5 m in one view and seen through
to 10 m by a later confident view loses its 5 m voxels (tests/model/test_fusion.py), and memory
grows with the surfaces, not with the volume (a dense 0.2 m chunk is 512^3 cells).

Open3D's `VoxelBlockGrid.integrate` (a TSDF) does not serve here: it updates only the truncation
band around each new depth, so a surface that a later view sees through far in front of its own
depth is never carved, and its weights know no per-pixel confidence.

Surfels (`evidence_voxsplat`): per occupied voxel, Gaussians fitted to the confident pixels'
points in it by `fit.fit_voxsplat` (the LiDAR build's fit), each point standing for its pixel's
footprint on the surface (the parallelogram of the steps to its neighbours' points), weighted by
confidence; colours from the pixels.

Unsure pixels (`weak_confidence` <= confidence < `min_confidence`, off by default): stereo's
confidence is conservative on near objects at grazing angles and on repetitive or faint texture,
where most depths are right yet unsure. Such pixels add their hit like the others but carve
nothing, and a voxel that no confident pixel hits is occupied only where `weak_views` images hit
it: a wrong match lands somewhere else in each view, a right one in the same voxel. Their points
weigh `weak_fit_weight` times their confidence in the surfel fit (a voxel holding confident points
too keeps their surfel). The `evidence` profile turns them on: they fill near objects' sides that
confident pixels leave open, and their low fit weight keeps their noise off the road.

Moving objects (`DepthObservation.uncarved`): an image taken at another instant than the one fused
saw through the space where a moving object stands at that instant; its rays carve nothing inside
the boxes it is given (the object's box then), and everything else along them as before.

Frames: points in the world frame, metres; voxel (i, j, k) spans [origin + vs (i, j, k),
origin + vs (i + 1, j + 1, k + 1)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..boxes import Box, points_in_boxes
from ..camera.frames import CameraImage
from ..errors import InputError
from ..raytrace import compiled
from ..voxsplat import voxel_keys
from .config import FusionConfig

__all__ = ["DepthObservation", "FusedGrid", "carve_band", "fuse_depth", "voxel_of"]


@dataclass
class DepthObservation:
    """One image's depth: `depth` (H, W) float32 metres along the optical axis (NaN: none),
    `confidence` (H, W) in [0, 1], on the pixels of `image` (its intrinsics, cam_to_world and
    colours); `uncarved`: boxes (the frame of cam_to_world) inside which its rays carve nothing
    (where a moving object stands at the instant fused, which this image, taken at another, saw
    through)."""

    image: CameraImage
    depth: np.ndarray
    confidence: np.ndarray
    uncarved: tuple[Box, ...] = ()


@dataclass
class FusedGrid:
    """The fused evidence. Voxels: ijk (V, 3) int64 of the occupied candidates, logodds (V,)
    float64, hits (V,) int32 (images that saw a point there), misses (V,) int32 (images whose rays
    passed through). Points on them (the pixels' points in occupied voxels): points (N, 3) float64
    world metres, weights (N,) float32 (the pixels' confidence), colors (N, 3) float32 in [0, 1],
    patch (N, 6) float32 m^2 (each pixel's footprint covariance, xx xy xz yy yz zz), normals (N, 3)
    float32 (unit, sign arbitrary; zero at a depth edge), voxel (N,) int64 index into ijk.
    `carved` (C, 3) int64: candidates the misses outweighed."""

    voxel_size: float
    origin: np.ndarray
    ijk: np.ndarray
    logodds: np.ndarray
    hits: np.ndarray
    misses: np.ndarray
    points: np.ndarray
    weights: np.ndarray
    colors: np.ndarray
    patch: np.ndarray
    normals: np.ndarray
    voxel: np.ndarray
    carved: np.ndarray

    @property
    def probability(self) -> np.ndarray:
        """(V,) float64 occupancy probability in (0, 1)."""
        return 1.0 / (1.0 + np.exp(-self.logodds))


def _check(obs: DepthObservation, i: int) -> None:
    intr = obs.image.intrinsics
    shape = (intr.height, intr.width)
    for name in ("depth", "confidence"):
        a = np.asarray(getattr(obs, name))
        if a.shape != shape:
            raise InputError(f"fuse_depth: observation {i} ({obs.image.name!r}): {name} is {a.shape}, "
                             f"expected the image's {shape}")
    c = np.asarray(obs.confidence)
    if not np.all(np.isfinite(c) & (c >= 0) & (c <= 1)):
        raise InputError(f"fuse_depth: observation {i} ({obs.image.name!r}): confidence must lie in [0, 1]")


def _pixel_steps(world: np.ndarray, depth: np.ndarray, max_rel: float) -> tuple[np.ndarray, np.ndarray]:
    """world (H, W, 3) points of a depth map (NaN: none), depth (H, W) -> (H, W, 3) steps to the
    next pixel along the columns and along the rows: of the two neighbours' differences the shorter
    (not across a depth edge), zero where both are missing or longer than `max_rel` x depth."""
    out = []
    for axis in (1, 0):
        fwd = np.full_like(world, np.nan)
        bwd = np.full_like(world, np.nan)
        diff = np.diff(world, axis=axis)
        if axis == 1:
            fwd[:, :-1], bwd[:, 1:] = diff, diff
        else:
            fwd[:-1], bwd[1:] = diff, diff
        nf, nb = np.linalg.norm(fwd, axis=-1), np.linalg.norm(bwd, axis=-1)
        nf, nb = np.where(np.isfinite(nf), nf, np.inf), np.where(np.isfinite(nb), nb, np.inf)
        step = np.where((nf <= nb)[..., None], fwd, bwd)
        ok = (np.minimum(nf, nb) <= max_rel * depth)[..., None]
        out.append(np.where(ok, step, 0.0))
    return out[0], out[1]


def _near_edges(depth: np.ndarray, max_rel: float, margin: int) -> np.ndarray:
    """(H, W) bool: within `margin` pixels (a square) of a depth edge, a pair of neighbouring
    pixels with depth whose depths differ by more than `max_rel` x the nearer one. Stereo's windows
    straddle such edges and give the background beside a near object the object's depth."""
    edge = np.zeros(depth.shape, bool)
    for axis in (0, 1):
        a = np.moveaxis(depth, axis, 0)
        with np.errstate(invalid="ignore"):
            jump = np.abs(a[1:] - a[:-1]) > max_rel * np.fmin(a[1:], a[:-1])
        e = np.moveaxis(edge, axis, 0)  # a view: marks land in `edge`
        e[1:] |= jump
        e[:-1] |= jump
    h, w = depth.shape
    padded = np.pad(edge, margin)
    out = np.zeros_like(edge)
    for dy in range(2 * margin + 1):
        for dx in range(2 * margin + 1):
            out |= padded[dy:dy + h, dx:dx + w]
    return out


def _points(obs: DepthObservation, cfg: FusionConfig):
    """The confident pixels' world points (N, 3), their depths (N,), confidences (N,), colours
    (N, 3), pixel (row, col) (N, 2) of the image, patch covariances (N, 6) (xx, xy, xz, yy, yz, zz: the
    pixel's footprint, the parallelogram of its steps to the neighbouring pixels' points, uniform:
    (a a^T + b b^T) / 12, so that neighbouring surfels close the surface) and unit normals (N, 3)
    (a x b, sign arbitrary; zero where a step is missing)."""
    s = cfg.pixel_stride
    d = np.asarray(obs.depth, np.float64)[::s, ::s]
    c = np.asarray(obs.confidence, np.float32)[::s, ::s]
    floor = cfg.min_confidence if cfg.weak_confidence is None else min(cfg.min_confidence, cfg.weak_confidence)
    keep = np.isfinite(d) & (d > 0) & (d <= cfg.max_depth_m) & (c >= floor) & (c > 0)
    if obs.image.sky is not None:
        keep &= ~np.asarray(obs.image.sky, bool)[::s, ::s]
    rays = obs.image.intrinsics.pixel_rays()[::s, ::s]
    pose = obs.image.cam_to_world
    world = (rays / rays[..., 2:3] * np.where(keep, d, np.nan)[..., None]) @ pose[:3, :3].T + pose[:3, 3]
    a, b = _pixel_steps(world, d, cfg.patch_max_rel)
    if cfg.edge_margin_px:
        # the confident pixels' edges as without unsure ones; an unsure pixel also keeps off theirs
        sure = keep & (c >= cfg.min_confidence)
        near = _near_edges(np.where(sure, d, np.nan), cfg.patch_max_rel, cfg.edge_margin_px)
        if cfg.weak_confidence is not None:
            near |= ~sure & _near_edges(np.where(keep, d, np.nan), cfg.patch_max_rel, cfg.edge_margin_px)
        keep &= ~near
    rows, cols = np.nonzero(keep)
    a, b = a[rows, cols], b[rows, cols]
    cov6 = np.stack([(a[:, i] * a[:, j] + b[:, i] * b[:, j]) / 12.0
                     for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))], 1)
    normal = np.cross(a, b)
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.where(length > 0, normal / np.where(length > 0, length, 1.0), 0.0)
    rgb = np.asarray(obs.image.image, np.float32)[rows * s, cols * s] / 255.0
    return world[rows, cols], d[rows, cols], c[rows, cols], rgb, np.stack([rows, cols], 1) * s, cov6, normal


def voxel_of(points: np.ndarray, origin: np.ndarray, vs: float) -> np.ndarray:
    return np.floor((points - origin) / vs).astype(np.int64)


def _per_voxel_mean(slots: np.ndarray, values: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """slots (K,) in [0, n), values (K,) -> (present (n,) bool, mean of the values per slot (n,))."""
    cnt = np.bincount(slots, minlength=n)
    total = np.bincount(slots, weights=values.astype(np.float64), minlength=n)
    return cnt > 0, total / np.maximum(cnt, 1)


def _key_ijk(keys: np.ndarray) -> np.ndarray:
    """(N,) `voxel_keys` -> (N, 3) int64 voxel indices."""
    mask = (1 << 21) - 1
    return np.stack([(keys >> 42) & mask, (keys >> 21) & mask, keys & mask], 1) - (1 << 20)


def carve_band(depth: np.ndarray, cfg: FusionConfig) -> np.ndarray:
    """Metres before a measured point (depth (N,) metres along the optical axis) that its ray does
    not carve: `band_voxels` voxels or `band_rel` of the depth, the larger."""
    return np.maximum(cfg.band_voxels * cfg.voxel_size, cfg.band_rel * depth)


def _misses(obs_points, depth, conf, origin_cam, candidates: np.ndarray, origin: np.ndarray,
            cfg: FusionConfig, core: str | None = None, threads: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The candidate voxels (indices into the sorted `candidates` keys) the rays from `origin_cam`
    to the points pass through short of the band, and per such voxel the mean confidence of those
    rays. Each ray is sampled every half voxel (a ray cannot skip a voxel it crosses by more than
    half its width). core: 'compiled' (`raytrace.compiled.carve_misses`) or 'reference' (the NumPy
    walk below, the same bytes); None: the tracer's default (`compiled.default_core_name`). threads:
    the compiled walk's (0: one per core; the bytes do not depend on it)."""
    vs = cfg.voxel_size
    step = 0.5 * vs
    # per ray, batch by batch as the walk below (the same bytes): where it starts, its direction, how far it carves
    direction, reach = np.zeros((len(obs_points), 3)), np.zeros(len(obs_points))
    for a in range(0, len(obs_points), cfg.chunk_rays):
        p = obs_points[a:a + cfg.chunk_rays]
        dist = np.linalg.norm(p - origin_cam, axis=1)
        band = carve_band(depth[a:a + cfg.chunk_rays], cfg)
        reach[a:a + cfg.chunk_rays] = np.clip(dist - band * dist / np.maximum(depth[a:a + cfg.chunk_rays], 1e-9),
                                              0.0, None)
        direction[a:a + cfg.chunk_rays] = (p - origin_cam) / np.maximum(dist, 1e-12)[:, None]
    conf64 = np.asarray(conf, np.float64)
    name = core or compiled.default_core_name()
    if name == "compiled":
        hit_any, conf_sum, conf_cnt = compiled.carve_misses(origin_cam, direction, reach, conf64, origin, vs, step,
                                                            cfg.chunk_rays, candidates, threads)
    elif name == "reference":
        hit_any, conf_sum, conf_cnt = _misses_reference(origin_cam, direction, reach, conf64, candidates, origin, vs,
                                                        step, cfg.chunk_rays)
    else:
        raise InputError(f"core: expected 'compiled' or 'reference', got {name!r}")
    idx = np.nonzero(hit_any)[0]
    return idx, conf_sum[idx] / conf_cnt[idx]


def _misses_reference(origin_cam, direction, reach, conf, candidates, origin, vs, step, batch):
    """`_misses`' walk in NumPy, `batch` rays at a time: (hit (K,) bool, confidence sum (K,),
    ray count (K,)) per candidate voxel."""
    n = len(candidates)
    hit_any = np.zeros(n, bool)
    conf_sum = np.zeros(n)
    conf_cnt = np.zeros(n)
    for a in range(0, len(direction), batch):
        r_reach = reach[a:a + batch]
        n_steps = int(np.ceil(r_reach.max() / step)) if len(r_reach) else 0
        if n_steps == 0:
            continue
        t = (np.arange(n_steps) + 0.5) * step  # (S,) metres along the ray
        inside = t[None, :] < r_reach[:, None]  # (R, S)
        r_idx, s_idx = np.nonzero(inside)
        samples = origin_cam + direction[a:a + batch][r_idx] * t[s_idx, None]
        keys = voxel_keys(voxel_of(samples, origin, vs))
        # one miss per ray and voxel: a voxel is convex, so a ray's samples in it are consecutive
        first = np.ones(len(keys), bool)
        first[1:] = (keys[1:] != keys[:-1]) | (r_idx[1:] != r_idx[:-1])
        keys, rays = keys[first], r_idx[first]
        pos = np.searchsorted(candidates, keys)
        found = pos < n
        found[found] = candidates[pos[found]] == keys[found]
        slots = pos[found]
        c = conf[a:a + batch][rays[found]]
        hit_any[slots] = True
        conf_sum += np.bincount(slots, weights=c, minlength=n)
        conf_cnt += np.bincount(slots, minlength=n)
    return hit_any, conf_sum, conf_cnt


def fuse_depth(observations: list[DepthObservation], cfg: FusionConfig | None = None, *,
               origin: np.ndarray | None = None) -> FusedGrid:
    """Fuse the observations' confident depth into occupancy on a grid of `cfg.voxel_size` anchored
    at `origin` ((3,) world metres, default zero) (module docstring). Deterministic: the images are
    taken in the given order and every sum runs in a fixed order."""
    cfg = cfg or FusionConfig()
    origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64).reshape(3)
    vs = cfg.voxel_size
    per = []
    for i, obs in enumerate(observations):
        _check(obs, i)
        per.append(_points(obs, cfg))
    if not per or sum(len(p[0]) for p in per) == 0:
        empty3 = np.zeros((0, 3), np.int64)
        return FusedGrid(vs, origin, empty3, np.zeros(0), np.zeros(0, np.int32), np.zeros(0, np.int32),
                         np.zeros((0, 3)), np.zeros(0, np.float32), np.zeros((0, 3), np.float32),
                         np.zeros((0, 6), np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.int64),
                         empty3.copy())
    all_keys = np.concatenate([voxel_keys(voxel_of(p[0], origin, vs)) for p in per])
    candidates = np.unique(all_keys)
    n = len(candidates)
    logodds = np.zeros(n)
    hits = np.zeros(n, np.int32)
    misses = np.zeros(n, np.int32)
    point_slot = []
    sure_hits = np.zeros(n, np.int32)
    for obs, (world, depth, conf, _, rc, _, _) in zip(observations, per):
        slot = np.searchsorted(candidates, voxel_keys(voxel_of(world, origin, vs)))
        point_slot.append(slot)
        hit, hit_conf = _per_voxel_mean(slot, conf, n)
        sure = conf >= cfg.min_confidence
        sure_hits += np.bincount(slot[sure], minlength=n) > 0
        s = cfg.carve_stride * cfg.pixel_stride
        sub = (rc[:, 0] % s == 0) & (rc[:, 1] % s == 0) if cfg.carve_stride > 1 else np.ones(len(rc), bool)
        sub &= sure  # an unsure depth may lie in front of the true surface: it carves nothing
        miss_idx, miss_conf = _misses(world[sub], depth[sub], conf[sub], obs.image.cam_to_world[:3, 3],
                                      candidates, origin, cfg)
        if obs.uncarved:
            out = points_in_boxes(origin + (_key_ijk(candidates[miss_idx]) + 0.5) * vs, list(obs.uncarved)) < 0
            miss_idx, miss_conf = miss_idx[out], miss_conf[out]
        miss = np.zeros(n, bool)
        miss_c = np.zeros(n)
        miss[miss_idx] = True
        miss_c[miss_idx] = miss_conf
        miss &= ~hit  # a hit wins over a miss of the same image
        logodds += np.where(hit, cfg.hit_logodds * hit_conf, 0.0)
        logodds += np.where(miss, cfg.miss_logodds * miss_c, 0.0)
        hits += hit
        misses += miss
    occupied = (logodds >= cfg.occupied_logodds) & ((sure_hits > 0) | (hits >= cfg.weak_views))
    ijk_all = _key_ijk(candidates)
    new_index = np.cumsum(occupied) - 1
    slot = np.concatenate(point_slot)
    keep = occupied[slot]
    points = np.concatenate([p[0] for p in per])[keep]
    conf_all = np.concatenate([p[2] for p in per]).astype(np.float32)
    if cfg.weak_confidence is not None and cfg.weak_fit_weight != 1.0:
        # where a voxel holds confident points too, they place its surfel
        conf_all = np.where(conf_all < cfg.min_confidence, conf_all * np.float32(cfg.weak_fit_weight), conf_all)
    weights = conf_all[keep]
    colors = np.concatenate([p[3] for p in per]).astype(np.float32)[keep]
    patch = np.concatenate([p[5] for p in per]).astype(np.float32)[keep]
    normals = np.concatenate([p[6] for p in per]).astype(np.float32)[keep]
    return FusedGrid(vs, origin, ijk_all[occupied], logodds[occupied], hits[occupied], misses[occupied],
                     points, weights, colors, patch, normals, new_index[slot[keep]], ijk_all[~occupied])


