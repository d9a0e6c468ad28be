"""Real LiDAR -> VoxSplat (the paper's data pipeline, step 1).

Accumulate sweeps in the world frame, optionally remove the points of moving objects (labelled
boxes, or free-space carving with another sweep), connect each sweep's neighbouring returns into
triangles in its range image, and fit M Gaussians per voxel with `fit.fit_voxsplat` to samples of
those triangles (returns in no triangle bring a small patch of their neighbourhood); colour from
the cameras where images exist, labels from the labelled boxes where the set has them, and
reflectance from the returns' intensities (each sweep's own sensor response inverted: range
fall-off, incidence cosine, per-laser corrections; `lidar.response`), averaged per Gaussian into
the VoxSplat's `reflectance` channel.

A LiDAR sweep samples a surface densely along each ring but sparsely across rings (an HDL-32E's
rings are 0.46 m apart on a wall 20 m away, 5 m apart on the ground there): a voxel often holds a
few points of one ring. Their own scatter would make a needle; the triangles between rings fill
the gap, so that a ray from a nearby pose still finds the surface.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from types import SimpleNamespace

import numpy as np

from ..boxes import Box, points_in_boxes
from ..camera.frames import Frames
from ..config import listed_twice
from ..datasets.base import LidarSweep, Sample
from ..datasets.origins import require_single_origin
from ..errors import InputError
from ..fit import FitOptions, fit_voxsplat
from ..lidar.config import LidarConfig, SpinningPattern
from ..lidar.pattern import channels_by_elevation
from ..lidar.response import Response
from ..mesh import TriangleMesh
from ..transforms import invert_pose, transform_points
from ..voxsplat import KNOWN_CHANNELS, VoxSplat
from .options import check_build_options


def _scipy() -> SimpleNamespace:
    """The scipy pieces used here, imported on first use: `runs.batch_jobs` imports this module at its top,
    and only building a scene (or scoring one) needs them."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import Delaunay, cKDTree

    return SimpleNamespace(coo_matrix=coo_matrix, connected_components=connected_components, Delaunay=Delaunay,
                           cKDTree=cKDTree)


@dataclass
class Accumulated:
    """Points of several sweeps in one frame. points (N, 3) float64 metres, relative to `origin`
    (float64 world; world = points + origin, so float64 stays exact far from the map origin);
    sensor (N, 3) the sensor position each point was seen from (same frame); intensity (N,)
    float32 in [0, 1]; labels (N,) int16 label ids (0 where unknown); sweep (N,) int32 index;
    ring (N,) int16 the sensor's channel (index into its per-channel tables; -1 where unknown);
    responses: per sweep index, the sensor's intensity response (None where the sweep has no
    intensity or no sensor model)."""

    points: np.ndarray
    sensor: np.ndarray
    intensity: np.ndarray
    labels: np.ndarray
    sweep: np.ndarray
    origin: np.ndarray
    removed: int = 0
    notes: list[str] = field(default_factory=list)
    faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    ring: np.ndarray | None = None
    responses: list = field(default_factory=list)

    def __post_init__(self):
        if self.ring is None:
            self.ring = np.full(self.points.shape[0], -1, np.int16)

    def __len__(self) -> int:
        return self.points.shape[0]

    def subset(self, keep: np.ndarray) -> "Accumulated":
        """The points where `keep` (N,) bool; triangles lose any corner that goes."""
        keep = np.asarray(keep, bool)
        new = np.cumsum(keep) - 1
        faces = self.faces[np.all(keep[self.faces], axis=1)] if len(self.faces) else self.faces
        return Accumulated(self.points[keep], self.sensor[keep], self.intensity[keep], self.labels[keep],
                           self.sweep[keep], self.origin, self.removed + int((~keep).sum()), list(self.notes),
                           new[faces] if len(faces) else faces, self.ring[keep], list(self.responses))


