"""How close is a simulated LiDAR to a real sweep? Ray for ray and cloud to cloud.

Each real return defines a ray (the sensor origin along the point's direction, in the sensor frame
at the point's own fire time); the simulator fires exactly those rays at the scene with the real
sensor's model (range limits, drops, intensity) and the same per-ray timing, so a range
difference is the scene's error, not a sampling difference. Range noise is off by default: the
real points already carry the sensor's noise, and adding the model's would count it twice.

No-returns. Some sets store the full firing grid (nuScenes: 32 x 1084, every ring every column)
and put a no-return at the origin (after motion compensation, a few decimetres from it): those are
all returns closer than `min_range`. On such a grid the no-return rays are rebuilt (the ring's
elevation and the column's azimuth, both medians of the real returns) and hit/miss agreement is
measured over every ray. Sets that keep only returns (KITTI, Argoverse 2) cannot say where the
sensor saw nothing; there, agreement is the share of real returns the simulation also returns.

Conventions: range error = simulated - real range (metres) on rays where both return; Chamfer
distance = the mean of the two mean nearest-neighbour distances (metres, not squared); F-score at
tau = harmonic mean of precision (simulated points within tau of a real point) and recall (real
points within tau of a simulated point); intensity correlation = Pearson's r, and intensity RMSE
the root mean square difference, on rays both return, both on the common 0-1 scale (the real
intensity / the set's `intensity_max`; the simulated one at `output_scale` 1: the sensor's response
to the scene's measured reflectance, or class reflectivity x cos incidence where it has none).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..camera.depth import project_to_pixels
from ..datasets.base import LidarSweep
from ..datasets.origins import require_single_origin
from ..errors import InputError
from ..labels import label_id
from ..lidar.compare import fidelity_config
from ..lidar.config import LidarConfig
from ..lidar.model import Lidar
from ..lidar.pattern import channels_by_elevation, replay_pattern
from ..mesh import TriangleMesh
from ..raytrace.posed import place_scene
from ..raytrace.tracer import Tracer
from ..reconstruct.ground import GroundPlane, fit_ground_plane
from ..transforms import invert_pose
from ..viz import fidelity_png, intensity_png, sweeps_over_image_png
from ..voxsplat import unique_voxels
from .build import BuildOptions, accumulate_from_dataset, free_space_mask, grow_to_objects, surface_patches


@dataclass
class RealRays:
    """The rays of a real sweep. directions (N, 3) unit, sensor frame (at each ray's fire time for
    raw sweeps); range (N,) metres, inf for a no-return; time (N,) seconds after the sweep
    timestamp; intensity (N,) in [0, 1] (NaN on no-returns); row, col (N,) int range-image cell;
    no_returns_known: whether the no-return rays are in the set; ring (N,) int the set's ring id
    (-1 where it has none); ego_body (N,) bool: returns under `min_range` off the sensor's
    horizontal plane (EGO_BODY_Z_M): the sensor saw its own vehicle (full grids only).

    Rays of a merged cloud (`concat_rays`): part (N,) int which sensor each ray is from, and
    to_sweep (K, 4, 4) each sensor's frame in the merged sweep's frame (directions stay in their
    own sensor's frame; `cloud` maps points to the common one). None for one sensor."""

    directions: np.ndarray
    range: np.ndarray
    time: np.ndarray
    intensity: np.ndarray
    row: np.ndarray
    col: np.ndarray
    rows: int
    cols: int
    no_returns_known: bool
    notes: list[str] = field(default_factory=list)
    ring: np.ndarray | None = None
    ego_body: np.ndarray | None = None
    part: np.ndarray | None = None
    to_sweep: np.ndarray | None = None

    def __post_init__(self):
        if self.ring is None:
            self.ring = np.full(self.range.shape[0], -1, np.int64)
        if self.ego_body is None:
            self.ego_body = np.zeros(self.range.shape[0], bool)

    def __len__(self) -> int:
        return self.range.shape[0]

    def subset(self, mask: np.ndarray) -> "RealRays":
        """The rays where `mask` (N,) bool."""
        return RealRays(self.directions[mask], self.range[mask], self.time[mask], self.intensity[mask],
                        self.row[mask], self.col[mask], self.rows, self.cols, self.no_returns_known, self.notes,
                        self.ring[mask], self.ego_body[mask], None if self.part is None else self.part[mask],
                        self.to_sweep)

    def cloud(self, rng: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(M, 3) metres: the points at ranges `rng` (N,) of the rays where `mask` (N,) bool, in one
        frame (the sensor's; a merged cloud's own frame for rays of several sensors)."""
        p = self.directions[mask] * rng[mask, None]
        if self.part is None:
            return p
        t = self.to_sweep[self.part[mask]]
        return np.einsum("nij,nj->ni", t[:, :3, :3], p) + t[:, :3, 3]

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.range)


EGO_BODY_Z_M = 0.05  # a no-return stored further above or below the sensor is the ego body


def _is_full_grid(sweep: LidarSweep) -> int:
    """The ring count if the sweep stores every ring of every column in order, else 0."""
    if sweep.ring is None or len(sweep) == 0:
        return 0
    rings = int(sweep.ring.max()) + 1
    n = len(sweep)
    if n % rings or not np.array_equal(sweep.ring, np.tile(np.arange(rings), n // rings)):
        return 0
    return rings


def _circular_mean(angles: np.ndarray, group: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    s = np.bincount(group, weights=np.sin(angles), minlength=n)
    c = np.bincount(group, weights=np.cos(angles), minlength=n)
    cnt = np.bincount(group, minlength=n)
    return np.arctan2(s, c), cnt > 0


def real_rays(sweep: LidarSweep, *, min_range: float = 1.0, azimuth_bins: int = 1024,
              elevation_bins: int = 64) -> RealRays:
    """Rays of a real sweep; returns closer than `min_range` metres count as no-returns (or
    are dropped when the set does not keep a full grid)."""
    p = sweep.points
    r = np.linalg.norm(p, axis=1)
    ret = r >= min_range
    n = len(sweep)
    t = np.zeros(n) if sweep.time_offset is None else np.asarray(sweep.time_offset, np.float64)
    inten = (np.full(n, np.nan) if sweep.intensity is None
             else np.asarray(sweep.intensity, np.float64) / sweep.intensity_max)
    notes: list[str] = []
    rings = _is_full_grid(sweep)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = p / r[:, None]
    if rings:
        cols = n // rings
        row, col = np.asarray(sweep.ring, np.int64), np.arange(n) // rings
        el = np.arcsin(np.clip(d[:, 2], -1, 1))
        az = np.arctan2(d[:, 1], d[:, 0])
        ring_el = np.full(rings, np.nan)
        for k in range(rings):
            sel = ret & (row == k)
            if sel.any():
                ring_el[k] = np.median(el[sel])
        col_az, seen = _circular_mean(az[ret], col[ret], cols)
        cidx = np.arange(cols)
        if seen.sum() >= 2:  # columns without any return: interpolate the unwrapped azimuth
            unwrapped = np.unwrap(col_az[seen])
            col_az = np.interp(cidx, cidx[seen], unwrapped)
        miss = ~ret & np.isfinite(ring_el[row])
        e, a = ring_el[row[miss]], col_az[col[miss]]
        rebuilt = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=1)
        # A placeholder sits at the origin, moved by motion compensation along the ego's level
        # path; a point off that plane is a return from the vehicle's own body (the roof under a
        # roof-mounted sensor), which compensation moves too, so its direction cannot tell.
        body = ~ret & (np.abs(p[:, 2]) > EGO_BODY_Z_M)
        d[miss] = rebuilt
        keep = ret | miss
        notes.append(f"full {rings} x {cols} firing grid: {int((~ret).sum())} of {n} rays "
                     f"({100.0 * (~ret).mean():.1f} %) are no-returns (stored under {min_range} m); "
                     f"their directions are the ring's median elevation and the column's mean azimuth; "
                     f"{int(body.sum())} of them lie over {EGO_BODY_Z_M} m off the sensor's plane: the ego body")
        order = np.argsort(-np.nan_to_num(ring_el, nan=-9))  # top beam first
        rank = np.empty(rings, np.int64)
        rank[order] = np.arange(rings)
        row = rank[row]
        known = True
    else:
        keep = ret
        body = np.zeros(n, bool)
        az = np.arctan2(d[:, 1], d[:, 0])
        el = np.arcsin(np.clip(d[:, 2], -1, 1))
        rings = elevation_bins
        cols = azimuth_bins
        if sweep.ring is not None:
            rr = np.asarray(sweep.ring, np.int64)
            uniq = np.unique(rr[ret])
            ring_el = np.array([np.median(el[ret & (rr == u)]) for u in uniq])
            rank = np.empty(int(uniq.max()) + 1, np.int64)
            rank[uniq[np.argsort(-ring_el)]] = np.arange(uniq.size)
            row, rings = rank[np.clip(rr, 0, uniq.max())], uniq.size
        else:
            lo, hi = np.percentile(el[ret], [0.5, 99.5]) if ret.any() else (0.0, 1.0)
            row = np.clip(((hi - el) / max(hi - lo, 1e-9) * elevation_bins).astype(np.int64), 0, elevation_bins - 1)
        col = np.clip(((np.pi - az) / (2 * np.pi) * cols).astype(np.int64), 0, cols - 1)
        if (~ret).any():
            notes.append(f"{int((~ret).sum())} returns under {min_range} m dropped (ego body or placeholders)")
        notes.append("returns only: no-return rays are not in this set, so hit agreement = share of real "
                     "returns the simulation also returns")
        known = False
    rng = np.where(ret, r, np.inf)
    laser = np.full(n, -1, np.int64) if sweep.ring is None else np.asarray(sweep.ring, np.int64)
    return RealRays(d[keep], rng[keep], t[keep], np.where(ret, inten, np.nan)[keep], row[keep], col[keep],
                    int(rings), int(cols), known, notes, laser[keep], body[keep])


def concat_rays(parts: list[RealRays], to_sweep: np.ndarray) -> RealRays:
    """The rays of several sensors (a merged cloud split by `LidarSweep.by_origin`) as one set:
    to_sweep (K, 4, 4) each part's sensor frame in the merged sweep's frame. Range-image rows are
    stacked (part k's rows below part k-1's), so pictures show one band per sensor."""
    if len(parts) == 1:
        return parts[0]
    offs = np.cumsum([0] + [p.rows for p in parts])
    cat = lambda name: np.concatenate([getattr(p, name) for p in parts])  # noqa: E731
    notes = [f"{k}: {n}" for k, p in enumerate(parts) for n in p.notes]
    return RealRays(cat("directions"), cat("range"), cat("time"), cat("intensity"),
                    np.concatenate([p.row + o for p, o in zip(parts, offs)]), cat("col"), int(offs[-1]),
                    max(p.cols for p in parts), all(p.no_returns_known for p in parts), notes, cat("ring"),
                    cat("ego_body"), np.concatenate([np.full(len(p), k, np.int64) for k, p in enumerate(parts)]),
                    np.asarray(to_sweep, np.float64))


def concat_sims(parts: list["SimRays"]) -> "SimRays":
    """SimRays of the parts of `concat_rays`, in the same order."""
    if len(parts) == 1:
        return parts[0]
    return SimRays(*(np.concatenate([getattr(p, n) for p in parts]) for n in ("range", "intensity", "label")))


@dataclass
class SimRays:
    """Per real ray: range (N,) metres (inf: no return), intensity (N,), label (N,)."""

    range: np.ndarray
    intensity: np.ndarray
    label: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.range)


def simulate_rays(scene, config: LidarConfig, rays: RealRays, sweep: LidarSweep, *, distortion: bool = True,
                  noise: bool = False, seed: int = 0, drop=None) -> SimRays:
    """Fire the real rays at `scene` (a Tracer, list of Tracers or a time-aware scene); `drop`
    as in `fidelity_config`.

    distortion: for a raw sweep (points in the sensor frame at their own fire time), move the
    sensor along `sweep.pose_fn` while it fires; False fires every ray from the pose at the sweep
    timestamp (what a simulator without a motion model does). Compensated sweeps always replay
    from the sweep pose."""
    t0 = float(rays.time.min(initial=0.0))
    # The sensor's own channel numbering; an unknown one gets an index past every per-channel
    # table (gain 1, no correction).
    channel = channels_by_elevation(rays.directions, rays.ring, config, valid=rays.hit)
    ring = np.where(channel >= 0, channel, np.iinfo(np.uint16).max)
    pattern = replay_pattern(rays.directions, rays.time - t0, ring, period_s=max(float(np.ptp(rays.time)), 1e-3)
                             if len(rays) else 0.1)
    lidar = Lidar(fidelity_config(config, noise=noise, drop=drop), pattern)
    if distortion and not sweep.motion_compensated:
        out = lidar.scan(scene, sweep.sensor_to_world, pose_fn=sweep.pose_fn, t_start=sweep.timestamp + t0,
                         seed=seed)
    else:
        out = lidar.scan(scene, sweep.sensor_to_world, t_start=sweep.timestamp + t0, seed=seed)
    n = len(rays)
    rng, inten, lab = np.full(n, np.inf), np.full(n, np.nan), np.zeros(n, np.int16)
    idx = out.points["column"].astype(np.int64)
    rng[idx] = out.points["range"]
    inten[idx] = out.points["intensity"]
    lab[idx] = out.points["label"]
    return SimRays(rng, inten, lab)


def _nn(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    if len(a) == 0:
        return np.zeros(0)
    if len(b) == 0:
        return np.full(len(a), np.inf)
    return cKDTree(b).query(a, k=1)[0]


def compare(rays: RealRays, sim: SimRays, *, taus=(0.05, 0.20), mask: np.ndarray | None = None) -> dict:
    """Ray-for-ray and cloud metrics (see the module docstring for the conventions); `mask`
    (N,) bool restricts them to some rays."""
    if mask is not None:
        rays = rays.subset(mask)
        sim = SimRays(sim.range[mask], sim.intensity[mask], sim.label[mask])
    real_hit, sim_hit = rays.hit, sim.hit
    both = real_hit & sim_hit
    err = sim.range[both] - rays.range[both]
    a = np.abs(err)
    out = {"rays": int(len(rays)), "real_returns": int(real_hit.sum()), "sim_returns": int(sim_hit.sum()),
           "both_return": int(both.sum())}
    out["median_abs_m"] = float(np.median(a)) if a.size else float("nan")
    out["p90_abs_m"] = float(np.percentile(a, 90)) if a.size else float("nan")
    out["mean_signed_m"] = float(np.mean(err)) if a.size else float("nan")
    if rays.no_returns_known:
        out["hit_agreement"] = float(np.mean(real_hit == sim_hit))
        out["false_returns"] = float(np.mean(sim_hit[~real_hit])) if (~real_hit).any() else 0.0
    else:
        out["hit_agreement"] = float(np.mean(sim_hit[real_hit])) if real_hit.any() else float("nan")
    out["missed_returns"] = float(np.mean(~sim_hit[real_hit])) if real_hit.any() else 0.0
    # Clouds in the sensor frame of each ray (both clouds share the rays).
    real_pts = rays.cloud(rays.range, real_hit)
    sim_pts = rays.cloud(sim.range, sim_hit)
    d_sr, d_rs = _nn(sim_pts, real_pts), _nn(real_pts, sim_pts)
    out["chamfer_m"] = float(0.5 * (d_sr.mean() + d_rs.mean())) if len(d_sr) and len(d_rs) else float("inf")
    for tau in taus:
        prec = float(np.mean(d_sr <= tau)) if len(d_sr) else 0.0
        rec = float(np.mean(d_rs <= tau)) if len(d_rs) else 0.0
        out[f"fscore_{round(tau * 100)}cm"] = 2 * prec * rec / (prec + rec) if prec + rec > 0 else 0.0
    ri, si = rays.intensity[both], sim.intensity[both]
    ok = np.isfinite(ri) & np.isfinite(si)
    if ok.sum() > 2 and np.std(ri[ok]) > 0 and np.std(si[ok]) > 0:
        out["intensity_r"] = float(np.corrcoef(ri[ok], si[ok])[0, 1])
    else:
        out["intensity_r"] = float("nan")
    out["intensity_rmse"] = float(np.sqrt(np.mean((si[ok] - ri[ok]) ** 2))) if ok.any() else float("nan")
    return out


def range_image(rays: RealRays, values: np.ndarray) -> np.ndarray:
    """(rows, cols) float32 image of per-ray values (NaN where no ray or no value; the nearest
    value where several rays share a cell)."""
    img = np.full(rays.rows * rays.cols, np.inf)
    cell = rays.row * rays.cols + rays.col
    v = np.where(np.isfinite(values), values, np.inf)
    np.minimum.at(img, cell, v)
    img[~np.isfinite(img)] = np.nan
    return img.reshape(rays.rows, rays.cols).astype(np.float32)


_CUBE_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                        [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]], np.int32)


_CUBE_CORNERS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
                         np.float64)


def voxel_cube_mesh(points: np.ndarray, voxel_size: float = 0.1, origin=None) -> TriangleMesh:
    """Baseline: every occupied voxel of (N, 3) points (local frame of `origin`) as a solid cube."""
    uniq, _, _ = unique_voxels(np.floor(np.asarray(points, np.float64) / voxel_size))
    v = ((uniq[:, None, :] + _CUBE_CORNERS[None]) * voxel_size).reshape(-1, 3)
    f = (_CUBE_FACES[None] + 8 * np.arange(uniq.shape[0])[:, None, None]).reshape(-1, 3)
    return TriangleMesh(v, f, origin=np.zeros(3) if origin is None else origin)


def poisson_mesh(points: np.ndarray, normals: np.ndarray, *, depth: int = 10, origin=None) -> TriangleMesh:
    """Baseline: open3d's screened Poisson surface of (N, 3) points with (N, 3) outward normals
    (untrimmed: where the points stop, the surface bulges or closes over holes)."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=depth, linear_fit=False)
    return TriangleMesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles),
                        origin=np.zeros(3) if origin is None else origin)


