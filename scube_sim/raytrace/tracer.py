"""`Tracer`: ray tracing of VoxSplats (hard or soft opacity) and triangle meshes with Embree.

Gaussians become closed bounding proxies (per-Gaussian octahedra or icosahedra, or one box per
voxel) in an Embree BVH, built once. A ray finds proxy faces in order of distance; each face names
a Gaussian (or a voxel's Gaussians), which is tested exactly in float64 (gaussian_math). The ray is
re-cast from just past each face until the next face lies beyond the best exact hit: the result is
the exact nearest hit, whatever the overlap of the proxies. Proxies only change the speed.

Depth definitions (hard opacity: alpha := 1 for Gaussians at or above `opacity_floor`):
- ``entry``: where the ray enters the k-sigma ellipsoid (a solid surface).
- ``max_response``: the point of maximum Gaussian response along the ray (3DGRT), the chord
  midpoint of the same ellipsoid.
- ``soft``: front-to-back compositing of every Gaussian the ray meets, each with its own
  opacity times its peak response along the ray (``alpha_i = o_i exp(-d2_i / 2)``), ordered by
  their max-response points, until the transmittance falls below `soft_min_transmittance`.
  The range is the composited (alpha-weighted, normalised) depth; the ray returns if the
  accumulated alpha reaches `soft_hit_alpha`. For splat files trained without a scaffold.

Frames: rays and hit points are in the scene's local frame (world = local + `origin`); use
`trace_world` to pass float64 world coordinates. Ranges are metres for unit directions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..mesh import TriangleMesh
from ..voxsplat import Gaussians, VoxSplat
from . import gaussian_math as gm
from .backends import BACKENDS, make_backend

MODES = ("entry", "max_response", "soft")
# Measured by `make bench` (bench/bench_tracer.py): open3d's multi-threaded Embree sweeps faster on
# this 2-core machine for every scene size and proxy; see README "Tracer benchmark".
DEFAULT_BACKEND = "open3d"
MIN_SCALE = 1e-9  # metres
STEP_ULPS = 1.0  # first re-cast step past a face, in float32 ulps of the face position (grows on a re-hit)


@dataclass
class Hits:
    """Per-ray results, all (N, ...) arrays.

    hit bool; t float64 range along the ray (inf on a miss); points float64 local frame;
    normals float32 unit, facing the ray; gaussian int64 (-1: none or a mesh); voxel int64
    (-1: none); face int64 (mesh triangle, -1 otherwise); label int16; instance int32;
    color float32 (N, 3) in [0, 1]; alpha float32 accumulated opacity (1 for hard hits).
    """

    hit: np.ndarray
    t: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    gaussian: np.ndarray
    voxel: np.ndarray
    face: np.ndarray
    label: np.ndarray
    instance: np.ndarray
    color: np.ndarray
    alpha: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "Hits":
        return cls(
            hit=np.zeros(n, bool), t=np.full(n, np.inf), points=np.full((n, 3), np.nan),
            normals=np.zeros((n, 3), np.float32), gaussian=np.full(n, -1, np.int64),
            voxel=np.full(n, -1, np.int64), face=np.full(n, -1, np.int64),
            label=np.zeros(n, np.int16), instance=np.zeros(n, np.int32),
            color=np.zeros((n, 3), np.float32), alpha=np.zeros(n, np.float32),
        )


@dataclass
class TraceStats:
    casts: int = 0  # Embree calls
    rays_cast: int = 0  # rays over all calls
    exact_tests: int = 0  # (ray, Gaussian) pairs tested
    unfinished: int = 0  # rays stopped by max_iterations (best hit so far kept)


class Tracer:
    """Build once per static scene, then `trace` any number of ray batches.

    scene: a VoxSplat, a `Gaussians` set (e.g. from a 3DGS PLY) or a TriangleMesh.
    backend: 'open3d' or 'embreex'. mode: 'entry' | 'max_response' | 'soft' (ignored for meshes).
    k: ellipsoid size in standard deviations. opacity_floor: hard modes drop Gaussians below it.
    proxy: 'octahedron' | 'icosahedron' (per Gaussian) or 'voxel_box' (one box per voxel).
    exact_order: True (default) returns the nearest exact hit; False stops each ray at the
    first exact hit found in proxy order, skipping the confirming re-casts (faster; its range error
    on overlapping Gaussians is measured by `make bench`).
    labels: (N,) per-Gaussian labels for a bare `Gaussians` scene.
    """

    def __init__(
        self,
        scene: VoxSplat | Gaussians | TriangleMesh,
        *,
        backend: str = DEFAULT_BACKEND,
        mode: str = "entry",
        k: float = 3.0,
        opacity_floor: float = 0.05,
        proxy: str = "octahedron",
        soft_min_transmittance: float = 1e-3,
        soft_alpha_min: float = 1.0 / 255.0,
        soft_hit_alpha: float = 0.5,
        max_iterations: int = 1000,
        exact_order: bool = True,
        labels: np.ndarray | None = None,
    ):
        if backend not in BACKENDS:
            raise ValueError(f"backend: expected one of {BACKENDS}, got {backend!r}")
        if mode not in MODES:
            raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
        if not (np.isfinite(k) and k > 0):
            raise ValueError(f"k: expected a positive number of standard deviations, got {k}")
        if proxy not in gm.PROXY_KINDS:
            raise ValueError(f"proxy: expected one of {gm.PROXY_KINDS}, got {proxy!r}")
        if proxy == "voxel_box" and not isinstance(scene, VoxSplat):
            raise ValueError("proxy 'voxel_box' needs a VoxSplat scene (Gaussians on a voxel grid)")
        self.backend_name, self.mode, self.k, self.proxy = backend, mode, float(k), proxy
        self.opacity_floor = float(opacity_floor)
        self.soft_min_transmittance = float(soft_min_transmittance)
        self.soft_alpha_min = float(soft_alpha_min)
        self.soft_hit_alpha = float(soft_hit_alpha)
        self.max_iterations = int(max_iterations)
        self.exact_order = bool(exact_order)
        self.stats = TraceStats()
        self.is_mesh = isinstance(scene, TriangleMesh)
        if self.is_mesh:
            self._build_mesh(scene)
        else:
            self._build_gaussians(scene, labels)

    # --- build -------------------------------------------------------------------------------
    def _build_mesh(self, mesh: TriangleMesh) -> None:
        self.origin = mesh.origin.copy()
        self.mesh = mesh
        self._face_normals = mesh.face_normals()
        self._face_offset = np.einsum("ij,ij->i", self._face_normals, mesh.vertices[mesh.faces[:, 0]])
        v = mesh.vertices
        self._set_tolerances(np.abs(v).max() if v.size else 0.0)
        self._set_bounds(v.min(0) if v.size else np.zeros(3), v.max(0) if v.size else np.zeros(3))
        self.num_primitives = mesh.num_faces
        self._backend = make_backend(self.backend_name, mesh.vertices.astype(np.float32), mesh.faces)

    def _build_gaussians(self, scene, labels) -> None:
        if isinstance(scene, VoxSplat):
            scene.check_finite()
            g = scene.gaussians()
            vox_labels = scene.labels
            g_labels = vox_labels[g.voxel] if len(g) else np.zeros(0, np.int16)
            self.num_voxels = scene.num_voxels
        else:
            g = scene
            g.check_finite()
            g_labels = (np.zeros(len(g), np.int16) if labels is None
                        else np.asarray(labels, np.int16).reshape(len(g)))
            self.num_voxels = 0
        self.origin = g.origin.copy()
        floor = self.soft_alpha_min if self.mode == "soft" else self.opacity_floor
        keep = g.opacities >= floor
        g = g.subset(keep)
        # A zero scale is a flat (2D) Gaussian and a negative one means the same spread: keep the
        # result defined by using |s|, floored where float64 still inverts it.
        g.scales = np.maximum(np.abs(g.scales), MIN_SCALE)
        self.gaussians = g
        self.labels = g_labels[keep]
        self.colors = g.colors
        rot = g.rotations()
        self._mu = g.means
        self._a = gm.unit_frame_matrices(rot, g.scales)
        self._opacity = g.opacities
        # Surfel normal for max-response hits: the axis of least spread.
        self._flat_axis = rot[np.arange(len(g)), :, np.argmin(g.scales, axis=1)] if len(g) else np.zeros((0, 3))
        self._voxel = g.voxel if g.voxel is not None else np.full(len(g), -1, np.int64)
        lo, hi = gm.gaussian_aabbs(self._mu, rot, g.scales, self.k) if len(g) else (np.zeros((0, 3)),) * 2
        # The float32 tolerance follows the scene's extent; proxies are padded by it, and the
        # search bounds are those of the padded proxies themselves (which reach beyond the
        # ellipsoids), so a clipped ray never starts inside a proxy it cannot then leave.
        self._set_tolerances(np.abs(np.concatenate([lo, hi])).max() if len(g) else 0.0)
        pad = self._pad
        if self.proxy == "voxel_box":
            # One box per voxel: the union of its Gaussians' k-sigma bounding boxes.
            vox, inv = np.unique(self._voxel, return_inverse=True)
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
            self._box_members = np.full((vox.shape[0], m), -1, np.int64)
            self._box_members[inv[order], slot] = order
            # Boxes of neighbouring voxels share face planes (a flat ground gives every box the
            # same top), and Embree reports one of several faces met at the same distance. So
            # overlapping boxes get different dilations: a class per voxel index modulo c, where
            # c = 2 * reach + 1 and reach is how many cells a box reaches beyond its own.
            ijk = scene.ijk[vox].astype(np.int64)
            cell_lo = ijk * scene.voxel_size
            reach = max(np.max((cell_lo - blo) / scene.voxel_size), np.max((bhi - cell_lo) / scene.voxel_size - 1), 0.0)
            c = 2 * int(np.ceil(reach)) + 1
            cls = (ijk[:, 0] % c) * c * c + (ijk[:, 1] % c) * c + (ijk[:, 2] % c)
            dil = pad * (1.0 + 2.0 * cls)
            v, f, fpp = gm.box_proxies(blo, bhi, dil)
            self._box_center = 0.5 * (blo + bhi)
            self._box_half = 0.5 * (bhi - blo) + dil[:, None]
        else:
            v, f, fpp, self._frame_scale = gm.gaussian_proxies(self.proxy, self._mu, rot, g.scales, self.k, pad)
        self._planes_n, self._planes_h = gm.template_planes(self.proxy)
        self._set_bounds(v.min(0).astype(np.float64) if len(v) else np.zeros(3),
                         v.max(0).astype(np.float64) if len(v) else np.zeros(3))
        self._faces_per_proxy = fpp
        self.num_primitives = int(f.shape[0])
        self._backend = make_backend(self.backend_name, v, f)

    def _set_tolerances(self, extent: float) -> None:
        """float32 tolerances for a scene reaching `extent` metres from the local origin.

        Rays are clipped to the scene bounds in float64 before they are handed to Embree in
        float32, so a float32 ray is never further from the scene than its extent: its rounding
        (origin and direction, ~1.2e-7 relative) stays below a few ulps of the extent wherever it
        meets a proxy. Proxies grow by `_pad` to absorb that."""
        self.extent = float(extent)
        eps32 = float(np.finfo(np.float32).eps)
        self._pad = 8.0 * eps32 * self.extent + 1e-12

    def _set_bounds(self, lo: np.ndarray, hi: np.ndarray) -> None:
        self._lo = np.asarray(lo, np.float64) - 2.0 * self._pad
        self._hi = np.asarray(hi, np.float64) + 2.0 * self._pad

    def _clip_to_bounds(self, o, d, tmin, tmax):
        """Shrink [tmin, tmax] to the part of each ray inside the scene bounds (empty: tmin > tmax)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            t1 = (self._lo - o) * inv
            t2 = (self._hi - o) * inv
        # A direction component of 0 gives inf/-inf or NaN (0 * inf): NaN means "inside the slab".
        near = np.nanmax(np.minimum(t1, t2), axis=1)
        far = np.nanmin(np.maximum(t1, t2), axis=1)
        return np.maximum(tmin, near), np.minimum(tmax, far)

    # --- queries -----------------------------------------------------------------------------
    def trace_world(self, origins, dirs, t_min=0.0, t_max=np.inf) -> Hits:
        """Like `trace` with float64 world-frame origins; hit points stay in the local frame."""
        return self.trace(np.asarray(origins, np.float64) - self.origin, dirs, t_min, t_max)

    def trace(self, origins, dirs, t_min=0.0, t_max=np.inf) -> Hits:
        """origins (N, 3) local frame, dirs (N, 3) (normalised here), t_min / t_max scalars or (N,).
        Returns the nearest hit with t in [t_min, t_max] per ray."""
        o = np.asarray(origins, np.float64).reshape(-1, 3)
        d = np.asarray(dirs, np.float64).reshape(-1, 3)
        n = o.shape[0]
        if d.shape[0] != n:
            raise ValueError(f"origins ({n}) and dirs ({d.shape[0]}) differ in length")
        if not (np.all(np.isfinite(o)) and np.all(np.isfinite(d))):
            raise ValueError("trace: ray origins or directions contain NaN or Inf")
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        if np.any(norm == 0):
            raise ValueError("trace: a ray direction has zero length")
        d = d / norm
        tmin = np.broadcast_to(np.asarray(t_min, np.float64), (n,)).copy()
        tmax = np.broadcast_to(np.asarray(t_max, np.float64), (n,)).copy()
        if np.any(np.isnan(tmin)) or np.any(np.isnan(tmax)):
            raise ValueError("trace: t_min / t_max contain NaN")
        if self.is_mesh:
            return self._trace_mesh(o, d, tmin, tmax)
        # Candidates are searched only inside the scene bounds; exact tests use the full ray.
        t_lo, t_hi = self._clip_to_bounds(o, d, tmin, tmax)
        if self.mode == "soft":
            return self._trace_soft(o, d, tmin, tmax, t_lo, t_hi)
        return self._trace_hard(o, d, tmin, tmax, t_lo, t_hi)

    # --- meshes ------------------------------------------------------------------------------
    def _trace_mesh(self, o, d, tmin, tmax) -> Hits:
        n = o.shape[0]
        out = Hits.empty(n)
        start = o + tmin[:, None] * d
        t32, prim = self._backend.first_hit(start.astype(np.float32), d.astype(np.float32),
                                            (tmax - tmin).astype(np.float32))
        self.stats.casts += 1
        self.stats.rays_cast += n
        idx = np.nonzero(prim >= 0)[0]
        f = prim[idx]
        # Refine the float32 hit in float64 on the triangle's plane.
        nrm = self._face_normals[f]
        di, oi = d[idx], o[idx]
        denom = nrm[:, 0] * di[:, 0] + nrm[:, 1] * di[:, 1] + nrm[:, 2] * di[:, 2]
        num = self._face_offset[f] - (nrm[:, 0] * oi[:, 0] + nrm[:, 1] * oi[:, 1] + nrm[:, 2] * oi[:, 2])
        ok = np.abs(denom) > 1e-12
        t = np.where(ok, num / np.where(ok, denom, 1.0), tmin[idx] + t32[idx])
        valid = (t >= tmin[idx] - 1e-9) & (t <= tmax[idx])
        idx, f, t, nrm, denom = idx[valid], f[valid], np.maximum(t[valid], tmin[idx[valid]]), nrm[valid], denom[valid]
        out.hit[idx] = True
        out.t[idx] = t
        out.points[idx] = o[idx] + t[:, None] * d[idx]
        out.normals[idx] = np.where(denom[:, None] > 0, -nrm, nrm)
        out.face[idx] = f
        out.label[idx] = self.mesh.labels[f]
        out.instance[idx] = self.mesh.instances[f]
        out.color[idx] = self.mesh.colors[f] if self.mesh.colors is not None else 0.5
        out.alpha[idx] = 1.0
        return out

    # --- hard Gaussians ----------------------------------------------------------------------
    def _next_step(self, active, prim, face_pts, last_prim, step):
        """How far past the face just found the next cast starts, per active ray.

        As little as float32 allows at the cast's origin (4 ulps), so that faces closer than the
        step to the one found are rarely skipped; if a ray finds the same face again (its new
        origin rounded back onto it), its step grows fourfold until it gets past. Returns the
        steps and which rays found their previous face again (not to be processed twice)."""
        base = STEP_ULPS * np.finfo(np.float32).eps * np.maximum(np.abs(face_pts).max(axis=1), 1e-3)
        again = prim == last_prim[active]
        st = np.where(again, np.maximum(step[active] * 4.0, base), base)
        step[active] = st
        last_prim[active] = prim
        return st, again

    def _to_template(self, owner, x, is_dir):
        """Points (or directions) (n, 3) into the template coordinates of proxies `owner`."""
        if self.proxy == "voxel_box":
            return (x if is_dir else x - self._box_center[owner]) / self._box_half[owner]
        v = x if is_dir else x - self._mu[owner]
        y = self._frame_scale[owner] * gm._matvec(self._a[owner], v)
        q = gm.template_rotations(owner, np.argmin(self.gaussians.scales[owner], axis=1))
        return np.einsum("nji,nj->ni", q, y)  # Q^T y

    def _candidates(self, prim, rays, d, start):
        """Proxy faces -> (ray index, Gaussian index) pairs to test exactly.

        In soft mode a ray visits each (convex) proxy once: when it crosses one of its entering
        faces, or, for a proxy it starts inside, when it leaves through an exiting face. Exit
        faces of proxies already entered are skipped, so no Gaussian is composited twice."""
        owner = prim // self._faces_per_proxy
        if self.mode != "soft":
            # Hard modes keep the nearest exact hit, so a repeated pair costs one exact test and
            # changes nothing; the visit test would cost about as much as it saves.
            return self._expand(rays, owner)
        face = prim % self._faces_per_proxy
        yd = self._to_template(owner, d[rays], True)
        entering = np.einsum("ij,ij->i", yd, self._planes_n[face]) < 0
        leave = np.nonzero(~entering)[0]
        if leave.size:
            ys = self._to_template(owner[leave], start[rays[leave]], False)
            inside = np.all(ys @ self._planes_n.T <= self._planes_h, axis=1)
            entering[leave[inside]] = True
        return self._expand(rays[entering], owner[entering])

    def _expand(self, rays, owner):
        """Proxy owners -> Gaussians (a voxel box stands for all of its voxel's Gaussians)."""
        if self.proxy != "voxel_box":
            return rays, owner
        members = self._box_members[owner]  # (n, M)
        r = np.repeat(rays, members.shape[1])
        g = members.reshape(-1)
        keep = g >= 0
        return r[keep], g[keep]

    def _exact(self, ray_idx, g, o, d):
        t_star, d2, half = gm.ray_ellipsoid(o[ray_idx], d[ray_idx], self._mu[g], self._a[g], self.k)
        self.stats.exact_tests += ray_idx.shape[0]
        return t_star, d2, half

    def _trace_hard(self, o, d, tmin, tmax, t_lo, t_hi) -> Hits:
        n = o.shape[0]
        best_t = np.full(n, np.inf)
        best_g = np.full(n, -1, np.int64)
        walk = _FaceWalk(self, o, d, t_lo, t_hi)
        entry_mode = self.mode == "entry"
        while walk.active.size and walk.iterations < self.max_iterations and len(self.gaussians):
            active, prim, _ = walk.cast(np.minimum(best_t, t_hi))
            if not active.size:
                break
            ray_idx, g = self._candidates(prim, active, d, walk.start_pt)
            t_star, d2, half = self._exact(ray_idx, g, o, d)
            inside = d2 <= self.k * self.k
            if entry_mode:
                t_in, t_out = t_star - half, t_star + half
                ok = inside & (t_out >= tmin[ray_idx]) & (t_in <= tmax[ray_idx])
                t_hit = np.maximum(t_in, tmin[ray_idx])  # a ray starting inside hits at once
            else:
                t_hit = t_star
                ok = inside & (t_star >= tmin[ray_idx]) & (t_star <= tmax[ray_idx])
            ri, gi, th = ray_idx[ok], g[ok], t_hit[ok]
            if self.proxy == "voxel_box":
                # Several candidates per ray this round: keep each ray's nearest.
                order = np.lexsort((th, ri))
                ri, gi, th = ri[order], gi[order], th[order]
                first = np.r_[True, ri[1:] != ri[:-1]] if ri.size else np.zeros(0, bool)
                ri, gi, th = ri[first], gi[first], th[first]
            better = th < best_t[ri]
            best_t[ri[better]] = th[better]
            best_g[ri[better]] = gi[better]
            go_on = walk.t_cur[active] < np.minimum(best_t[active], t_hi[active])
            if not self.exact_order:
                go_on &= best_g[active] < 0  # stop at the first exact hit found (see class doc)
            walk.active = active[go_on]
        active = walk.active
        it = walk.iterations
        self.stats.unfinished += int(active.size) if it >= self.max_iterations else 0
        return self._gaussian_hits(o, d, best_t, best_g)

    def _gaussian_hits(self, o, d, best_t, best_g, alpha=None) -> Hits:
        n = o.shape[0]
        out = Hits.empty(n)
        idx = np.nonzero(best_g >= 0)[0]
        g = best_g[idx]
        t = best_t[idx]
        out.hit[idx] = True
        out.t[idx] = t
        p = o[idx] + t[:, None] * d[idx]
        out.points[idx] = p
        if self.mode == "entry":
            nrm = gm.ellipsoid_normals(p, self._mu[g], self._a[g])
        else:
            nrm = self._flat_axis[g]
        facing = np.einsum("ij,ij->i", nrm, d[idx]) > 0
        nrm = np.where(facing[:, None], -nrm, nrm)
        out.normals[idx] = nrm
        out.gaussian[idx] = g
        out.voxel[idx] = self._voxel[g]
        out.label[idx] = self.labels[g]
        out.color[idx] = self.colors[g]
        out.alpha[idx] = 1.0 if alpha is None else alpha[idx]
        return out

    # --- soft Gaussians ----------------------------------------------------------------------
    def _soft_contributions(self, ray_idx, g, o, d, tmin, tmax):
        """(ray, gaussian) pairs -> the ones that contribute: (ray, gaussian, t*, alpha)."""
        t_star, d2, _ = self._exact(ray_idx, g, o, d)
        alpha = self._opacity[g] * np.exp(-0.5 * d2)
        ok = ((d2 <= self.k * self.k) & (t_star >= tmin[ray_idx]) & (t_star <= tmax[ray_idx])
              & (alpha >= self.soft_alpha_min))
        return ray_idx[ok], g[ok], t_star[ok], np.minimum(alpha[ok], 0.999)

    def _soft_result(self, n, o, d, parts) -> Hits:
        cr, cg, ct, ca = (np.concatenate([x[i] for x in parts]) for i in range(4))
        if not cr.size:
            return Hits.empty(n)
        depth, acc, best = composite_front_to_back(cr, ct, ca, cg, n, self.soft_min_transmittance)
        hit = acc >= self.soft_hit_alpha
        best_t = np.where(hit, depth, np.inf)
        best_g = np.where(hit, best, -1)
        return self._gaussian_hits(o, d, best_t, best_g, alpha=acc.astype(np.float32))

    def _trace_soft_listed(self, o, d, tmin, tmax, t_lo, t_hi) -> Hits:
        """Soft mode with a backend that lists all crossings in one traversal (open3d): every
        proxy along the ray at once, then the exact compositing."""
        n = o.shape[0]
        active = np.nonzero(t_hi >= t_lo)[0]
        t0 = np.where(np.isfinite(t_lo), t_lo, 0.0)
        start_pt = o + t0[:, None] * d
        parts = [(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))]
        if active.size and len(self.gaussians):
            self.stats.casts += 1
            self.stats.rays_cast += active.size
            for r, _, prim in self._backend.all_hits(start_pt[active].astype(np.float32),
                                                     d[active].astype(np.float32), (t_hi - t0)[active]):
                ray_idx, g = self._candidates(prim, active[r], d, start_pt)
                # A ray through a shared edge or vertex crosses several faces of one proxy at once.
                key = np.unique(ray_idx * len(self.gaussians) + g)
                ray_idx, g = key // len(self.gaussians), key % len(self.gaussians)
                parts.append(self._soft_contributions(ray_idx, g, o, d, tmin, tmax))
        return self._soft_result(n, o, d, parts)

    def _trace_soft(self, o, d, tmin, tmax, t_lo, t_hi) -> Hits:
        if hasattr(self._backend, "all_hits"):
            return self._trace_soft_listed(o, d, tmin, tmax, t_lo, t_hi)
        n = o.shape[0]
        walk = _FaceWalk(self, o, d, t_lo, t_hi)
        log_t_min = np.log(self.soft_min_transmittance)
        log_tr = np.zeros(n)  # log transmittance of the contributions known to be final
        done = []  # finalised contributions (ray, gaussian, t*, alpha) per round
        pend = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
        while walk.active.size and walk.iterations < self.max_iterations and len(self.gaussians):
            active, prim, again = walk.cast(t_hi)
            if not active.size:
                break
            ray_idx, g = self._candidates(prim[~again], active[~again], d, walk.start_pt)
            pend = tuple(np.concatenate([a, b]) for a, b in
                         zip(pend, self._soft_contributions(ray_idx, g, o, d, tmin, tmax)))
            # Any Gaussian not found yet has its proxy entry, hence its t*, beyond this ray's last
            # face: contributions in front of it are final, and once their transmittance is below
            # the threshold the ray is done.
            final = pend[2] < walk.t_cur[pend[0]] - walk.step[pend[0]]
            if np.any(final):
                done.append(tuple(a[final] for a in pend))
                np.add.at(log_tr, pend[0][final], np.log1p(-pend[3][final]))
                pend = tuple(a[~final] for a in pend)
            walk.active = active[(log_tr[active] > log_t_min) & (walk.t_cur[active] < t_hi[active])]
        active = walk.active
        it = walk.iterations
        self.stats.unfinished += int(active.size) if it >= self.max_iterations else 0
        done.append(pend)
        return self._soft_result(n, o, d, done)


