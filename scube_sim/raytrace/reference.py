"""The reference traversal of hard- and soft-opacity Gaussians: a NumPy face walk over Embree
triangle proxies with exact float64 tests (`TraceCore`; a compiled core implements the same
`TraceCore` and is tested against this one, ray for ray).

A ray finds proxy faces in order of distance, one Embree first-hit cast per step; each face
names a Gaussian (or a voxel's Gaussians), which is tested exactly (gaussian_math). The ray is
re-cast from just past each face until the next face lies beyond the best exact hit: the result
is the exact nearest hit, whatever the overlap of the proxies, for rays that start outside every
proxy. A hard ray starting inside one (t_min > 0 inside a Gaussian) meets that proxy only at its
exit face, and the walk may stop at a farther hit before reaching it (a few of the random rays
in `tests/raytrace/test_core.py`'s scene). The compiled core has no such blind spot. Soft mode composites every
contribution front to back until the transmittance falls below its threshold.

Frames: everything here is in the scene's local frame (world = local + origin), float64, with
unit directions; only the Embree casts are float32.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..voxsplat import Gaussians
from . import gaussian_math as gm
from .backends import BACKENDS, DEFAULT_BACKEND, make_backend
from .contracts import HardMode, SceneGaussians, SoftMode, TraceMode, TracerBackend
from .hits import Hits, TraceStats

STEP_ULPS = 1.0  # first re-cast step past a face, in float32 ulps of the face position (grows on a re-hit)


@dataclass
class PreparedGaussians:
    """What a traversal needs of a scene, built once by `Tracer` (all local frame, float64).

    gaussians: the kept Gaussians (|scales| floored); mu (G, 3) means; a (G, 3, 3) world-to-unit
    frame matrices; opacity (G,); backend: the Embree BVH of the proxies, whose primitive p
    belongs to proxy p // faces_per_proxy. Per-Gaussian proxies: frame_scale (G,) and the
    template's planes (planes_n (F, 3), planes_h (F,)). Voxel boxes: box_center, box_half (B, 3)
    and box_members (B, M) Gaussian ids (-1 padded). lo, hi (3,): the search box (the proxies'
    bounds, padded);
    num_faces: triangles in the BVH; attributes: the scene the proxies were built from."""

    gaussians: Gaussians
    mu: np.ndarray
    a: np.ndarray
    opacity: np.ndarray
    k: float
    proxy: str
    backend: TracerBackend
    faces_per_proxy: int
    planes_n: np.ndarray
    planes_h: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    num_faces: int
    attributes: SceneGaussians
    frame_scale: np.ndarray | None = None
    box_center: np.ndarray | None = None
    box_half: np.ndarray | None = None
    box_members: np.ndarray | None = None


class ReferenceCore:
    """The NumPy face walk as a `TraceCore`: proxies (`proxy`: 'octahedron' | 'icosahedron' per
    Gaussian, or 'voxel_box' per voxel) in an Embree triangle BVH (`backend`: 'open3d' |
    'embreex' | 'compiled'), walked face by face with exact float64 tests.

    exact_order: True returns each ray's nearest exact hit; False stops a hard ray at the first
    exact hit found in proxy order (faster; `make bench` measures its range error on overlapping
    Gaussians). max_iterations: Embree casts per ray at most."""

    name = "reference"

    def __init__(self, backend: str = DEFAULT_BACKEND, proxy: str = "octahedron", exact_order: bool = True,
                 max_iterations: int = 1000):
        if backend not in BACKENDS:
            raise InputError(f"backend: expected one of {BACKENDS}, got {backend!r}")
        if proxy not in gm.PROXY_KINDS:
            raise InputError(f"proxy: expected one of {gm.PROXY_KINDS}, got {proxy!r}")
        if int(max_iterations) < 1:
            raise InputError(f"max_iterations: expected at least 1, got {max_iterations}")
        self.backend, self.proxy = backend, proxy
        self.exact_order, self.max_iterations = bool(exact_order), int(max_iterations)

    def prepare(self, scene: SceneGaussians) -> PreparedGaussians:
        g, pad = scene.gaussians, scene.pad
        lo, hi = scene.aabb_lo, scene.aabb_hi
        if self.proxy == "voxel_box":
            vs = scene.voxsplat
            if vs is None:
                raise InputError("proxy 'voxel_box' needs a VoxSplat scene (Gaussians on a voxel grid)")
            # One box per voxel: the union of its Gaussians' k-sigma bounding boxes.
            vox, inv = np.unique(scene.voxel, return_inverse=True)
            inv = inv.reshape(-1)
            blo = np.full((vox.shape[0], 3), np.inf)
            bhi = np.full((vox.shape[0], 3), -np.inf)
            for ax in range(3):
                np.minimum.at(blo[:, ax], inv, lo[:, ax])
                np.maximum.at(bhi[:, ax], inv, hi[:, ax])
            counts = np.bincount(inv, minlength=vox.shape[0])
            m = int(counts.max()) if counts.size else 1
            order = np.argsort(inv, kind="stable")
            starts = np.r_[0, np.cumsum(counts)[:-1]]
            slot = np.arange(order.shape[0]) - starts[inv[order]]
            box_members = np.full((vox.shape[0], m), -1, np.int64)
            box_members[inv[order], slot] = order
            # Boxes of neighbouring voxels share face planes (a flat ground gives every box the
            # same top), and Embree reports one of several faces met at the same distance. So
            # overlapping boxes get different dilations: a class per voxel index modulo c, where
            # c = 2 * reach + 1 and reach is how many cells a box reaches beyond its own.
            ijk = vs.ijk[vox].astype(np.int64)
            cell_lo = ijk * vs.voxel_size
            reach = max(np.max((cell_lo - blo) / vs.voxel_size), np.max((bhi - cell_lo) / vs.voxel_size - 1), 0.0)
            c = 2 * int(np.ceil(reach)) + 1
            cls = (ijk[:, 0] % c) * c * c + (ijk[:, 1] % c) * c + (ijk[:, 2] % c)
            dil = pad * (1.0 + 2.0 * cls)
            v, f, fpp = gm.box_proxies(blo, bhi, dil)
            box_center = 0.5 * (blo + bhi)
            box_half = 0.5 * (bhi - blo) + dil[:, None]
            frame_scale = None
        else:
            v, f, fpp, frame_scale = gm.gaussian_proxies(self.proxy, scene.mu, scene.rot, g.scales, scene.k, pad)
            box_center = box_half = box_members = None
        planes_n, planes_h = gm.template_planes(self.proxy)
        return PreparedGaussians(
            gaussians=g, mu=scene.mu, a=scene.a, opacity=scene.opacity, k=scene.k, proxy=self.proxy,
            backend=make_backend(self.backend, v, f), faces_per_proxy=fpp, planes_n=planes_n, planes_h=planes_h,
            # The search box reaches beyond the padded proxies, so a clipped ray never starts
            # inside a proxy it cannot then leave.
            lo=(v.min(0).astype(np.float64) if len(v) else np.zeros(3)) - 2.0 * pad,
            hi=(v.max(0).astype(np.float64) if len(v) else np.zeros(3)) + 2.0 * pad, num_faces=int(f.shape[0]),
            attributes=scene, frame_scale=frame_scale, box_center=box_center, box_half=box_half,
            box_members=box_members)

    def trace(self, prepared: PreparedGaussians, mode: TraceMode, o, d, tmin, tmax, stats: TraceStats) -> Hits:
        # Candidates are searched only inside the bounds; exact tests use the full ray.
        t_lo, t_hi = gm.clip_to_box(o, d, tmin, tmax, prepared.lo, prepared.hi)
        if isinstance(mode, SoftMode):
            depth, g, acc = trace_soft(prepared, mode, self.max_iterations, o, d, tmin, tmax, t_lo, t_hi, stats)
            hit = acc >= mode.hit_alpha
            return gaussian_hits(prepared.attributes, "soft", o, d, np.where(hit, depth, np.inf),
                                 np.where(hit, g, -1), alpha=acc.astype(np.float32))
        best_t, best_g = trace_hard(prepared, mode, self, o, d, tmin, tmax, t_lo, t_hi, stats)
        return gaussian_hits(prepared.attributes, mode.name, o, d, best_t, best_g)


def gaussian_hits(scene: SceneGaussians, mode: str, o, d, best_t, best_g, alpha=None) -> Hits:
    """Per-ray (t, Gaussian) answers -> `Hits`: points, normals facing the ray (the ellipsoid's
    in `entry` mode, the flat axis otherwise), the Gaussian's voxel, label and colour."""
    n = o.shape[0]
    out = Hits.empty(n)
    idx = np.nonzero(best_g >= 0)[0]
    g = best_g[idx]
    t = best_t[idx]
    out.hit[idx] = True
    out.t[idx] = t
    p = o[idx] + t[:, None] * d[idx]
    out.points[idx] = p
    nrm = gm.ellipsoid_normals(p, scene.mu[g], scene.a[g]) if mode == "entry" else scene.flat_axis[g]
    facing = np.einsum("ij,ij->i", nrm, d[idx]) > 0
    out.normals[idx] = np.where(facing[:, None], -nrm, nrm)
    out.gaussian[idx] = g
    out.voxel[idx] = scene.voxel[g]
    out.label[idx] = scene.labels[g]
    out.color[idx] = scene.colors[g]
    out.alpha[idx] = 1.0 if alpha is None else alpha[idx]
    return out