DYNAMIC_SPEED = 0.5  # m/s: remove='dynamic' drops the points in boxes moving faster than this
BOX_MARGIN = 0.1  # metres: a box holds the points within this of its faces (`points_in_boxes`)


def accumulate(samples: list[Sample], opts: BuildOptions | None = None, *,
               origin: np.ndarray | None = None) -> Accumulated:
    """Gather the sweeps of `samples` in the world frame.

    opts: the cloud's settings (default: `BuildOptions`' defaults); read here are sensors,
    min_range, max_range, remove, mesh, the mesh_* limits and assume_single_origin, not
    `opts.samples` (the samples are given). sensors: which sweeps (default all). Returns closer
    than `min_range` metres are dropped (the ego body and the no-return placeholders some sets
    store); `max_range` optionally drops far ones. remove: 'none' | 'dynamic' (points in boxes
    moving faster than DYNAMIC_SPEED m/s, or of unknown speed in multi-sample builds) | 'all'
    (every box). Points inside remaining boxes (BOX_MARGIN metres around) take the box's label.
    origin: the local frame (float64 world; default: the first sweep's sensor position). mesh:
    also connect each sweep's neighbouring returns into triangles (`range_image_mesh` with the
    mesh_* limits; the angle limit widened to a sensor's own ring gap where that is wider:
    `mesh_angle_deg`).

    A cloud merged from several LiDARs (`LidarSweep.merged`) is split by origin first: each part
    is meshed in its own sensor's range image, seen from its own position, with its own sensor
    model (`Sample.lidars` under its origin's name, else the merged sweep's). A sweep without
    origins whose geometry shows several (`datasets.origins.check_origin`) is refused with
    MergedCloudError, unless `opts.assume_single_origin`.
    """
    opts = BuildOptions(samples=[]) if opts is None else opts
    if opts.remove not in ("none", "dynamic", "all"):
        raise InputError(f"remove: expected 'none', 'dynamic' or 'all', got {opts.remove!r}")
    sweeps: list[tuple[LidarSweep, list[Box]]] = []
    configs = []  # each sweep's sensor model, where the sample has one
    notes = []
    for s in samples:
        for sw in s.sweeps:
            if opts.sensors is not None and sw.sensor not in opts.sensors:
                continue
            if not sw.merged and not opts.assume_single_origin:
                require_single_origin(sw, f"sample {s.name!r}", min_range=opts.min_range,
                                      allow_flag="assume_single_origin=True (scube-sim build --assume-single-origin)")
            parts = sw.by_origin()
            if sw.merged:
                notes.append(f"sample {s.name!r}: sweep {sw.sensor!r} merges {len(parts)} LiDARs "
                             f"({', '.join(p.sensor for p in parts)}): each part meshed from its own origin")
            for part in parts:
                sweeps.append((part, s.boxes))
                spec = s.lidars.get(part.sensor) or s.lidars.get(sw.sensor)
                configs.append(None if spec is None else spec.config)
    responses = [None if c is None or sw.intensity is None else Response(c.intensity)
                 for c, (sw, _) in zip(configs, sweeps)]
    if not sweeps:
        which = "" if opts.sensors is None else " of " + ", ".join(opts.sensors)
        raise InputError(f"accumulate: no LiDAR sweeps{which} in {len(samples)} sample(s)")
    origin = sweeps[0][0].sensor_to_world[:3, 3].copy() if origin is None else np.asarray(origin, np.float64)
    parts = {k: [] for k in ("points", "sensor", "intensity", "labels", "sweep", "ring", "faces")}
    removed = 0
    base = 0
    for k, (sw, boxes) in enumerate(sweeps):
        r = np.linalg.norm(sw.points, axis=1)
        keep = r >= opts.min_range
        if opts.max_range is not None:
            keep &= r <= opts.max_range
        sw = sw.subset(keep)
        poses = sw.point_poses()
        world = sw.world_points()
        labels = np.zeros(len(sw), np.int16)
        if boxes:
            inside = points_in_boxes(world, boxes, margin=BOX_MARGIN)
            drop = np.zeros(len(boxes), bool)
            if opts.remove == "all":
                drop[:] = True
            elif opts.remove == "dynamic":
                speeds = np.array([b.speed for b in boxes])
                drop = speeds > DYNAMIC_SPEED
                if len(samples) > 1:
                    drop |= ~np.isfinite(speeds)
            gone = (inside >= 0) & drop[np.maximum(inside, 0)]
            removed += int(gone.sum())
            ids = np.array([b.label for b in boxes], np.int16)
            labels = np.where(inside >= 0, ids[np.maximum(inside, 0)], 0).astype(np.int16)
            keep2 = ~gone
            world, labels, poses, sw = world[keep2], labels[keep2], poses[keep2], sw.subset(keep2)
        if opts.mesh and len(sw) >= 3:
            parts["faces"].append(range_image_mesh(sw.points, max_edge=opts.mesh_max_edge,
                                                   max_edge_rel=opts.mesh_max_edge_rel,
                                                   max_angle_deg=mesh_angle_deg(configs[k], opts.mesh_max_angle_deg),
                                                   max_incidence_deg=opts.mesh_max_incidence_deg) + base)
        base += len(sw)
        inten = (np.zeros(len(sw), np.float32) if sw.intensity is None
                 else np.clip(sw.intensity / sw.intensity_max, 0, 1).astype(np.float32))
        parts["points"].append(world - origin)
        parts["sensor"].append(poses[:, :3, 3] - origin)
        parts["intensity"].append(inten)
        parts["labels"].append(labels)
        parts["sweep"].append(np.full(len(sw), k, np.int32))
        channel = np.full(len(sw), -1, np.int16)
        if sw.ring is not None and configs[k] is not None:
            dirs = sw.points / np.maximum(np.linalg.norm(sw.points, axis=1), 1e-9)[:, None]
            channel = channels_by_elevation(dirs, sw.ring, configs[k]).astype(np.int16)
        parts["ring"].append(channel)
    face_parts = parts.pop("faces")
    faces = np.concatenate(face_parts) if face_parts else np.zeros((0, 3), np.int64)
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    return Accumulated(cat["points"], cat["sensor"], cat["intensity"], cat["labels"], cat["sweep"], origin, removed,
                       notes, faces, cat["ring"], responses)


