"""Differentiable 3D Gaussian splatting on the CPU, in PyTorch (gsplat's rasterization needs CUDA).

`rasterization` has gsplat's call shape, ``rasterization(means, quats, scales, opacities, colors,
viewmats, Ks, width, height, ...) -> (render_colors, render_alphas, meta)``, so a GPU user can swap
``gsplat.rasterization`` in. What it computes, gsplat's way (EWA splatting, 3DGS):

1. **Projection** (`project_gaussians`): each Gaussian's camera-frame mean t = R mu + T and
   covariance W Sigma W^T, Sigma = R_q S S R_q^T; the 2D mean is t through the camera model of
   `camera/model.py` (pinhole, or OpenCV / fisheye distortion: the same formulas, in torch), the 2D
   covariance J W Sigma W^T J^T + eps2d I with J the Jacobian of that projection at t (pinhole: the
   3DGS Jacobian, its tx / tz clamped as gsplat does). Culled (radius 0): depth outside
   (near_plane, far_plane), past the lens's fold limit, or off the image by more than its radius
   ceil(3.33 sigma) per axis.
2. **Tiles**: every Gaussian is listed in the 16 x 16 tiles its radius box touches, sorted by
   depth within each tile.
3. **Compositing**, front to back per pixel (centres at integer + 0.5): sigma = 1/2 d^T Sigma2D^-1 d,
   alpha = min(0.999, o exp(-sigma)), skipped when sigma < 0 or alpha < 1/255; weight alpha T,
   T *= 1 - alpha, and a pixel stops before the Gaussian that would take T to 1e-4 or below.
   Colour = sum of weight x colour + T_final x background; alpha = 1 - T_final; depth: "D" the
   weighted sum of camera z, "ED" that over alpha.

Gradients reach means, quats, scales, opacities, colours (and the cameras) through autograd; each
tile is checkpointed, so memory is the inputs and one tile at a time, not every tile's
intermediates. The projection runs in float64 (cheap, O(N)): extreme scales neither overflow
nor lose the 2D inverse.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch.utils.checkpoint import checkpoint

from .activations import quats as unit_quats
from .activations import rotations
from .camera import distort, distort_jacobian, fold_limit

__all__ = ["Projection", "rasterization", "project_gaussians", "quat_scale_to_covar"]

ALPHA_MAX = 0.999
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
RADIUS_SIGMAS = 3.33  # gsplat's box half-width per axis, in standard deviations
RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")


def quat_scale_to_covar(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """(N, 4) wxyz quaternions (any norm; near zero -> identity) and (N, 3) std-devs -> (N, 3, 3)."""
    m = rotations(unit_quats(quats)) * scales[..., None, :]
    return m @ m.transpose(-1, -2)


# ---------------------------------------------------------------------------- projection
@dataclass
class Projection:
    """Per camera and Gaussian: means2d (C, N, 2) pixels; conics (C, N, 3) the upper triangle
    (a, b, c) of the inverse 2D covariance; depths (C, N) camera z, metres; radii (C, N, 2) int32
    half-widths of the box in pixels (0: culled); covars2d (C, N, 2, 2) with eps2d added."""

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor
    covars2d: torch.Tensor


def project_gaussians(means, quats, scales, viewmats, Ks, width: int, height: int, *, eps2d: float = 0.3,
                      near_plane: float = 0.01, far_plane: float = 1e10, camera_model: str = "pinhole",
                      dist_coeffs=None) -> Projection:
    """Project (N, 3) world means with (N, 4) wxyz quats and (N, 3) std-devs into C cameras:
    viewmats (C, 4, 4) world-to-camera (OpenCV axes), Ks (C, 3, 3) pixels. `camera_model`
    pinhole | opencv | fisheye with `dist_coeffs` (C, 5 | 4). Outputs in the means' dtype."""
    if camera_model not in ("pinhole", "opencv", "fisheye"):
        raise ValueError(f"camera_model: expected pinhole, opencv or fisheye, got {camera_model!r}")
    dtype = means.dtype
    f64 = torch.float64
    mu, covar = means.to(f64), quat_scale_to_covar(quats.to(f64), scales.to(f64))
    vm, k = viewmats.to(f64), Ks.to(f64)
    rot, trans = vm[:, :3, :3], vm[:, :3, 3]
    t = torch.einsum("cij,nj->cni", rot, mu) + trans[:, None, :]  # (C, N, 3)
    cov_c = rot[:, None] @ covar[None] @ rot.transpose(-1, -2)[:, None]  # (C, N, 3, 3)
    tz = t[..., 2]
    in_depth = (tz > near_plane) & (tz < far_plane)
    tzs = torch.where(in_depth, tz, torch.ones_like(tz))  # culled ones never divide by ~0 (no NaN grads)
    fx, fy = k[:, 0, 0, None], k[:, 1, 1, None]
    cx, cy = k[:, 0, 2, None], k[:, 1, 2, None]
    x, y = t[..., 0] / tzs, t[..., 1] / tzs
    # gsplat's clamp of the Jacobian's evaluation point: 30 % of the field of view past the edges
    tan_fx, tan_fy = 0.5 * width / fx, 0.5 * height / fy
    xj = torch.maximum(torch.minimum(x, (width - cx) / fx + 0.3 * tan_fx), -(cx / fx + 0.3 * tan_fx))
    yj = torch.maximum(torch.minimum(y, (height - cy) / fy + 0.3 * tan_fy), -(cy / fy + 0.3 * tan_fy))
    keep = in_depth.clone()  # in_depth is saved by torch.where for the backward
    if camera_model == "pinhole":
        xd, yd = x, y
        dj = None
    else:
        if dist_coeffs is None:
            raise ValueError(f"camera_model {camera_model!r}: give dist_coeffs (C, {5 if camera_model == 'opencv' else 4})")
        dc = torch.as_tensor(dist_coeffs, dtype=f64)
        need = 5 if camera_model == "opencv" else 4
        if dc.shape != (len(k), need):
            raise ValueError(f"dist_coeffs: expected shape ({len(k)}, {need}) for {camera_model}, got {tuple(dc.shape)}")
        coeffs = [dc[:, i, None] for i in range(need)]
        xd, yd = distort(x, y, camera_model, coeffs)
        dj = distort_jacobian(xj, yj, camera_model, coeffs)
        for c in range(len(k)):
            limit = fold_limit(camera_model, dc[c].tolist())
            if math.isfinite(limit):
                r = torch.sqrt(x[c] ** 2 + y[c] ** 2)
                keep[c] &= (r if camera_model == "opencv" else torch.atan(r)) <= limit
    means2d = torch.stack([fx * xd + cx, fy * yd + cy], -1)
    # J = diag(f) . d(distorted)/d(ideal) . d(ideal)/dt, ideal = (tx/tz, ty/tz)
    zero = torch.zeros_like(tz)
    inv_z = 1.0 / tzs
    d_ideal = torch.stack([inv_z, zero, -xj * inv_z, zero, inv_z, -yj * inv_z], -1).reshape(tz.shape + (2, 3))
    if dj is not None:
        d_ideal = dj @ d_ideal
    jac = torch.stack([fx.expand_as(tz), fy.expand_as(tz)], -1)[..., None] * d_ideal
    cov2d = jac @ cov_c @ jac.transpose(-1, -2) + eps2d * torch.eye(2, dtype=f64)
    det = (cov2d[..., 0, 0] * cov2d[..., 1, 1] - cov2d[..., 0, 1] * cov2d[..., 1, 0]).clamp_min(1e-10)
    conics = torch.stack([cov2d[..., 1, 1] / det, -0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0]) / det,
                          cov2d[..., 0, 0] / det], -1)
    with torch.no_grad():
        radii = torch.ceil(RADIUS_SIGMAS * torch.sqrt(torch.stack([cov2d[..., 0, 0], cov2d[..., 1, 1]], -1)))
        inside = ((means2d[..., 0] + radii[..., 0] > 0) & (means2d[..., 0] - radii[..., 0] < width)
                  & (means2d[..., 1] + radii[..., 1] > 0) & (means2d[..., 1] - radii[..., 1] < height))
        ok = keep & inside & torch.isfinite(means2d).all(-1) & torch.isfinite(conics).all(-1)
        radii = torch.where(ok[..., None], radii.clamp_max(2.0**30), torch.zeros_like(radii)).to(torch.int32)
    return Projection(means2d.to(dtype), conics.to(dtype), tz.to(dtype), radii, cov2d.to(dtype))