# --- pieces shared by the walks ------------------------------------------------------------

def next_step(active, prim, face_pts, last_prim, step):
    """How far past the face just found the next cast starts, per active ray.

    As little as float32 allows at the cast's origin (STEP_ULPS ulps), so that faces closer than
    the step to the one found are rarely skipped; if a ray finds the same face again (its new
    origin rounded back onto it), its step grows fourfold until it gets past. Returns the steps
    and which rays found their previous face again (not to be processed twice)."""
    base = STEP_ULPS * np.finfo(np.float32).eps * np.maximum(np.abs(face_pts).max(axis=1), 1e-3)
    again = prim == last_prim[active]
    st = np.where(again, np.maximum(step[active] * 4.0, base), base)
    step[active] = st
    last_prim[active] = prim
    return st, again


def to_template(scene: PreparedGaussians, owner, x, is_dir):
    """Points (or directions) (n, 3) into the template coordinates of proxies `owner`."""
    if scene.proxy == "voxel_box":
        return (x if is_dir else x - scene.box_center[owner]) / scene.box_half[owner]
    v = x if is_dir else x - scene.mu[owner]
    y = scene.frame_scale[owner] * gm._matvec(scene.a[owner], v)
    q = gm.template_rotations(owner, np.argmin(scene.gaussians.scales[owner], axis=1))
    return np.einsum("nji,nj->ni", q, y)  # Q^T y