RING_GAP_SLACK = 1.15  # a triangle between rings spans the ring gap and a little azimuth


def mesh_angle_deg(config: LidarConfig | None, max_angle_deg: float) -> float:
    """The angle limit for meshing one sensor's range image: `max_angle_deg`, or a little over the
    sensor's median ring gap where that is wider (a VLP-16's rings are 2 degrees apart: under a
    1.5 degree limit its rings would never be joined). Degrees."""
    if config is None or not isinstance(config.pattern, SpinningPattern):
        return max_angle_deg
    el = np.unique(np.asarray(config.pattern.channels.elevation_deg, np.float64))
    if el.size < 2:
        return max_angle_deg
    return max(max_angle_deg, RING_GAP_SLACK * float(np.median(np.diff(el))))


def range_image_mesh(points: np.ndarray, *, max_edge: float = 0.5, max_edge_rel: float = 0.2,
                     max_angle_deg: float = 1.5, max_incidence_deg: float = 88.0) -> np.ndarray:
    """Triangles between neighbouring returns of one sweep: (F, 3) int64 indices into `points`.

    points (N, 3) metres in the sensor frame. The returns are triangulated in (azimuth,
    elevation), which connects each return to its neighbours on its own and the adjacent rings
    without needing ring ids. A triangle is kept only where it spans one surface: every edge at
    most `max_angle_deg` apart as seen from the sensor (no bridging over no-returns) and at most
    `max_edge` metres or `max_edge_rel` x the nearer range long, and its normal at most
    `max_incidence_deg` from the sensor's line of sight. A triangle across a depth jump lies
    almost along the rays; the ground 20 m from a car's roof is seen at ~85 degrees.
    """
    Delaunay = _scipy().Delaunay

    p = np.asarray(points, np.float64)
    r = np.linalg.norm(p, axis=1)
    ang = np.stack([np.arctan2(p[:, 1], p[:, 0]), np.arcsin(np.clip(p[:, 2] / np.maximum(r, 1e-12), -1, 1))], 1)
    try:
        tri = Delaunay(ang).simplices.astype(np.int64)
    except Exception:  # qhull: all points collinear or too few
        return np.zeros((0, 3), np.int64)
    keep = np.ones(tri.shape[0], bool)
    lim_ang = np.deg2rad(max_angle_deg)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        i, j = tri[:, a], tri[:, b]
        keep &= np.linalg.norm(ang[i] - ang[j], axis=1) <= lim_ang
        keep &= np.linalg.norm(p[i] - p[j], axis=1) <= np.maximum(max_edge, max_edge_rel * np.minimum(r[i], r[j]))
    v0, v1, v2 = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
    n = np.cross(v1 - v0, v2 - v0)
    c = (v0 + v1 + v2) / 3.0
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_inc = np.abs(np.einsum("ij,ij->i", n, c)) / (np.linalg.norm(n, axis=1) * np.linalg.norm(c, axis=1))
    keep &= cos_inc >= np.cos(np.deg2rad(max_incidence_deg))
    return tri[keep]


