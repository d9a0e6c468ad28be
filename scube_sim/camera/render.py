"""Render cameras on triangle meshes with Embree: RGB, metric depth, semantics, sky mask.

Shading: Lambertian with a sun (and its shadow, traced) plus sky ambient light, on an albedo the
caller passes (the worlds pass their procedural `worlds.textures.albedo`); the sky is a
horizon-to-zenith gradient with a glow around the sun. Albedo and output are sRGB; lighting is
applied in linear light.
"""

from __future__ import annotations

import numpy as np

from ..labels import label_id
from ..raytrace.compose import nearest_hits
from ..raytrace.tracer import Tracer
from .model import Intrinsics

SKY = label_id("sky")


def _to_linear(c):
    return np.power(np.clip(c, 0, 1), 2.2)


def _to_srgb(c):
    return np.power(np.clip(c, 0, 1), 1 / 2.2)


def sky_color(dirs: np.ndarray, sun_dir: np.ndarray) -> np.ndarray:
    """(N, 3) world directions -> (N, 3) linear RGB of the sky."""
    up = np.clip(dirs[:, 2], -0.2, 1.0)
    horizon = np.array([0.80, 0.85, 0.92])
    zenith = np.array([0.25, 0.45, 0.85])
    w = np.clip(up, 0, 1)[:, None] ** 0.6
    c = _to_linear((1 - w) * horizon + w * zenith)
    glow = np.clip(dirs @ sun_dir, 0, 1) ** 64
    return c + glow[:, None] * np.array([1.0, 0.9, 0.7])


def _footprint(t: np.ndarray, d: np.ndarray, nrm: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(N,) metres of surface one pixel covers at hits `t` metres along unit rays `d` on faces
    with normals `nrm`: range times the pixel's angle, stretched by the incidence (the geometric
    mean of the footprint's two axes, so a road at a grazing angle blurs along the ray only as
    much as a lens would average it across both)."""
    cos = np.abs(np.sum(d * nrm, axis=1))
    return t / intr.fx / np.sqrt(np.maximum(cos, 0.05))


def render_camera(tracers: list[Tracer], intr: Intrinsics, cam_to_world: np.ndarray, *,
                  sun_dir=(0.3, 0.2, 0.93), shadows: bool = True, shading: bool = True, albedo_fn=None,
                  max_depth: float = 1000.0, exposure: float = 1.0, vignetting: float = 0.0):
    """Render one camera.

    tracers: mesh tracers (e.g. the static world and its actors at this instant).
    cam_to_world: (4, 4) OpenCV camera -> world. shading=False skips colour (rgb is None): depth,
    semantics and sky only. albedo_fn(points (N, 3) world, normals (N, 3), labels (N,), face
    colours (N, 3), instances (N,), *, footprint (N,) metres a pixel covers at the hit (for
    filtering detail finer than a pixel), view (N, 3) unit ray directions, world) -> (N, 3) sRGB
    in [0, 1]: the surface colour to shade, e.g. `scube_sim.worlds.textures.albedo`; required
    when shading. exposure: the camera's gain on linear light (auto exposure differs between
    cameras and drifts in time); vignetting: the lens's fall-off, the share of light lost at the
    image's corners (1 - vignetting * r^2, r the distance from the principal point over the
    half-diagonal). Returns a dict with
    rgb (H, W, 3) uint8, depth (H, W) float32 metres along the optical axis (inf on sky),
    semantic (H, W) int16 (sky where nothing is hit), instance (H, W) int32, sky (H, W) bool.
    """
    if shading and albedo_fn is None:
        raise TypeError("render_camera: shading needs an albedo_fn (e.g. scube_sim.worlds.textures.albedo), "
                         "or pass shading=False")
    sun = np.asarray(sun_dir, np.float64)
    sun = sun / np.linalg.norm(sun)
    d_cam = intr.pixel_rays().reshape(-1, 3)
    r, t = cam_to_world[:3, :3], cam_to_world[:3, 3]
    d = d_cam @ r.T
    o = np.broadcast_to(t, d.shape)
    h = nearest_hits(tracers, o, d, 0.0, max_depth)
    hit = h.hit
    n = d.shape[0]
    rgb = np.empty((n, 3))
    rgb[~hit] = sky_color(d[~hit], sun) if shading else 0.0
    if hit.any() and shading:
        p = h.points[hit]
        nrm = h.normals[hit].astype(np.float64)
        alb = _to_linear(albedo_fn(p, nrm, h.label[hit], h.color[hit], h.instance[hit],
                                   footprint=_footprint(h.t[hit], d[hit], nrm, intr), view=d[hit]))
        lambert = np.clip(nrm @ sun, 0.0, None)
        if shadows:
            lit = lambert > 0
            sh = nearest_hits(tracers, p[lit] + nrm[lit] * 1e-3, np.broadcast_to(sun, (int(lit.sum()), 3)), 0.0, max_depth)
            lambert[np.nonzero(lit)[0][sh.hit]] = 0.0
        ambient = 0.35 + 0.15 * np.clip(nrm[:, 2], 0, 1)  # more sky light on upward faces
        rgb[hit] = alb * (ambient[:, None] * np.array([0.85, 0.9, 1.0]) + 0.9 * lambert[:, None] * np.array([1.0, 0.97, 0.9]))
    if shading and (exposure != 1.0 or vignetting != 0.0):
        uu, vv = np.meshgrid(np.arange(intr.width) + 0.5, np.arange(intr.height) + 0.5)
        r2 = ((uu - intr.cx) ** 2 + (vv - intr.cy) ** 2).reshape(-1) / ((intr.width / 2) ** 2 + (intr.height / 2) ** 2)
        rgb *= (exposure * (1.0 - vignetting * np.minimum(r2, 1.5)))[:, None]
    depth = np.where(hit, h.t * d_cam[:, 2], np.inf).astype(np.float32)
    sem = np.where(hit, h.label, SKY).astype(np.int16)
    inst = np.where(hit, h.instance, 0).astype(np.int32)
    shape = (intr.height, intr.width)
    return {
        "rgb": (np.round(_to_srgb(rgb) * 255)).astype(np.uint8).reshape(shape + (3,)) if shading else None,
        "depth": depth.reshape(shape),
        "semantic": sem.reshape(shape),
        "instance": inst.reshape(shape),
        "sky": (~hit).reshape(shape),
    }