def candidates(scene: PreparedGaussians, soft: bool, prim, rays, d, start):
    """Proxy faces -> (ray index, Gaussian index) pairs to test exactly.

    In soft mode a ray visits each (convex) proxy once: when it crosses one of its entering
    faces, or, for a proxy it starts inside, when it leaves through an exiting face. Exit
    faces of proxies already entered are skipped, so no Gaussian is composited twice."""
    owner = prim // scene.faces_per_proxy
    if not soft:
        # Hard modes keep the nearest exact hit, so a repeated pair costs one exact test and
        # changes nothing; the visit test would cost about as much as it saves.
        return expand(scene, rays, owner)
    face = prim % scene.faces_per_proxy
    yd = to_template(scene, owner, d[rays], True)
    entering = np.einsum("ij,ij->i", yd, scene.planes_n[face]) < 0
    leave = np.nonzero(~entering)[0]
    if leave.size:
        ys = to_template(scene, owner[leave], start[rays[leave]], False)
        inside = np.all(ys @ scene.planes_n.T <= scene.planes_h, axis=1)
        entering[leave[inside]] = True
    return expand(scene, rays[entering], owner[entering])


def expand(scene: PreparedGaussians, rays, owner):
    """Proxy owners -> Gaussians (a voxel box stands for all of its voxel's Gaussians)."""
    if scene.proxy != "voxel_box":
        return rays, owner
    members = scene.box_members[owner]  # (n, M)
    r = np.repeat(rays, members.shape[1])
    g = members.reshape(-1)
    keep = g >= 0
    return r[keep], g[keep]