def surface_patches(points: np.ndarray, sensor: np.ndarray, *, neighbours: int = 16, radius: float = 1.0,
                    patch_scale: float = 0.5, normal_sigma: float = 0.005,
                    max_patch_sigma: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The surface patch each point stands for.

    points, sensor (N, 3) metres. Each point's `neighbours` nearest points within `radius` give
    the local tangent plane (PCA); the patch covariance is `patch_scale` times their spread
    projected into that plane (each axis capped at `max_patch_sigma` metres std, so that blobs do
    not overhang edges), plus `normal_sigma`^2 along the normal. Returns normals (N, 3)
    unit, facing the sensor, and the patch covariances (N, 6) as xx, xy, xz, yy, yz, zz.
    """
    cKDTree = _scipy().cKDTree

    p = np.asarray(points, np.float64)
    n = p.shape[0]
    k = min(neighbours, n)
    tree = cKDTree(p)
    dist, idx = tree.query(p, k=k, distance_upper_bound=radius, workers=1)
    valid = np.isfinite(dist)
    idx = np.where(valid, idx, np.arange(n)[:, None])  # missing neighbours: the point itself
    cnt = valid.sum(1).astype(np.float64)
    nb = p[idx]  # (N, k, 3)
    w = valid[..., None].astype(np.float64)
    mean = (nb * w).sum(1) / cnt[:, None]
    q = (nb - mean[:, None, :]) * w
    cov = np.einsum("nki,nkj->nij", q, q) / cnt[:, None, None]
    evals, evecs = np.linalg.eigh(cov)
    normal = evecs[:, :, 0]
    view = sensor - p
    normal = np.where((np.einsum("ij,ij->i", normal, view) < 0)[:, None], -normal, normal)
    proj = np.eye(3)[None] - normal[:, :, None] * normal[:, None, :]
    patch = patch_scale * proj @ cov @ proj
    if max_patch_sigma is not None:
        pe, pv = np.linalg.eigh(patch)
        patch = (pv * np.minimum(np.maximum(pe, 0.0), max_patch_sigma ** 2)[:, None, :]) @ np.swapaxes(pv, 1, 2)
    patch = patch + normal_sigma ** 2 * normal[:, :, None] * normal[:, None, :]
    # A point with under 3 neighbours has no plane: an isotropic speck of normal_sigma.
    lonely = cnt < 3
    patch[lonely] = normal_sigma ** 2 * np.eye(3)
    cov6 = np.stack([patch[:, 0, 0], patch[:, 0, 1], patch[:, 0, 2], patch[:, 1, 1], patch[:, 1, 2],
                     patch[:, 2, 2]], axis=1)
    return normal.astype(np.float64), cov6


def color_from_frames(points_world: np.ndarray, frames: Frames, *, block: int = 4,
                      tolerance: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Colour world points (N, 3) float64 from the images of `frames`.

    Each point takes the pixel of the camera that sees it nearest its image centre; a point is
    seen if it projects into the image in front of the camera and is not behind other points:
    the points' own depth, min-pooled over `block` x `block` pixel cells, is the occluder
    (tolerance: metres + 5 % of the depth). Returns colors (N, 3) float32 in [0, 1] (grey 0.5
    where unseen) and seen (N,) bool."""
    p = np.asarray(points_world, np.float64)
    n = p.shape[0]
    color = np.full((n, 3), 0.5, np.float32)
    best = np.full(n, np.inf)
    for im in frames.images:
        intr = im.intrinsics
        pc = transform_points(invert_pose(im.cam_to_world), p)
        uv, z = intr.project(pc)
        ok = (z > 0.3) & np.all(np.isfinite(uv), axis=1)
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] < intr.width) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.height)
        i = np.flatnonzero(ok)
        if i.size == 0:
            continue
        u, v = uv[i, 0].astype(np.int64), uv[i, 1].astype(np.int64)
        bw, bh = -(-intr.width // block), -(-intr.height // block)
        cell = (v // block) * bw + (u // block)
        zmin = np.full(bw * bh, np.inf)
        np.minimum.at(zmin, cell, z[i])
        visible = z[i] <= zmin[cell] + tolerance + 0.05 * zmin[cell]
        i, u, v = i[visible], u[visible], v[visible]
        centre = np.hypot((u - intr.cx) / intr.width, (v - intr.cy) / intr.height)
        better = centre < best[i]
        i, u, v = i[better], u[better], v[better]
        best[i] = centre[better]
        color[i] = im.image[v, u, :3].astype(np.float32) / 255.0
    return color, np.isfinite(best)


def return_reflectance(acc: Accumulated, index: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Reflectance estimates of the returns acc[index] (K,) seen on surfaces of unit `normals`
    (K, 3): each one's sweep's sensor response inverted at the return's range, incidence and
    laser. (K,) float64, NaN where the sweep has no intensity or no sensor model; capped at the
    channel's bound."""
    index = np.asarray(index, np.int64)
    v = acc.points[index] - acc.sensor[index]
    r = np.linalg.norm(v, axis=1)
    cos = np.abs(np.einsum("ij,ij->i", normals, v)) / np.maximum(r, 1e-9)
    out = np.full(index.shape[0], np.nan)
    sweep = acc.sweep[index]
    for k, resp in enumerate(acc.responses):
        if resp is not None:
            sel = sweep == k
            out[sel] = resp.inverse(acc.intensity[index[sel]], cos[sel], r[sel], acc.ring[index[sel]])
    return np.minimum(out, KNOWN_CHANNELS["reflectance"].bounds[1])


def face_reflectance(acc: Accumulated) -> np.ndarray:
    """(F,) reflectance of each triangle of `acc.faces`: the mean of its corners' estimates, each
    inverted with the triangle's own normal (so a corner on a crease, a wall's foot, is read
    with the incidence of each face it belongs to, not an average normal); NaN where no corner
    has an estimate."""
    f = acc.faces
    p = acc.points
    n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    corners = return_reflectance(acc, f.ravel(), np.repeat(n, 3, axis=0)).reshape(-1, 3)
    known = np.isfinite(corners)
    with np.errstate(invalid="ignore"):
        return np.where(known, corners, 0.0).sum(1) / known.sum(1)


@dataclass
class BuildReport:
    """What `build_voxsplat` did, for the CLI and the notes."""

    points: int
    removed: int
    colored: int
    voxels: int
    gaussians: int
    voxel_size: float
    gaussians_per_voxel: int
    reflectance: int = 0  # returns whose sweep has intensity and a sensor model (reflectance estimated)


def build_voxsplat(acc: Accumulated, *, voxel_size: float = 0.1, gaussians_per_voxel: int = 4,
                   frames: list[Frames] | None = None, neighbours: int = 16, patch_scale: float = 0.5,
                   max_patch_sigma: float | None = 0.03, max_normal_scale: float = 0.02, min_scale: float | None = None,
                   opacity: float = 0.99, all_points: bool = False,
                   reflectance: bool = True) -> tuple[VoxSplat, BuildReport]:
    """Fit a VoxSplat (origin = acc.origin) to accumulated points.

    Where the sweeps were meshed (`acc.faces`), the triangles are sampled at the voxel size and
    each sample brings its sub-triangle's exact covariance (the same fit as the worlds' ground
    truth; finer sampling only costs time, the covariance already being exact); returns in no
    triangle (thin poles, isolated hits) are fitted as points with their neighbourhood patch
    (`surface_patches`); with `all_points` every return adds its patch too, which carries the
    surface a little past the mesh's borders. max_normal_scale caps each Gaussian's thickness
    (metres, std) so range noise does not inflate surfaces. reflectance: estimate the returns'
    reflectance (`return_reflectance`; a return in no triangle with its neighbourhood's normal)
    and store its mean per Gaussian as the `reflectance` channel (a
    sample of a triangle takes the mean of its corners', each read with the triangle's normal:
    `face_reflectance`)."""
    n = len(acc)
    colors = None
    colored = 0
    if frames:
        colors = np.full((n, 3), 0.5, np.float32)
        seen_any = np.zeros(n, bool)
        for fr in frames:
            c, seen = color_from_frames(acc.points + acc.origin, fr)
            colors[seen] = c[seen]
            seen_any |= seen
        colored = int(seen_any.sum())
    used = np.zeros(n, bool)
    used[acc.faces.ravel()] = True
    lonely = np.arange(n) if all_points else np.flatnonzero(~used)
    pca_normals, cov_pts = surface_patches(acc.points, acc.sensor, neighbours=neighbours, patch_scale=patch_scale,
                                           max_patch_sigma=max_patch_sigma)
    measure = reflectance and any(r is not None for r in acc.responses)
    pts, wts, labs, cols, table, index, refl = [], [], [], [], [], [], []
    nf = len(acc.faces)
    if nf:
        f = acc.faces
        l0, l1, l2 = (acc.labels[f[:, k]] for k in range(3))
        face_lab = np.where((l0 == l1) | (l0 == l2), l0, np.where(l1 == l2, l1, 0)).astype(np.int16)
        face_col = None if colors is None else colors[f].mean(axis=1)
        smp = TriangleMesh(acc.points, f, labels=face_lab, colors=face_col).sample_surface_grid(voxel_size)
        pts.append(smp["points"]), wts.append(smp["weights"]), labs.append(smp["labels"])
        cols.append(smp["colors"])
        table.append(smp["patch_cov"]), index.append(smp["face"])
        if measure:
            refl.append(face_reflectance(acc)[smp["face"]])
    # A lone return stands for about as much surface as a sample (its patch sets the shape).
    pts.append(acc.points[lonely]), wts.append(np.full(lonely.size, (0.5 * voxel_size) ** 2))
    labs.append(acc.labels[lonely])
    cols.append(np.full((lonely.size, 3), 0.5, np.float32) if colors is None else colors[lonely])
    table.append(cov_pts[lonely]), index.append(nf + np.arange(lonely.size))
    if measure:
        refl.append(return_reflectance(acc, lonely, pca_normals[lonely]))
    fit = FitOptions(gaussians_per_voxel=gaussians_per_voxel, min_scale=min_scale, max_normal_scale=max_normal_scale,
                     opacity=opacity)
    vs = fit_voxsplat(np.concatenate(pts), voxel_size,
                      colors=None if colors is None else np.concatenate(cols), labels=np.concatenate(labs),
                      weights=np.concatenate(wts), patch_cov=(np.concatenate(table), np.concatenate(index)),
                      values={"reflectance": np.concatenate(refl)} if measure else None, origin=acc.origin, fit=fit)
    with_model = np.array([r is not None for r in acc.responses] + [False], bool)
    measured = int(with_model[acc.sweep].sum()) if measure else 0
    report = BuildReport(n, acc.removed, colored, vs.num_voxels, int(vs.valid.sum()), float(voxel_size),
                         int(gaussians_per_voxel), measured)
    return vs, report


def free_space_mask(points_world: np.ndarray, sweep: LidarSweep, *, angle_deg: float = 0.3,
                    margin: float = 0.5, relative: float = 0.05) -> np.ndarray:
    """(N,) bool: world points (N, 3) that `sweep` saw through (a ray of it passed the point's
    position and returned at least `margin` + `relative` x range beyond it). Such points were
    not there when `sweep` was taken: moving objects. Logs without labelled boxes use this to
    remove them (free-space carving with a second sweep)."""
    cKDTree = _scipy().cKDTree

    local = transform_points(invert_pose(sweep.sensor_to_world), np.asarray(points_world, np.float64))
    rp = np.linalg.norm(local, axis=1)
    r = np.linalg.norm(sweep.points, axis=1)
    ok = r > 1.0
    dirs = sweep.points[ok] / r[ok, None]
    dist, j = cKDTree(dirs).query(local / np.maximum(rp, 1e-9)[:, None], k=1)
    near = dist <= np.deg2rad(angle_deg)  # chord ~ angle for small angles
    return near & (r[ok][np.minimum(j, ok.sum() - 1)] > rp + margin + relative * rp)


@dataclass
class BuildOptions:
    """Everything `build_from_dataset` needs to rebuild the same cloud (stored in the VoxSplat's
    metadata, so `fidelity` can rebuild the baselines from the same points)."""

    samples: list[int]
    sensors: list[str] | None = None
    min_range: float = 1.0
    max_range: float | None = None
    remove: str = "none"
    carve_with: list[int] = field(default_factory=list)
    grow_objects: bool = True
    mesh: bool = True
    mesh_max_angle_deg: float = 1.5
    mesh_max_edge: float = 0.5
    mesh_max_edge_rel: float = 0.2
    mesh_max_incidence_deg: float = 88.0
    voxel_size: float = 0.1
    gaussians_per_voxel: int = 4
    patch_scale: float = 0.5
    max_patch_sigma: float | None = 0.03
    max_normal_scale: float = 0.02
    all_points: bool = False
    color: bool = True
    reflectance: bool = True
    assume_single_origin: bool = False

    def __post_init__(self):
        check_build_options(self)  # each number in its range (`realdata.options.BUILD_RANGES`)


def check_build_lists(opts: BuildOptions, prefix: str = "") -> None:
    """InputError where `opts` lists a sample or sensor twice (its sweeps would count twice):
    `samples: 0 is listed twice (at [0] and [1])`, each key after `prefix`."""
    for key in ("samples", "sensors", "carve_with"):
        msg = listed_twice(list(getattr(opts, key) or []))
        if msg:
            raise InputError(f"{prefix}{key}: {msg}")


def accumulate_from_dataset(ds, opts: BuildOptions) -> tuple[Accumulated, list[Sample]]:
    """Load the samples, accumulate their sweeps and carve away what other sweeps saw through."""
    check_build_lists(opts)
    samples = [ds[i] for i in opts.samples]
    acc = accumulate(samples, opts)
    carved = 0
    for j in opts.carve_with:
        for whole in ds[j].sweeps:
            if opts.sensors is not None and whole.sensor not in opts.sensors:
                continue
            for sw in whole.by_origin():  # a merged cloud carves from each sensor's own origin
                gone = free_space_mask(acc.points + acc.origin, sw)
                if opts.grow_objects:
                    gone = grow_to_objects(acc.points, gone)
                carved += int(gone.sum())
                acc = acc.subset(~gone)
    if opts.carve_with:
        acc.notes.append(f"{carved} points removed as moving: seen through by sample(s) {opts.carve_with}")
    return acc, samples


def build_from_dataset(ds, opts: BuildOptions) -> tuple[VoxSplat, BuildReport, Accumulated]:
    """The `scube-sim build` pipeline: a VoxSplat from the dataset's samples `opts.samples`."""
    acc, samples = accumulate_from_dataset(ds, opts)
    frames = [s.frames for s in samples if s.frames is not None] if opts.color else None
    vs, report = build_voxsplat(acc, voxel_size=opts.voxel_size, gaussians_per_voxel=opts.gaussians_per_voxel,
                                frames=frames, patch_scale=opts.patch_scale, max_patch_sigma=opts.max_patch_sigma,
                                max_normal_scale=opts.max_normal_scale, all_points=opts.all_points,
                                reflectance=opts.reflectance)
    vs.metadata = {"source": "lidar", "dataset": ds.name, "root": str(ds.root), "build": asdict(opts),
                   "poses_from_icp": bool(getattr(ds, "poses_from_icp", False)), "notes": acc.notes,
                   "report": asdict(report)}
    return vs, report, acc


def height_above_ground(points: np.ndarray, *, cell: float = 1.0) -> np.ndarray:
    """(N,) metres above the local ground: the lowest point within the 3 x 3 cells of `cell`
    metres around each point (roads slope and crown; one plane does not fit a whole sweep)."""
    p = np.asarray(points, np.float64)
    ij = np.floor(p[:, :2] / cell).astype(np.int64)
    ij -= ij.min(axis=0)
    w, h = int(ij[:, 0].max()) + 3, int(ij[:, 1].max()) + 3
    low = np.full((w, h), np.inf)
    np.minimum.at(low, (ij[:, 0] + 1, ij[:, 1] + 1), p[:, 2])
    pooled = np.full((w, h), np.inf)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            pooled[1:-1, 1:-1] = np.minimum(pooled[1:-1, 1:-1], low[1 + di:w - 1 + di, 1 + dj:h - 1 + dj])
    return p[:, 2] - pooled[ij[:, 0] + 1, ij[:, 1] + 1]


def grow_to_objects(points: np.ndarray, seeds: np.ndarray, *, radius: float = 0.3, ground_height: float = 0.3,
                    min_seed_share: float = 0.05, max_extent: float = 20.0) -> np.ndarray:
    """(N,) bool: the whole objects that free-space carving touched.

    Carving finds only the parts of a moving object that another sweep saw through; the rest of
    it stays. Points (N, 3) (z up) more than `ground_height` metres above the local ground are
    linked within `radius` into objects; an object at most `max_extent` metres across whose
    share of carved `seeds` (N,) bool is at least `min_seed_share` is marked whole."""
    sp = _scipy()

    p = np.asarray(points, np.float64)
    out = np.asarray(seeds, bool).copy()
    if not out.any() or len(p) < 10:
        return out
    above = np.flatnonzero(height_above_ground(p) > ground_height)
    if above.size == 0:
        return out
    pairs = sp.cKDTree(p[above]).query_pairs(radius, output_type="ndarray")
    m = above.size
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
    ncomp, comp = sp.connected_components(graph, directed=False)
    total = np.bincount(comp, minlength=ncomp)
    hit = np.bincount(comp, weights=out[above].astype(np.float64), minlength=ncomp)
    lo = np.full((ncomp, 3), np.inf)
    hi = np.full((ncomp, 3), -np.inf)
    np.minimum.at(lo, comp, p[above])
    np.maximum.at(hi, comp, p[above])
    moving = (hit >= min_seed_share * total) & (hit > 0) & (np.max(hi - lo, axis=1) <= max_extent)
    out[above[moving[comp]]] = True
    return out