CLASS_ROW = "voxsplat, class reflectivity"


GROUND_ROW = "baseline: flat ground plane (the road under the ego)"


METRIC_COLUMNS = (("median_abs_m", "median |dr| [cm]", 100), ("p90_abs_m", "p90 |dr| [cm]", 100),
                  ("hit_agreement", "hit agreement [%]", 100), ("chamfer_m", "Chamfer [cm]", 100),
                  ("fscore_5cm", "F@5cm", 1), ("fscore_20cm", "F@20cm", 1), ("intensity_r", "intensity r", 1),
                  ("intensity_rmse", "intensity RMSE", 1))


REGION_MAX_M = 40.0  # `regions`: real returns within this range ...
REGION_GROUND_M = 0.25  # ... ground within this height of the plane fitted to the sweep, above ground over it
FITTED_PLANE_ROW = "baseline: plane fitted to the sweep"
SURFACE_COLUMNS = (("to_scene_median_m", "real -> surface median [cm]", 100),
                   ("to_scene_p90_m", "real -> surface p90 [cm]", 100),
                   ("from_scene_median_m", "surface -> real median [cm]", 100), ("real", "real returns", 1),
                   ("scene_points", "surface points", 1))


@dataclass
class FidelityResult:
    """rows: model name -> metrics (see `compare`); images: name -> range image (metres);
    intensity_images: 'real' and row name -> intensity range image (0-1 scale); notes: how rays
    were chosen and what was left out; surface: region -> the surface distances of `regions`;
    camera_view: with `regions`, the first camera's image and the real and replayed returns in it
    (`camera_view`)."""

    rows: dict[str, dict]
    images: dict[str, np.ndarray]
    notes: list[str]
    context: dict
    mismatch: np.ndarray | None = None
    intensity_images: dict[str, np.ndarray] = field(default_factory=dict)
    surface: dict[str, dict] = field(default_factory=dict)
    camera_view: dict | None = None

    def markdown(self) -> str:
        head = "| scene | " + " | ".join(c[1] for c in METRIC_COLUMNS) + " | rays | both return |"
        lines = [head, "|" + "---|" * (len(METRIC_COLUMNS) + 3)]
        for name, m in self.rows.items():
            cells = [f"{m[k] * s:.2f}" if s != 1 else f"{m[k]:.3f}" for k, _, s in METRIC_COLUMNS]
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {m['rays']} | {m['both_return']} |")
        if self.surface:
            lines += ["", "| surface distances | " + " | ".join(c[1] for c in SURFACE_COLUMNS) + " |",
                      "|" + "---|" * (len(SURFACE_COLUMNS) + 1)]
            for name, m in self.surface.items():
                cells = [("–" if m[k] is None else f"{m[k] * sc:.1f}") if sc != 1 else f"{m[k]}"
                         for k, _, sc in SURFACE_COLUMNS]
                lines.append(f"| {name} | " + " | ".join(cells) + " |")
        ctx = ", ".join(f"{k}: {v}" for k, v in self.context.items())
        return "\n".join([f"# LiDAR fidelity ({ctx})", "", *lines, "", *[f"- {n}" for n in self.notes], ""])