def exact(scene: PreparedGaussians, ray_idx, g, o, d, stats: TraceStats):
    """Exact ray-ellipsoid tests of (ray, Gaussian) pairs: (t*, d2, half chord), see gaussian_math."""
    t_star, d2, half = gm.ray_ellipsoid(o[ray_idx], d[ray_idx], scene.mu[g], scene.a[g], scene.k)
    stats.exact_tests += ray_idx.shape[0]
    return t_star, d2, half


class FaceWalk:
    """Each ray's walk through the proxy faces in order of distance, one Embree cast per step.

    A cast starts at `t_cur` (float64, converted to float32 only for Embree) and finds the next
    face; the next cast starts just past it (see `next_step`)."""

    def __init__(self, scene: PreparedGaussians, stats: TraceStats, o, d, t_lo, t_hi):
        self.backend, self.stats, self.o, self.d = scene.backend, stats, o, d
        self.d32 = d.astype(np.float32)
        n = o.shape[0]
        self.t_cur = t_lo.copy()
        self.start_pt = o + np.where(np.isfinite(t_lo), t_lo, 0.0)[:, None] * d
        self.step = np.zeros(n)
        self.last_prim = np.full(n, -1, np.int64)
        self.active = np.nonzero(t_hi >= t_lo)[0]
        self.iterations = 0

    def cast(self, far: np.ndarray):
        """Next face of every active ray before `far` (absolute, (N,)): returns the rays that
        found one, their face ids, and which of them found the same face as last time."""
        a = self.active
        self.iterations += 1
        start = (self.o[a] + self.t_cur[a, None] * self.d[a]).astype(np.float32)
        tf, prim = self.backend.first_hit(start, self.d32[a], (far[a] - self.t_cur[a]).astype(np.float32))
        self.stats.casts += 1
        self.stats.rays_cast += a.size
        found = prim >= 0
        a, tf, prim = a[found], tf[found], prim[found]
        step, again = next_step(a, prim, start[found] + tf[:, None] * self.d32[a], self.last_prim, self.step)
        self.t_cur[a] += tf.astype(np.float64) + step
        self.active = a
        return a, prim, again


# --- hard opacity --------------------------------------------------------------------------