# ---------------------------------------------------------------------------- tiles and compositing
def _tile_lists(means2d, radii, depths, width: int, height: int, tile_size: int):
    """(Gaussian ids sorted by tile then depth, start offset of each tile (T + 1,)) for one camera."""
    tw, th = -(-width // tile_size), -(-height // tile_size)
    ids = torch.nonzero((radii > 0).all(-1)).squeeze(1)
    ids = ids[torch.argsort(depths[ids], stable=True)]
    m, r = means2d[ids].detach(), radii[ids].to(means2d.dtype)
    x0 = torch.floor((m[:, 0] - r[:, 0]) / tile_size).clamp(0, tw).long()
    x1 = torch.ceil((m[:, 0] + r[:, 0]) / tile_size).clamp(0, tw).long()
    y0 = torch.floor((m[:, 1] - r[:, 1]) / tile_size).clamp(0, th).long()
    y1 = torch.ceil((m[:, 1] + r[:, 1]) / tile_size).clamp(0, th).long()
    nx, ny = (x1 - x0).clamp_min(0), (y1 - y0).clamp_min(0)
    count = nx * ny
    owner = torch.repeat_interleave(torch.arange(len(ids)), count)
    local = torch.arange(int(count.sum())) - torch.repeat_interleave(torch.cumsum(count, 0) - count, count)
    tile = (y0[owner] + local // nx[owner]) * tw + x0[owner] + local % nx[owner]
    order = torch.argsort(tile, stable=True)  # within a tile: depth order, as `ids` was sorted
    offsets = torch.zeros(tw * th + 1, dtype=torch.long)
    offsets[1:] = torch.cumsum(torch.bincount(tile, minlength=tw * th), 0)
    return ids[owner[order]], offsets, tw, th


def _composite_tile(pix, means2d, conics, opacities, feats, chunk: int):
    """Front-to-back compositing of one tile: pix (P, 2) pixel centres; the tile's Gaussians in
    depth order. Returns (P, F) weighted features and (P,) log final transmittance."""
    log_t_min = math.log(T_MIN)
    acc = pix.new_zeros((pix.shape[0], feats.shape[1]))
    log_t = pix.new_zeros(pix.shape[0])
    for s in range(0, means2d.shape[0], chunk):
        m, cn = means2d[s:s + chunk], conics[s:s + chunk]
        dx = pix[:, None, 0] - m[None, :, 0]
        dy = pix[:, None, 1] - m[None, :, 1]
        sigma = 0.5 * (cn[None, :, 0] * dx * dx + cn[None, :, 2] * dy * dy) + cn[None, :, 1] * dx * dy
        alpha = torch.clamp_max(opacities[None, s:s + chunk] * torch.exp(-sigma.clamp_min(0)), ALPHA_MAX)
        alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
        l1 = torch.log1p(-alpha)
        incl = log_t[:, None] + torch.cumsum(l1, 1)  # log T after each Gaussian
        used = incl > log_t_min  # a pixel stops before the Gaussian that takes T to 1e-4
        w = torch.where(used, alpha * torch.exp(incl - l1), torch.zeros_like(alpha))
        acc = acc + w @ feats[s:s + chunk]
        log_t = log_t + torch.where(used, l1, torch.zeros_like(l1)).sum(1)
        if not bool(used[:, -1].any()):
            break  # every pixel is done: no later Gaussian can contribute
    return acc, log_t


def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width: int, height: int, *,
                  near_plane: float = 0.01, far_plane: float = 1e10, eps2d: float = 0.3, tile_size: int = 16,
                  backgrounds=None, render_mode: str = "RGB", camera_model: str = "pinhole", dist_coeffs=None,
                  chunk: int = 256, use_checkpoint: bool | None = None):
    """Render N Gaussians into C cameras (gsplat's call shape; see the module doc).

    means (N, 3) world metres; quats (N, 4) wxyz; scales (N, 3) std-devs (activated); opacities
    (N,) or (C, N) in [0, 1]; colors (N, D) or (C, N, D) any D features; viewmats (C, 4, 4)
    world-to-camera; Ks (C, 3, 3); backgrounds (C, D) or None (black). render_mode RGB | D | ED
    | RGB+D | RGB+ED (depth last). Returns render_colors (C, H, W, D[+1]), render_alphas
    (C, H, W, 1) and meta (the `Projection` fields, and tile counts)."""
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode: expected one of {', '.join(RENDER_MODES)}, got {render_mode!r}")
    n, cams = means.shape[0], viewmats.shape[0]
    for name, tensor, shape in (("means", means, (n, 3)), ("quats", quats, (n, 4)), ("scales", scales, (n, 3)),
                                ("viewmats", viewmats, (cams, 4, 4)), ("Ks", Ks, (cams, 3, 3))):
        if tuple(tensor.shape) != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {tuple(tensor.shape)}")
    proj = project_gaussians(means, quats, scales, viewmats, Ks, width, height, eps2d=eps2d, near_plane=near_plane,
                             far_plane=far_plane, camera_model=camera_model, dist_coeffs=dist_coeffs)
    dtype = means.dtype
    if colors.dim() == 2:
        colors = colors.expand(cams, -1, -1)
    if opacities.dim() == 1:
        opacities = opacities.expand(cams, -1)
    with_color = render_mode.startswith("RGB")
    with_depth = render_mode.endswith("D")
    if use_checkpoint is None:
        use_checkpoint = torch.is_grad_enabled()
    ys, xs = torch.meshgrid(torch.arange(height, dtype=dtype), torch.arange(width, dtype=dtype), indexing="ij")
    centres = torch.stack([xs, ys], -1) + 0.5  # (H, W, 2)
    images, alphas, tiles_hit = [], [], []
    for c in range(cams):
        feats = [colors[c]] if with_color else []
        if with_depth:
            feats.append(proj.depths[c][:, None])
        feat = torch.cat(feats, 1).to(dtype)
        order, offsets, tw, th = _tile_lists(proj.means2d[c], proj.radii[c], proj.depths[c], width, height, tile_size)
        pix_ids, values, log_ts = [], [], []
        for t in range(tw * th):
            a, b = int(offsets[t]), int(offsets[t + 1])
            if a == b:
                continue
            ty, tx = divmod(t, tw)
            block = centres[ty * tile_size:(ty + 1) * tile_size, tx * tile_size:(tx + 1) * tile_size]
            gy = torch.arange(ty * tile_size, ty * tile_size + block.shape[0])
            gx = torch.arange(tx * tile_size, tx * tile_size + block.shape[1])
            pix_ids.append((gy[:, None] * width + gx[None, :]).reshape(-1))
            g = order[a:b]
            args = (block.reshape(-1, 2), proj.means2d[c][g], proj.conics[c][g], opacities[c][g], feat[g])
            if use_checkpoint:
                acc, log_t = checkpoint(_composite_tile, *args, chunk, use_reentrant=False)
            else:
                acc, log_t = _composite_tile(*args, chunk)
            values.append(acc)
            log_ts.append(log_t)
        tiles_hit.append(len(pix_ids))
        d = feat.shape[1]
        if pix_ids:
            idx = torch.cat(pix_ids)
            img = torch.zeros(height * width, d, dtype=dtype).index_copy(0, idx, torch.cat(values))
            log_final = torch.zeros(height * width, dtype=dtype).index_copy(0, idx, torch.cat(log_ts))
        else:
            img = torch.zeros(height * width, d, dtype=dtype)
            log_final = torch.zeros(height * width, dtype=dtype)
        trans = torch.exp(log_final)[:, None]
        alpha = 1.0 - trans
        if with_depth and render_mode.endswith("ED"):
            img = torch.cat([img[:, :-1], img[:, -1:] / alpha.clamp_min(1e-10)], 1)
        if backgrounds is not None and with_color:
            bg = backgrounds[c].to(dtype)
            k = bg.shape[0]
            img = torch.cat([img[:, :k] + trans * bg, img[:, k:]], 1)
        images.append(img.reshape(height, width, d))
        alphas.append(alpha.reshape(height, width, 1))
    meta = {"means2d": proj.means2d, "conics": proj.conics, "depths": proj.depths, "radii": proj.radii,
            "covars2d": proj.covars2d, "tiles_hit": tiles_hit, "tile_width": -(-width // tile_size),
            "tile_height": -(-height // tile_size), "tile_size": tile_size}
    return torch.stack(images), torch.stack(alphas), meta
