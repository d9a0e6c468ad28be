"""The reference traversal of hard- and soft-opacity Gaussians: a NumPy face walk over Embree
triangle proxies with exact float64 tests (`TraceCore`; a compiled core implements the same
`trace_hard` / `trace_soft` and is tested against this one).

A ray finds proxy faces in order of distance, one Embree first-hit cast per step; each face
names a Gaussian (or a voxel's Gaussians), which is tested exactly (gaussian_math). The ray is
re-cast from just past each face until the next face lies beyond the best exact hit: the result
is the exact nearest hit, whatever the overlap of the proxies. Soft mode composites every
contribution front to back until the transmittance falls below its threshold.

Frames: everything here is in the scene's local frame (world = local + origin), float64, with
unit directions; only the Embree casts are float32.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..voxsplat import Gaussians
from . import gaussian_math as gm
from .contracts import TracerBackend
from .hits import TraceStats

STEP_ULPS = 1.0  # first re-cast step past a face, in float32 ulps of the face position (grows on a re-hit)


@dataclass
class PreparedGaussians:
    """What a traversal needs of a scene, built once by `Tracer` (all local frame, float64).

    gaussians: the kept Gaussians (|scales| floored); mu (G, 3) means; a (G, 3, 3) world-to-unit
    frame matrices; opacity (G,); backend: the Embree BVH of the proxies, whose primitive p
    belongs to proxy p // faces_per_proxy. Per-Gaussian proxies: frame_scale (G,) and the
    template's planes (planes_n (F, 3), planes_h (F,)). Voxel boxes: box_center, box_half (B, 3)
    and box_members (B, M) Gaussian ids (-1 padded)."""

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
    frame_scale: np.ndarray | None = None
    box_center: np.ndarray | None = None
    box_half: np.ndarray | None = None
    box_members: np.ndarray | None = None


@dataclass(frozen=True)
class TraceOptions:
    """How one trace call walks (read from the `Tracer` at each call, so its settings may change
    between calls): mode 'entry' | 'max_response' | 'soft'; exact_order False stops a hard ray
    at its first exact hit; max_iterations caps the casts per ray; soft_min_transmittance ends a
    soft ray; soft_alpha_min drops fainter soft contributions."""

    mode: str = "entry"
    exact_order: bool = True
    max_iterations: int = 1000
    soft_min_transmittance: float = 1e-3
    soft_alpha_min: float = 1.0 / 255.0


class ReferenceCore:
    """The NumPy face walk as a `TraceCore`."""

    name = "reference"

    @staticmethod
    def trace_hard(scene: PreparedGaussians, opts: TraceOptions, o, d, tmin, tmax, t_lo, t_hi, stats: TraceStats):
        return trace_hard(scene, opts, o, d, tmin, tmax, t_lo, t_hi, stats)

    @staticmethod
    def trace_soft(scene: PreparedGaussians, opts: TraceOptions, o, d, tmin, tmax, t_lo, t_hi, stats: TraceStats):
        return trace_soft(scene, opts, o, d, tmin, tmax, t_lo, t_hi, stats)


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

def trace_hard(scene: PreparedGaussians, opts: TraceOptions, o, d, tmin, tmax, t_lo, t_hi, stats: TraceStats):
    """Nearest exact hit per ray: (t (N,) float64, inf on a miss; gaussian (N,) int64, -1)."""
    n = o.shape[0]
    best_t = np.full(n, np.inf)
    best_g = np.full(n, -1, np.int64)
    walk = FaceWalk(scene, stats, o, d, t_lo, t_hi)
    entry_mode = opts.mode == "entry"
    kk = scene.k * scene.k
    while walk.active.size and walk.iterations < opts.max_iterations and len(scene.gaussians):
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
        if not opts.exact_order:
            go_on &= best_g[active] < 0  # stop at the first exact hit found (see Tracer's doc)
        walk.active = active[go_on]
    stats.unfinished += int(walk.active.size) if walk.iterations >= opts.max_iterations else 0
    return best_t, best_g


# --- soft opacity --------------------------------------------------------------------------

def _soft_contributions(scene: PreparedGaussians, opts: TraceOptions, ray_idx, g, o, d, tmin, tmax, stats):
    """(ray, gaussian) pairs -> the ones that contribute: (ray, gaussian, t*, alpha)."""
    t_star, d2, _ = exact(scene, ray_idx, g, o, d, stats)
    alpha = scene.opacity[g] * np.exp(-0.5 * d2)
    ok = ((d2 <= scene.k * scene.k) & (t_star >= tmin[ray_idx]) & (t_star <= tmax[ray_idx])
          & (alpha >= opts.soft_alpha_min))
    return ray_idx[ok], g[ok], t_star[ok], np.minimum(alpha[ok], 0.999)


def _soft_result(opts: TraceOptions, n, parts):
    cr, cg, ct, ca = (np.concatenate([x[i] for x in parts]) for i in range(4))
    if not cr.size:
        return np.full(n, np.inf), np.full(n, -1, np.int64), np.zeros(n)
    return composite_front_to_back(cr, ct, ca, cg, n, opts.soft_min_transmittance)


def trace_soft(scene: PreparedGaussians, opts: TraceOptions, o, d, tmin, tmax, t_lo, t_hi, stats: TraceStats):
    """Front-to-back compositing per ray: (depth (N,) float64, inf where nothing; gaussian of
    the largest weight (N,) int64, -1; accumulated alpha (N,) float64)."""
    if scene.backend.lists_all_hits:
        return _trace_soft_listed(scene, opts, o, d, tmin, tmax, t_lo, t_hi, stats)
    n = o.shape[0]
    walk = FaceWalk(scene, stats, o, d, t_lo, t_hi)
    log_t_min = np.log(opts.soft_min_transmittance)
    log_tr = np.zeros(n)  # log transmittance of the contributions known to be final
    done = []  # finalised contributions (ray, gaussian, t*, alpha) per round
    pend = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
    while walk.active.size and walk.iterations < opts.max_iterations and len(scene.gaussians):
        active, prim, again = walk.cast(t_hi)
        if not active.size:
            break
        ray_idx, g = candidates(scene, True, prim[~again], active[~again], d, walk.start_pt)
        pend = tuple(np.concatenate([a, b]) for a, b in
                     zip(pend, _soft_contributions(scene, opts, ray_idx, g, o, d, tmin, tmax, stats)))
        # Any Gaussian not found yet has its proxy entry, hence its t*, beyond this ray's last
        # face: contributions in front of it are final, and once their transmittance is below
        # the threshold the ray is done.
        final = pend[2] < walk.t_cur[pend[0]] - walk.step[pend[0]]
        if np.any(final):
            done.append(tuple(a[final] for a in pend))
            np.add.at(log_tr, pend[0][final], np.log1p(-pend[3][final]))
            pend = tuple(a[~final] for a in pend)
        walk.active = active[(log_tr[active] > log_t_min) & (walk.t_cur[active] < t_hi[active])]
    stats.unfinished += int(walk.active.size) if walk.iterations >= opts.max_iterations else 0
    done.append(pend)
    return _soft_result(opts, n, done)


def _trace_soft_listed(scene: PreparedGaussians, opts: TraceOptions, o, d, tmin, tmax, t_lo, t_hi, stats):
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
            parts.append(_soft_contributions(scene, opts, ray_idx, g, o, d, tmin, tmax, stats))
    return _soft_result(opts, n, parts)


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