def trace_hard(scene: PreparedGaussians, mode: HardMode, walk_limits: ReferenceCore, o, d, tmin, tmax, t_lo, t_hi,
               stats: TraceStats):
    """Nearest exact hit per ray: (t (N,) float64, inf on a miss; gaussian (N,) int64, -1).
    walk_limits: the core whose `max_iterations` and `exact_order` end each ray's walk."""
    n = o.shape[0]
    best_t = np.full(n, np.inf)
    best_g = np.full(n, -1, np.int64)
    walk = FaceWalk(scene, stats, o, d, t_lo, t_hi)
    entry_mode = mode.name == "entry"
    max_iterations, exact_order = walk_limits.max_iterations, walk_limits.exact_order
    kk = scene.k * scene.k
    while walk.active.size and walk.iterations < max_iterations and len(scene.gaussians):
        active, prim, _ = walk.cast(np.minimum(best_t, t_hi))
        if not active.size:
            break
        ray_idx, g = candidates(scene, False, prim, active, d, walk.start_pt)
        t_star, d2, half = exact(scene, ray_idx, g, o, d, stats)
        inside = d2 <= kk
        if entry_mode:
            t_in, t_out = t_star - half, t_star + half
            ok = inside & (t_out >= tmin[ray_idx]) & (t_in <= tmax[ray_idx])
            t_hit = np.maximum(t_in, tmin[ray_idx])  # a ray starting inside hits at once
        else:
            t_hit = t_star
            ok = inside & (t_star >= tmin[ray_idx]) & (t_star <= tmax[ray_idx])
        ri, gi, th = ray_idx[ok], g[ok], t_hit[ok]
        if scene.proxy == "voxel_box":
            # Several candidates per ray this round: keep each ray's nearest.
            order = np.lexsort((th, ri))
            ri, gi, th = ri[order], gi[order], th[order]
            first = np.r_[True, ri[1:] != ri[:-1]] if ri.size else np.zeros(0, bool)
            ri, gi, th = ri[first], gi[first], th[first]
        better = th < best_t[ri]
        best_t[ri[better]] = th[better]
        best_g[ri[better]] = gi[better]
        go_on = walk.t_cur[active] < np.minimum(best_t[active], t_hi[active])
        if not exact_order:
            go_on &= best_g[active] < 0  # stop at the first exact hit found (see Tracer's doc)
        walk.active = active[go_on]
    stats.unfinished += int(walk.active.size) if walk.iterations >= max_iterations else 0
    return best_t, best_g


# --- soft opacity --------------------------------------------------------------------------

def _soft_contributions(scene: PreparedGaussians, mode: SoftMode, ray_idx, g, o, d, tmin, tmax, stats):
    """(ray, gaussian) pairs -> the ones that contribute: (ray, gaussian, t*, alpha)."""
    t_star, d2, _ = exact(scene, ray_idx, g, o, d, stats)
    alpha = scene.opacity[g] * np.exp(-0.5 * d2)
    ok = ((d2 <= scene.k * scene.k) & (t_star >= tmin[ray_idx]) & (t_star <= tmax[ray_idx])
          & (alpha >= mode.alpha_min))
    return ray_idx[ok], g[ok], t_star[ok], np.minimum(alpha[ok], 0.999)


def _soft_result(mode: SoftMode, n, parts):
    cr, cg, ct, ca = (np.concatenate([x[i] for x in parts]) for i in range(4))
    if not cr.size:
        return np.full(n, np.inf), np.full(n, -1, np.int64), np.zeros(n)
    return composite_front_to_back(cr, ct, ca, cg, n, mode.min_transmittance)


def trace_soft(scene: PreparedGaussians, mode: SoftMode, max_iterations: int, o, d, tmin, tmax, t_lo, t_hi,
               stats: TraceStats):
    """Front-to-back compositing per ray: (depth (N,) float64, inf where nothing; gaussian of
    the largest weight (N,) int64, -1; accumulated alpha (N,) float64). max_iterations: Embree
    casts per ray at most."""
    if scene.backend.lists_all_hits:
        return _trace_soft_listed(scene, mode, o, d, tmin, tmax, t_lo, t_hi, stats)
    n = o.shape[0]
    walk = FaceWalk(scene, stats, o, d, t_lo, t_hi)
    log_t_min = np.log(mode.min_transmittance)
    log_tr = np.zeros(n)  # log transmittance of the contributions known to be final
    done = []  # finalised contributions (ray, gaussian, t*, alpha) per round
    pend = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
    while walk.active.size and walk.iterations < max_iterations and len(scene.gaussians):
        active, prim, again = walk.cast(t_hi)
        if not active.size:
            break
        ray_idx, g = candidates(scene, True, prim[~again], active[~again], d, walk.start_pt)
        pend = tuple(np.concatenate([a, b]) for a, b in
                     zip(pend, _soft_contributions(scene, mode, ray_idx, g, o, d, tmin, tmax, stats)))
        # Any Gaussian not found yet has its proxy entry, hence its t*, beyond this ray's last
        # face: contributions in front of it are final, and once their transmittance is below
        # the threshold the ray is done.
        final = pend[2] < walk.t_cur[pend[0]] - walk.step[pend[0]]
        if np.any(final):
            done.append(tuple(a[final] for a in pend))
            np.add.at(log_tr, pend[0][final], np.log1p(-pend[3][final]))
            pend = tuple(a[~final] for a in pend)
        walk.active = active[(log_tr[active] > log_t_min) & (walk.t_cur[active] < t_hi[active])]
    stats.unfinished += int(walk.active.size) if walk.iterations >= max_iterations else 0
    done.append(pend)
    return _soft_result(mode, n, done)