def plane_mesh(plane: GroundPlane, centre: np.ndarray, half_size: float = 250.0) -> TriangleMesh:
    """A square of `plane`, 2 * half_size metres wide, around the foot of `centre` (3,) on it."""
    n = plane.normal
    foot = np.asarray(centre, np.float64) - plane.distance(np.asarray(centre)[None])[0] * n
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    h = float(half_size)
    corners = np.array([-h * u - h * v, h * u - h * v, h * u + h * v, -h * u + h * v])
    return TriangleMesh(corners, [[0, 1, 2], [0, 2, 3]], labels=np.full(2, label_id("road")), origin=foot)


def region_masks(rays: RealRays, sweep: LidarSweep, frames) -> tuple[dict[str, np.ndarray], GroundPlane | None,
                                                                     np.ndarray]:
    """The real returns within REGION_MAX_M and inside any camera of `frames`, split into ground
    (within REGION_GROUND_M of a plane fitted to the sweep's returns) and above ground: name ->
    (N,) bool over the rays; the plane (None: none found); the returns' world points (M, 3)."""
    hit = rays.hit
    world = rays.cloud(rays.range, hit) @ sweep.sensor_to_world[:3, :3].T + sweep.sensor_to_world[:3, 3]
    plane = fit_ground_plane(world, sweep.sensor_to_world[:3, 2])
    view = np.zeros(len(world), bool)
    for im in (frames.images if frames is not None else []):
        kept, _, _ = project_to_pixels(world, im)
        view[kept] = True
    base = view & (rays.range[hit] <= REGION_MAX_M)
    h = plane.distance(world) if plane is not None else np.full(len(world), np.nan)
    out = {}
    for name, m in (("ground", base & (np.abs(h) < REGION_GROUND_M)), ("above ground", base & (h >= REGION_GROUND_M))):
        full = np.zeros(len(rays), bool)
        full[np.flatnonzero(hit)] = m
        out[name] = full
    return out, plane, world