class _FaceWalk:
    """Each ray's walk through the proxy faces in order of distance, one Embree cast per step.

    A cast starts at `t_cur` (float64, converted to float32 only for Embree) and finds the next
    face; the next cast starts just past it (see `Tracer._next_step`)."""

    def __init__(self, tracer: "Tracer", o, d, t_lo, t_hi):
        self.tracer, self.o, self.d = tracer, o, d
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
        tr, a = self.tracer, self.active
        self.iterations += 1
        start = (self.o[a] + self.t_cur[a, None] * self.d[a]).astype(np.float32)
        tf, prim = tr._backend.first_hit(start, self.d32[a], (far[a] - self.t_cur[a]).astype(np.float32))
        tr.stats.casts += 1
        tr.stats.rays_cast += a.size
        found = prim >= 0
        a, tf, prim = a[found], tf[found], prim[found]
        step, again = tr._next_step(a, prim, start[found] + tf[:, None] * self.d32[a], self.last_prim, self.step)
        self.t_cur[a] += tf.astype(np.float64) + step
        self.active = a
        return a, prim, again


def composite_front_to_back(ray, t, alpha, gid, n, min_transmittance):
    """Alpha-composite per-ray samples in order of t until transmittance < min_transmittance.

    ray, t, alpha, gid: (K,) samples. Returns (depth (n,) float64: sum(w t) / sum(w) with
    w = T alpha, inf where nothing; accumulated alpha (n,) = 1 - T_final; gaussian (n,) int64 of
    the largest weight, -1 where nothing)."""
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
    return depth, acc, best