def _trace_soft_listed(scene: PreparedGaussians, mode: SoftMode, o, d, tmin, tmax, t_lo, t_hi, stats):
    """Soft mode with a backend that lists all crossings in one traversal (open3d): every proxy
    along the ray at once, then the exact compositing."""
    n = o.shape[0]
    active = np.nonzero(t_hi >= t_lo)[0]
    t0 = np.where(np.isfinite(t_lo), t_lo, 0.0)
    start_pt = o + t0[:, None] * d
    parts = [(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))]
    num = len(scene.gaussians)
    if active.size and num:
        stats.casts += 1
        stats.rays_cast += active.size
        for r, _, prim in scene.backend.all_hits(start_pt[active].astype(np.float32),
                                                 d[active].astype(np.float32), (t_hi - t0)[active]):
            ray_idx, g = candidates(scene, True, prim, active[r], d, start_pt)
            # A ray through a shared edge or vertex crosses several faces of one proxy at once.
            key = np.unique(ray_idx * num + g)
            ray_idx, g = key // num, key % num
            parts.append(_soft_contributions(scene, mode, ray_idx, g, o, d, tmin, tmax, stats))
    return _soft_result(mode, n, parts)


def composite_front_to_back(ray, t, alpha, gid, n, min_transmittance):
    """Alpha-composite per-ray samples in order of t until transmittance < min_transmittance.

    ray, t, alpha, gid: (K,) samples. Returns (depth (n,) float64: sum(w t) / sum(w) with
    w = T alpha, inf where nothing; gaussian (n,) int64 of the largest weight, -1 where nothing;
    accumulated alpha (n,) = 1 - T_final)."""
    order = np.lexsort((t, ray))
    ray, t, alpha, gid = ray[order], t[order], alpha[order], gid[order]
    log1m = np.log1p(-alpha)
    # Exclusive cumulative sum of log(1 - alpha) within each ray: log T before each sample.
    csum = np.cumsum(log1m)
    starts = np.r_[0, np.nonzero(ray[1:] != ray[:-1])[0] + 1] if ray.size else np.zeros(0, np.int64)
    seg_start = np.repeat(starts, np.diff(np.r_[starts, ray.size]))
    base = np.where(seg_start > 0, csum[seg_start - 1], 0.0) if ray.size else csum
    log_t_before = csum - log1m - base
    live = log_t_before >= np.log(min_transmittance)
    w = np.where(live, np.exp(log_t_before) * alpha, 0.0)
    wsum = np.bincount(ray, weights=w, minlength=n)
    wt = np.bincount(ray, weights=w * t, minlength=n)
    depth = np.where(wsum > 0, wt / np.where(wsum > 0, wsum, 1.0), np.inf)
    acc = wsum  # sum of T_i alpha_i = 1 - T_final over the live samples
    best = np.full(n, -1, np.int64)
    if ray.size:
        o2 = np.lexsort((-w, ray))
        firsts = np.r_[True, ray[o2][1:] != ray[o2][:-1]]
        sel = o2[firsts]
        best[ray[sel]] = np.where(w[sel] > 0, gid[sel], -1)
    return depth, best, acc