def _scene_points_world(scene) -> np.ndarray:
    """The scene's Gaussian means (N, 3), world frame (a chunk-frame scene placed by its metadata)."""
    local = scene.gaussians().means + scene.origin
    meta = scene.metadata if isinstance(scene.metadata, dict) else {}
    if meta.get("frame") == "chunk" and meta.get("chunk_to_world") is not None:
        c = np.asarray(meta["chunk_to_world"], np.float64)
        return local @ c[:3, :3].T + c[:3, 3]
    return local


def surface_distances(rays: RealRays, sweep: LidarSweep, frames, scene, masks: dict[str, np.ndarray],
                      world: np.ndarray, plane: GroundPlane | None) -> dict[str, dict]:
    """Per region: the real returns' distance to the scene's nearest Gaussian mean (median, p90)
    and to the fitted plane; the scene's means (within REGION_MAX_M of the sensor, inside a camera,
    within the sweep's elevation span) to the nearest real return of any region."""
    hit_idx = np.flatnonzero(rays.hit)
    pts = _scene_points_world(scene)
    sensor = sweep.sensor_to_world
    rel = (pts - sensor[:3, 3]) @ sensor[:3, :3]
    dist = np.linalg.norm(rel, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        elev = np.arcsin(np.clip(rel[:, 2] / dist, -1, 1))
    dirs = rays.directions[rays.hit]
    real_elev = np.arcsin(np.clip(dirs[:, 2], -1, 1))
    view = np.zeros(len(pts), bool)
    for im in (frames.images if frames is not None else []):
        kept, _, _ = project_to_pixels(pts, im)
        view[kept] = True
    mine = view & (dist <= REGION_MAX_M) & (elev >= real_elev.min()) & (elev <= real_elev.max())
    any_region = np.zeros(len(hit_idx), bool)
    for m in masks.values():
        any_region |= m[hit_idx]
    from_scene = _nn(pts[mine], world[any_region])
    out = {}
    for name, m in masks.items():
        sel = m[hit_idx]
        d = _nn(world[sel], pts)
        row = {"real": int(sel.sum()), "scene_points": int(mine.sum()),
               "to_scene_median_m": float(np.median(d)) if d.size else None,
               "to_scene_p90_m": float(np.percentile(d, 90)) if d.size else None,
               "from_scene_median_m": float(np.median(from_scene)) if from_scene.size else None}
        out[f"voxsplat, {name}"] = row
        if plane is not None:
            dp = np.abs(plane.distance(world[sel]))
            out[f"{FITTED_PLANE_ROW}, {name}"] = {
                "real": int(sel.sum()), "scene_points": 0,
                "to_scene_median_m": float(np.median(dp)) if dp.size else None,
                "to_scene_p90_m": float(np.percentile(dp, 90)) if dp.size else None, "from_scene_median_m": None}
    return out


def moving_rays(ds, sweep: LidarSweep, rays: RealRays, others: list[int], sensors=None) -> np.ndarray:
    """(N,) bool: real returns on objects that moved, found without labels: points of `sweep`
    that the other samples' sweeps saw through (free space then), grown to whole objects."""
    pts = rays.directions[rays.hit] * rays.range[rays.hit, None]
    world = pts @ sweep.sensor_to_world[:3, :3].T + sweep.sensor_to_world[:3, 3]
    seeds = np.zeros(len(pts), bool)
    for j in others:
        for whole in ds[j].sweeps:
            if sensors is None or whole.sensor in sensors:
                for sw in whole.by_origin():
                    seeds |= free_space_mask(world, sw)
    moving = np.zeros(len(rays), bool)
    moving[np.flatnonzero(rays.hit)] = grow_to_objects(pts, seeds)
    return moving


def ground_plane_mesh(ego_pose: np.ndarray, ego_height: float = 0.0, half_size: float = 250.0) -> TriangleMesh:
    """A flat square of road, 2 * half_size metres wide, `ego_height` metres below the ego frame's
    origin (its z = -ego_height plane), world frame: the floor any scene must beat."""
    h = float(half_size)
    z = -float(ego_height)
    corners = np.array([[-h, -h, z], [h, -h, z], [h, h, z], [-h, h, z]])
    pose = np.asarray(ego_pose, np.float64)
    world = corners @ pose[:3, :3].T + pose[:3, 3]
    return TriangleMesh(world - pose[:3, 3], [[0, 1, 2], [0, 2, 3]], labels=np.full(2, label_id("road")),
                        origin=pose[:3, 3].copy())


@dataclass(frozen=True)
class FidelityOptions:
    """What `run_fidelity` compares, and how.

    sensor: which sweep of the sample (default its first). mode: the tracer depth of the VoxSplat
    ('max_response' | 'entry'). baselines: also trace the two baselines (0.1 m voxel cubes and an
    open3d Poisson surface of the points the scene was built from, rebuilt from the build options
    stored in the scene). noise: add the sensor model's range noise (off by default: the real
    points already carry the sensor's noise), drawn with `seed`. min_range: real returns closer
    than this (metres) are no-returns. static_from: sample indices whose sweeps find the real
    returns on moving objects (see `moving_rays`); every row is then also given on the static
    rays only. raw: compare with the sweep as measured (motion compensation undone with the set's
    per-point times and poses), so the simulator's motion model is tested; compensated sets are
    otherwise replayed as stored. assume_single_origin: trace a sweep without origins whose
    geometry shows several LiDARs from its stated origin anyway (`datasets.origins`).
    ground_plane: add the row of a flat road plane under the ego (`ground_plane_mesh`, the
    frames' ``ego_height_m`` below it). regions: every row also on the real returns within
    REGION_MAX_M inside the sample's cameras, ground and above ground apart (`region_masks`),
    beside a plane fitted to the sweep (its own row), and the surface distances both ways
    (`surface_distances`) in `FidelityResult.surface`.
    """

    sensor: str | None = None
    mode: str = "max_response"
    baselines: bool = True
    noise: bool = False
    min_range: float = 1.0
    seed: int = 0
    static_from: list[int] | None = None
    raw: bool = False
    assume_single_origin: bool = False
    ground_plane: bool = False
    regions: bool = False


def run_fidelity(ds, scene, sample: int, opts: FidelityOptions = FidelityOptions(), *,
                 progress=None) -> FidelityResult:
    """Compare a VoxSplat `scene` with the real sweep of `opts.sensor` in `ds[sample]`, next to the
    two baselines (`FidelityOptions.baselines`), all traced on the same rays in the same run. Raw
    sweeps are also replayed without the motion model. progress: called with a short message
    before each long step.

    A cloud merged from several LiDARs (`LidarSweep.merged`) is traced ray by ray from each
    point's own sensor, with that sensor's model (`Sample.lidars` under its origin's name, else
    the merged sweep's). A sweep without origins whose geometry shows several is refused
    (`datasets.origins`), unless `opts.assume_single_origin`. A scene in a chunk frame (the
    converter's: metadata ``frame: chunk`` and ``chunk_to_world``) is placed in the world by it."""
    step = progress or (lambda msg: None)
    smp = ds[sample]
    sweep = smp.sweep(opts.sensor)
    if opts.raw:
        sweep = sweep.raw()
    if not sweep.merged and not opts.assume_single_origin:
        require_single_origin(sweep, f"{ds.name}: sample {sample}", min_range=opts.min_range,
                              allow_flag="assume_single_origin=True (scube-sim fidelity --assume-single-origin)")
    parts = sweep.by_origin()
    specs = [smp.lidars.get(p.sensor) or smp.lidars.get(sweep.sensor) for p in parts]
    for p, spec in zip(parts, specs):
        if spec is None:
            raise InputError(f"{ds.name}: sample {sample} has no LiDAR model for sensor {p.sensor!r}")
    configs = [spec.config for spec in specs]
    part_rays = [real_rays(p, min_range=opts.min_range) for p in parts]
    rays = concat_rays(part_rays, [invert_pose(sweep.sensor_to_world) @ p.sensor_to_world for p in parts])
    notes = list(rays.notes)
    if sweep.merged:
        notes.append(f"merged sweep: {len(parts)} LiDARs ({', '.join(p.sensor for p in parts)}), each real ray "
                     f"traced from its own sensor with its own model; range-image rows stacked in that order")

    def simulate(sc, **kw) -> SimRays:
        return concat_sims([simulate_rays(sc, c, r, p, noise=opts.noise, seed=opts.seed, **kw)
                            for c, r, p in zip(configs, part_rays, parts)])

    rows, images = {}, {"real": range_image(rays, rays.range)}
    step("tracing the VoxSplat")
    tracer = Tracer(scene, mode=opts.mode)
    placed = place_scene(tracer, scene)  # a converted scene lives in its chunk frame
    sim = simulate(placed)
    sims = {"voxsplat": sim}
    images["voxsplat"] = range_image(rays, sim.range)
    intensity_images = {"real": range_image(rays, np.where(rays.hit, rays.intensity, np.nan))}
    if tracer.reflectance is not None:
        # Before/after in one run: the same tracer without the measured reflectance.
        measured, tracer.reflectance = tracer.reflectance, None
        try:
            sims[CLASS_ROW] = simulate(placed)
        finally:
            tracer.reflectance = measured
        intensity_images["voxsplat"] = range_image(rays, sim.intensity)
        intensity_images[CLASS_ROW] = range_image(rays, sims[CLASS_ROW].intensity)
        known = np.isfinite(scene.channel("reflectance")[scene.valid])
        notes.append(f"intensity: the scene carries measured reflectance ({int(known.sum())} of {known.size} "
                     f"Gaussians); '{CLASS_ROW}' traces it without (geometry rows equal 'voxsplat')")
    else:
        intensity_images["voxsplat"] = range_image(rays, sim.intensity)
        notes.append("intensity: the scene carries no measured reflectance: class reflectivity x cos incidence")
    if not sweep.motion_compensated:
        sims["voxsplat, no motion model"] = simulate(placed, distortion=False)
        notes.append("raw sweep: 'voxsplat' fires each ray from the sensor pose at its own time (per-point "
                     "offsets, real pose stream); 'no motion model' fires all from the sweep-time pose")
    if opts.ground_plane:
        step("tracing the flat ground plane")
        height = float((smp.frames.metadata if smp.frames is not None else {}).get("ego_height_m", 0.0))
        sims[GROUND_ROW] = simulate(Tracer(ground_plane_mesh(smp.ego_pose, height)))
    build = scene.metadata.get("build") if isinstance(scene.metadata, dict) else None
    if opts.baselines and build is not None and scene.metadata.get("dataset") == ds.name:
        step("building the baselines")
        built = BuildOptions(**build)  # the points the scene was built from
        acc, _ = accumulate_from_dataset(ds, built)
        cubes = Tracer(voxel_cube_mesh(acc.points, built.voxel_size, acc.origin))
        sims[f"baseline: {built.voxel_size:g} m voxel cubes"] = simulate(cubes)
        normals, _ = surface_patches(acc.points, acc.sensor)
        pm = poisson_mesh(acc.points, normals, origin=acc.origin)
        sims["baseline: Poisson surface (open3d, depth 10)"] = simulate(Tracer(pm))
        notes.append(f"baselines rebuilt from the scene's input: {len(acc)} points of sample(s) {built.samples}")
    elif opts.baselines:
        notes.append("baselines skipped: the scene was not built from this dataset by `scube-sim build`")
    masks, plane, world = ({}, None, None)
    if opts.regions:
        if smp.frames is None or not smp.frames.images:
            raise InputError(f"{ds.name}: sample {sample} has no camera images: --regions scores the cameras' view")
        masks, plane, world = region_masks(rays, sweep, smp.frames)
        if plane is not None:
            step("tracing the plane fitted to the sweep")
            sims[FITTED_PLANE_ROW] = simulate(Tracer(plane_mesh(plane, sweep.sensor_to_world[:3, 3])))
        notes.append(f"regions: real returns within {REGION_MAX_M:g} m inside the sample's cameras ("
                     + ", ".join(f"{k}: {int(m.sum())}" for k, m in masks.items()) + f"), ground within "
                     f"{REGION_GROUND_M:g} m of a plane fitted to the sweep, above ground over it; surface "
                     f"distances to and from the scene's Gaussian means (the scene's within {REGION_MAX_M:g} m "
                     f"of the sensor, inside a camera and the sweep's elevation span)")
    for name, sr in sims.items():
        rows[name] = compare(rays, sr)
        for region, m in masks.items():
            rows[f"{name} [camera view, {region}]"] = compare(rays, sr, mask=m)
    if opts.static_from:
        step("finding returns on moving objects")
        moving = np.concatenate([moving_rays(ds, p, r, opts.static_from, [sweep.sensor])
                                 for p, r in zip(parts, part_rays)])
        for name, sr in list(sims.items()):
            rows[f"{name} [static rays]"] = compare(rays, sr, mask=~moving)
        notes.append(f"[static rays]: {int(moving.sum())} of {int(rays.hit.sum())} real returns lie on objects "
                     f"that moved (seen through by the sweeps of sample(s) {opts.static_from}, grown to whole "
                     f"objects above the ground plane) and are left out")
    if not opts.noise:
        notes.append("range noise off in the simulated sensor (the real points carry the real noise)")
    models = "; ".join(f"{c.name} (range {c.range.min_m}-{c.range.max_m} m)" for c in configs)
    notes.append(f"tracer depth: {opts.mode}; sensor model{'s' if len(configs) > 1 else ''}: {models}, incidence drop "
                 f"off: real sensors return at grazing angles")
    images["error (voxsplat - real)"] = images["voxsplat"] - images["real"]
    mismatch = range_image(rays, np.where(rays.hit != sim.hit, 1.0, np.nan)) > 0
    context = {"dataset": ds.name, "sample": sample, "sensor": sweep.sensor}
    if scene.metadata.get("build"):
        context["built from"] = scene.metadata["build"].get("samples")
    surface = surface_distances(rays, sweep, smp.frames, scene, masks, world, plane) if masks else {}
    view = camera_view(rays, sim, sweep, smp.frames.images[0]) if masks else None
    return FidelityResult(rows, images, notes, context, mismatch, intensity_images, surface, view)


def camera_view(rays: RealRays, sim: SimRays, sweep: LidarSweep, image) -> dict:
    """The real returns and the scene's replayed ones projected into `image` (a CameraImage):
    {"image", "camera", "real": (uv (N, 2), range (N,)), "scene": (uv, range), "error": (uv of the
    real returns that both hit, |scene - real| range)}, pixel coordinates, metres."""
    def project(hit, rng):
        pts = rays.cloud(rng, hit) @ sweep.sensor_to_world[:3, :3].T + sweep.sensor_to_world[:3, 3]
        kept, flat, _ = project_to_pixels(pts, image)
        w = image.intrinsics.width
        uv = np.column_stack([flat % w + 0.5, flat // w + 0.5]).astype(np.float32)
        return uv, np.flatnonzero(hit)[kept]

    uv_r, idx_r = project(rays.hit, rays.range)
    uv_s, idx_s = project(sim.hit, sim.range)
    both = sim.hit[idx_r]
    return {"image": np.asarray(image.image), "camera": image.name,
            "real": (uv_r, rays.range[idx_r]), "scene": (uv_s, sim.range[idx_s]),
            "error": (uv_r[both], np.abs(sim.range[idx_r[both]] - rays.range[idx_r[both]]))}


def write_report(result: FidelityResult, out_dir) -> dict:
    """report.md, report.json, range_images.png, intensity_images.png and (with regions)
    camera_view.png in `out_dir` (each written atomically)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"markdown": out / "report.md", "json": out / "report.json", "png": out / "range_images.png",
             "intensity_png": out / "intensity_images.png"}
    with atomic_path(paths["markdown"]) as tmp:
        Path(tmp).write_text(result.markdown())
    with atomic_path(paths["json"]) as tmp:
        Path(tmp).write_text(json.dumps({"context": result.context, "rows": result.rows, "notes": result.notes,
                                         "surface": result.surface},
                                        indent=2, default=str))
    title = ", ".join(f"{k}: {v}" for k, v in result.context.items())
    fidelity_png(paths["png"], result.images, mismatch=result.mismatch, title=title)
    if result.intensity_images:
        captions = {}
        for name in result.intensity_images:
            static = f"{name} [static rays]"
            m = result.rows.get(static, result.rows.get(name))
            if m is not None:
                captions[name] = (f"intensity r {m['intensity_r']:.2f}, RMSE {m['intensity_rmse']:.3f}"
                                  + (" on static rays" if static in result.rows else ""))
        intensity_png(paths["intensity_png"], result.intensity_images, title=title, captions=captions)
    else:
        paths.pop("intensity_png")
    if result.camera_view is not None:
        v = result.camera_view
        paths["camera_png"] = out / "camera_view.png"
        sweeps_over_image_png(paths["camera_png"], v["image"],
                              {"real returns": v["real"], "replayed through the scene": v["scene"],
                               "|replayed - real| where both return": v["error"]},
                              title=f"{title}; camera {v['camera']}", error_panel="|replayed - real| where both return")
    return paths
