"""Procedural surface detail per semantic class, evaluated at surface points.

The worlds' images are the converter's training data and the stereo's test bed, so their surfaces
must be as matchable as real photographs: brick and plaster facades with framed windows whose
glass reflects a constant environment, worn asphalt with cracks and patches, kerb stones, paving,
grass, leaves at leaf scale, bark, planks, and vehicles with panels, windows, lights and plates.

Every pattern is a deterministic function of where the point sits on its surface: world
coordinates for the static scene, the object's own frame for anything with a box (parked and
moving vehicles, pedestrians: `ObjectFrames`), so a surface looks the same from every camera and
instant and a moving car carries its paint with it. Nothing is drawn per image.

Detail finer than a pixel would alias (point sampling turns it into noise that differs between
views, which no matcher can use and real lenses never show), so each pattern is filtered by the
pixel footprint at the hit (`footprint`, metres): noise octaves fade out below two pixels, lines
and joints are box-filtered analytically. Glass adds the reflection of a fixed environment (a sky
and a skyline at infinity) along the mirrored view ray, so it is the one view-dependent surface,
as in real streets. Colours are sRGB in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..labels import label_id

_ROAD, _MARK, _SIDEWALK, _CURB = label_id("road"), label_id("lane_marker"), label_id("sidewalk"), label_id("curb")
_TERRAIN, _BUILDING, _VEG, _TRUNK = label_id("terrain"), label_id("building"), label_id("vegetation"), label_id("tree_trunk")
_FENCE, _CAR, _TRUCK = label_id("fence"), label_id("car"), label_id("truck")
_PED, _POLE, _SIGN = label_id("pedestrian"), label_id("pole"), label_id("sign")

# 1: flat per-class patterns (worlds datasets of layout versions 2 and 3). 2: surface detail
# filtered by the pixel footprint, objects textured in their own frames, reflecting glass.
TEXTURE_VERSION = 2

# The vehicle generator's fixed construction (`generator.vehicle_mesh`): wheel radius, the body's
# underside and the cabin's colour, so that lights and plates land on the body's faces.
_WHEEL_R = {"car": 0.33, "truck": 0.48}
_CABIN_RGB = np.array([0.12, 0.15, 0.2])
_TYRE_RGB = np.array([0.05, 0.05, 0.05])


@dataclass
class ObjectFrames:
    """The frames of the objects that carry their texture with them, at one instant.

    ids (K,) int instance ids; to_object (K, 4, 4) float64 world -> object (x forward, y left,
    z up, origin at the middle of the box's bottom face); size (K, 3) length, width, height, metres."""

    ids: np.ndarray
    to_object: np.ndarray
    size: np.ndarray

    @classmethod
    def from_boxes(cls, boxes) -> "ObjectFrames":
        """From `Box`es (world frame) with instance ids; boxes without one (0) are left out."""
        boxes = [b for b in boxes if b.instance]
        if not boxes:
            return cls(np.zeros(0, np.int64), np.zeros((0, 4, 4)), np.zeros((0, 3)))
        mats = []
        for b in boxes:
            r = b.rotation
            bottom = b.center - r[:, 2] * b.size[2] / 2
            m = np.eye(4)
            m[:3, :3] = r.T
            m[:3, 3] = -r.T @ bottom
            mats.append(m)
        return cls(np.array([b.instance for b in boxes], np.int64), np.stack(mats),
                   np.stack([b.size for b in boxes]))

    def lookup(self, instances: np.ndarray) -> np.ndarray:
        """(N,) instance ids -> (N,) row in this table, -1 where the instance has no frame."""
        if len(self.ids) == 0:
            return np.full(len(instances), -1)
        order = np.argsort(self.ids)
        pos = np.clip(np.searchsorted(self.ids[order], instances), 0, len(self.ids) - 1)
        row = order[pos]
        return np.where(self.ids[row] == instances, row, -1)


def world_albedo(world, t: float):
    """The albedo function of `world` at time `t` (its vehicles and pedestrians where they are
    then): `albedo` with the objects' frames bound, for `camera.render.render_camera`."""
    frames = ObjectFrames.from_boxes(world.boxes_at(t))

    def fn(points, normals, labels, base, instances, **kw):
        return albedo(points, normals, labels, base, instances, objects=frames, **kw)

    return fn


# --- noise and filtered patterns ---------------------------------------------------------------

def _hash(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Integer lattice -> uniform [0, 1) values (a 32-bit integer hash)."""
    h = (np.asarray(ix).astype(np.int64) * 374761393 + np.asarray(iy).astype(np.int64) * 668265263
         + seed * 2147483647) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).astype(np.float64) / float(1 << 24)


def value_noise(x: np.ndarray, y: np.ndarray, scale: float, seed: int = 0) -> np.ndarray:
    """Smooth noise in [0, 1] with features about `scale` metres across."""
    u, v = x / scale, y / scale
    i, j = np.floor(u), np.floor(v)
    fu, fv = u - i, v - j
    fu, fv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    a, b = _hash(i, j, seed), _hash(i + 1, j, seed)
    c, d = _hash(i, j + 1, seed), _hash(i + 1, j + 1, seed)
    return (a * (1 - fu) + b * fu) * (1 - fv) + (c * (1 - fu) + d * fu) * fv


def _fade(feature_m, fw: np.ndarray) -> np.ndarray:
    """How much of a pattern with features `feature_m` across survives a pixel footprint `fw`
    (metres): 1 from three pixels per feature, 0 at one (what a lens and the sensor average out)."""
    return np.clip(feature_m / (2.0 * np.maximum(fw, 1e-6)) - 0.5, 0.0, 1.0)


def noise(x, y, scale: float, seed: int, fw) -> np.ndarray:
    """`value_noise` filtered by the footprint: it fades to its mean, 0.5, where too fine to see."""
    a = _fade(scale, fw)
    if not np.any(a > 0):
        return np.full(np.shape(x), 0.5)
    return 0.5 + (value_noise(x, y, scale, seed) - 0.5) * a


def fbm(x, y, scale: float, octaves: int = 3, seed: int = 0, fw=1e-4) -> np.ndarray:
    """Fractal noise in [0, 1]: `octaves` layers of filtered value noise, each half the size."""
    total, amp, norm = 0.0, 1.0, 0.0
    for k in range(octaves):
        total = total + amp * noise(x, y, scale / 2**k, seed + 17 * k, fw)
        norm += amp
        amp *= 0.5
    return total / norm


def _ramp_integral(x, period: float, width: float):
    k = np.floor(x / period)
    return k * width + np.clip(x - k * period, 0.0, width)


def lines(x, period: float, width: float, fw, offset=0.0) -> np.ndarray:
    """Coverage in [0, 1] of lines `width` wide every `period` metres (starting at `offset`),
    averaged over a footprint `fw` (an exact box filter): thin lines far away turn into a faint
    tone instead of flickering."""
    f = np.maximum(fw, 1e-4)
    x = x - offset
    return (_ramp_integral(x + f / 2, period, width) - _ramp_integral(x - f / 2, period, width)) / f


def _box(x, lo, hi, fw) -> np.ndarray:
    """Coverage in [0, 1] of the interval [lo, hi) averaged over a footprint `fw`."""
    f = np.maximum(fw, 1e-4)
    return np.clip((np.minimum(x + f / 2, hi) - np.maximum(x - f / 2, lo)) / f, 0.0, 1.0)


def _cells(x, y, size_x: float, size_y: float, seed: int, fw, stagger: float = 0.0):
    """Per-cell uniform values of a (staggered) grid of cells, faded to 0.5 where the cells are
    under three pixels, and the cell-local coordinates (u in [0, size_x), v in [0, size_y))."""
    row = np.floor(y / size_y)
    xs = x + stagger * size_x * (row % 2)
    col = np.floor(xs / size_x)
    val = 0.5 + (_hash(col, row, seed) - 0.5) * _fade(min(size_x, size_y), fw)
    return val, xs - col * size_x, y - row * size_y


def _cracks(x, y, scale: float, width: float, seed: int, fw) -> np.ndarray:
    """Coverage of thin cracks along the zero set of a noise field (a ridge), in patches."""
    n = value_noise(x, y, scale, seed) - 0.5
    d = np.abs(n) * scale * 2.5  # roughly metres to the ridge (the noise's slope ~ 1 / (2.5 scale))
    w = np.maximum(width, fw)
    cover = np.clip(1.0 - d / w, 0.0, 1.0) * np.minimum(1.0, width / np.maximum(fw, 1e-4))
    return cover * (value_noise(x, y, scale * 4, seed + 1) > 0.55)


def _mix(a, b, t):
    """a * (1 - t) + b * t for (N, 3) colours and (N,) weights."""
    t = np.asarray(t)[:, None]
    return a * (1.0 - t) + b * t


# --- the environment reflected by glass -----------------------------------------------------------

def environment(dirs: np.ndarray) -> np.ndarray:
    """(N, 3) unit world directions -> (N, 3) sRGB radiance of a fixed environment at infinity:
    a sky gradient, a skyline of blocks around the horizon and grey ground below it."""
    z = dirs[:, 2]
    az = np.arctan2(dirs[:, 1], dirs[:, 0])
    block = np.floor(az / 0.09)
    sky_w = np.clip(z, 0.0, 1.0)[:, None] ** 0.6
    sky = (1 - sky_w) * np.array([0.80, 0.85, 0.92]) + sky_w * np.array([0.30, 0.50, 0.85])
    # clouds, and windows on the skyline's blocks, a few milliradians across: a pane reflects
    # them with detail a matcher can see (it is still view-dependent, as real glass is)
    el = np.arcsin(np.clip(z, -1.0, 1.0))
    sky = sky * (0.85 + 0.3 * fbm(az, el, 0.08, 3, 43))[:, None]
    height = 0.04 + 0.3 * _hash(block, 7, 41)
    windows = (lines(az, 0.012, 0.006, 1e-4) * lines(el, 0.015, 0.008, 1e-4))
    facade = ((0.25 + 0.45 * _hash(block, 3, 42)) * (1.0 - 0.5 * windows))[:, None] * np.array([1.0, 0.97, 0.93])
    ground = np.array([0.28, 0.27, 0.26]) * (0.7 + 0.6 * value_noise(az, el, 0.01, 44))[:, None]
    out = np.where((z < height)[:, None], facade, sky)
    return np.where((z < 0)[:, None], ground, out)


def _glass(view, n, tint, dark: float = 0.12) -> np.ndarray:
    """Glass seen along `view` (N, 3), normals `n`: a dark tint plus the mirrored environment,
    stronger at grazing angles (Schlick's Fresnel term on a 4 % base). Without a view (texturing
    a VoxSplat) the environment's mean reflection at normal incidence."""
    if view is None:
        return np.clip(dark * tint + 0.1, 0, 1)
    cos = np.clip(-np.sum(view * n, axis=1), 0.0, 1.0)
    refl = view + 2.0 * cos[:, None] * n
    fres = 0.04 + 0.96 * (1.0 - cos) ** 5
    return np.clip(dark * tint + (0.25 + 0.75 * fres)[:, None] * environment(refl), 0.0, 1.0)


# --- surface coordinates --------------------------------------------------------------------------

def _surface_uv(p: np.ndarray, n: np.ndarray):
    """2D coordinates on the surface: (x, y) on ground-like faces, (along-wall, z) on walls."""
    wall = np.abs(n[:, 2]) < 0.5
    t = np.stack([-n[:, 1], n[:, 0]], 1)
    tn = np.linalg.norm(t, axis=1, keepdims=True)
    t = np.divide(t, tn, out=np.zeros_like(t), where=tn > 0)
    along = t[:, 0] * p[:, 0] + t[:, 1] * p[:, 1]
    return np.where(wall, along, p[:, 0]), np.where(wall, p[:, 2], p[:, 1]), wall


def albedo(points: np.ndarray, normals: np.ndarray, labels: np.ndarray, base: np.ndarray,
           instances: np.ndarray, *, footprint=None, view=None, objects: ObjectFrames | None = None) -> np.ndarray:
    """The surface colour at world points.

    points, normals (N, 3) world frame; labels, instances (N,); base (N, 3) the faces' colours;
    footprint: (N,) or scalar, metres a pixel covers at the point (None: 1 cm, full detail);
    view: (N, 3) unit ray directions from the camera (None: no reflections); objects: the frames
    of boxed objects at this instant (`ObjectFrames`; None: vehicles textured in world
    coordinates, right for a still scene only). Returns (N, 3) float32 sRGB."""
    p = np.asarray(points, np.float64)
    n = np.asarray(normals, np.float64)
    lab = np.asarray(labels)
    inst = np.asarray(instances)
    col = np.asarray(base, np.float64).copy()
    if len(p) == 0:
        return col.astype(np.float32)
    fw = np.broadcast_to(np.asarray(0.01 if footprint is None else footprint, np.float64), (len(p),)).copy()
    v = None if view is None else np.asarray(view, np.float64)
    u, w, wall = _surface_uv(p, n)
    x, y = p[:, 0], p[:, 1]

    def sel(mask):
        return mask, fw[mask]

    m, f = sel(lab == _ROAD)
    if m.any():
        col[m] = _asphalt(x[m], y[m], col[m], f)
    m, f = sel(lab == _MARK)
    if m.any():
        wear = fbm(x[m], y[m], 0.4, 3, 3, f)
        asphalt = _asphalt(x[m], y[m], np.tile([0.22, 0.22, 0.24], (int(m.sum()), 1)), f)
        paint = col[m] * (0.88 + 0.2 * noise(x[m], y[m], 0.03, 4, f))[:, None]
        col[m] = _mix(paint, asphalt, np.clip((wear - 0.62) * 4.0, 0, 0.85))
    m, f = sel(lab == _SIDEWALK)
    if m.any():
        col[m] = _paving(x[m], y[m], col[m], f)
    m, f = sel(lab == _CURB)
    if m.any():
        col[m] = _kerb(u[m], w[m], col[m], f)
    m, f = sel(lab == _TERRAIN)
    if m.any():
        col[m] = _grass(x[m], y[m], col[m], f)
    m, f = sel(lab == _BUILDING)
    if m.any():
        col[m] = _facade(u[m], w[m], wall[m], col[m], inst[m], x[m], y[m], n[m], None if v is None else v[m], f)
    m, f = sel(lab == _VEG)
    if m.any():
        col[m] = _foliage(p[m], u[m], w[m], col[m], inst[m], f)
    m, f = sel(lab == _TRUNK)
    if m.any():
        # bark: furrows 2 cm across and 13 cm along the trunk (u runs around it, face by face)
        furrow = noise(u[m], w[m] * 0.15, 0.02, 10, f)
        col[m] *= ((0.55 + 0.7 * furrow) * (0.8 + 0.4 * noise(u[m], w[m], 0.08, 11, f)))[:, None]
    m, f = sel(lab == _FENCE)
    if m.any():
        gap = lines(u[m], 0.15, 0.015, f)
        grain = noise(u[m] * 8.0, w[m], 0.05, 12, f)  # wood grain runs along the plank (vertical)
        plank = 0.85 + 0.3 * _cells(u[m], w[m], 0.15, 50.0, 13, f)[0]  # a tone per plank
        col[m] *= ((1 - 0.65 * gap) * (0.8 + 0.35 * grain) * plank)[:, None]
    m, f = sel((lab == _POLE) | (lab == _SIGN))
    if m.any():
        col[m] *= (0.8 + 0.4 * fbm(u[m], w[m], 0.3, 3, 14, f))[:, None]

    boxed = (lab == _CAR) | (lab == _TRUCK) | (lab == _PED)
    if boxed.any():
        q, qn, size = p[boxed], n[boxed], np.zeros((int(boxed.sum()), 3))
        if objects is not None:
            row = objects.lookup(inst[boxed])
            has = row >= 0
            mat = objects.to_object[row[has]]
            q[has] = np.einsum("nij,nj->ni", mat[:, :3, :3], q[has]) + mat[:, :3, 3]
            qn[has] = np.einsum("nij,nj->ni", mat[:, :3, :3], qn[has])
            size[has] = objects.size[row[has]]
        vb = None if v is None else v[boxed]
        if vb is not None and objects is not None:
            vb = vb.copy()
            vb[has] = np.einsum("nij,nj->ni", mat[:, :3, :3], vb[has])
        lb = lab[boxed]
        out = col[boxed]
        vm = (lb == _CAR) | (lb == _TRUCK)
        if vm.any():
            out[vm] = _vehicle(q[vm], qn[vm], size[vm], out[vm], lb[vm], None if vb is None else vb[vm], fw[boxed][vm])
        pm = lb == _PED
        if pm.any():
            out[pm] *= (0.8 + 0.4 * fbm(q[pm, 0] + q[pm, 1], q[pm, 2], 0.15, 3, 15, fw[boxed][pm]))[:, None]
        col[boxed] = out
    return np.clip(col, 0.0, 1.0).astype(np.float32)


# --- materials --------------------------------------------------------------------------------------

def _asphalt(x, y, base, fw):
    """Asphalt: aggregate grain, wear at metre scale, darker repaired patches, cracks."""
    grain = 0.62 + 0.55 * noise(x, y, 0.012, 21, fw) + 0.3 * (noise(x, y, 0.04, 22, fw) - 0.5)
    wear = 0.8 + 0.35 * fbm(x, y, 2.5, 3, 23, fw)
    _, pu, pv = _cells(x, y, 5.0, 3.0, 24, fw, stagger=0.5)
    patched = _hash(np.floor((x + 2.5 * (np.floor(y / 3.0) % 2)) / 5.0), np.floor(y / 3.0), 24) > 0.8
    tone = 1.0 - 0.28 * patched * _box(pu, 0.6, 3.4, fw) * _box(pv, 0.4, 2.2, fw)
    crack = np.maximum(_cracks(x, y, 1.2, 0.012, 25, fw), _cracks(x + 31.0, y, 0.7, 0.008, 26, fw))
    return base * (grain * wear * tone * (1.0 - 0.7 * crack))[:, None]


def _paving(x, y, base, fw):
    """Sidewalk slabs 0.6 m square with joints, each slab its own tone, grain and stains."""
    tile, _, _ = _cells(x, y, 0.6, 0.6, 31, fw)
    joint = 1.0 - (1.0 - lines(x, 0.6, 0.012, fw)) * (1.0 - lines(y, 0.6, 0.012, fw))
    grain = 0.8 + 0.4 * noise(x, y, 0.015, 32, fw)
    stain = 0.8 + 0.3 * fbm(x, y, 1.5, 3, 33, fw)
    return base * ((0.82 + 0.3 * tile) * grain * stain * (1.0 - 0.55 * joint))[:, None]


def _kerb(u, z, base, fw):
    """Kerb stones 0.8 m long with joints, speckled granite."""
    stone, _, _ = _cells(u, z, 0.8, 10.0, 36, fw)
    joint = lines(u, 0.8, 0.01, fw)
    speckle = 0.7 + 0.6 * noise(u, z, 0.01, 37, fw)
    return base * ((0.85 + 0.25 * stone) * speckle * (1.0 - 0.6 * joint))[:, None]


def _grass(x, y, base, fw):
    """Grass: blades (fine high-contrast noise), clumps, and dirt patches."""
    blades = 0.5 + 0.9 * (noise(x, y, 0.015, 41, fw) - 0.5) + 0.6 * (noise(x * 1.7, y * 0.6, 0.03, 42, fw) - 0.5)
    tufts = 0.45 + 1.1 * fbm(x, y, 0.2, 3, 45, fw)  # tufts and their shadows, 5-20 cm
    clumps = 0.55 + 0.9 * fbm(x, y, 0.8, 2, 43, fw)
    c = base * (clumps * tufts * (0.5 + blades))[:, None]
    dirt = np.clip((fbm(x, y, 5.0, 3, 8, fw) - 0.6) * 6.0, 0, 1)
    soil = np.array([0.42, 0.34, 0.24]) * (0.7 + 0.5 * noise(x, y, 0.02, 44, fw))[:, None]
    return _mix(c, soil, dirt)


def _foliage(p, u, w, base, inst, fw):
    """Leaves: a cellular pattern of leaf-sized blobs (5-8 cm) with dark gaps between them, in
    clusters, lit unevenly; varies per plant."""
    offset = 13.0 * inst
    leaf, lu, lv = _cells(u + offset, w, 0.06, 0.05, 51, fw, stagger=0.5)
    # each leaf off its cell's centre and of its own size, so the cells do not read as a lattice
    cu, cv = 0.5 + 0.35 * (leaf - 0.5), 0.5 - 0.35 * (_hash(np.floor(w / 0.05), np.floor(u / 0.06), 53) - 0.5)
    r2 = ((lu / 0.06 - cu) ** 2 + (lv / 0.05 - cv) ** 2) * (0.8 + 0.5 * leaf)
    gap = np.clip((r2 - 0.16) * 6.0, 0, 1) * _fade(0.05, fw)  # the dark between leaves
    cluster = fbm(u + offset, w + p[:, 0] * 0.3, 0.35, 3, 52, fw)
    sprigs = noise(u + offset, w, 0.12, 54, fw)  # sprigs and the shade between them, 12 cm
    canopy = fbm(u + offset, w - p[:, 1] * 0.3, 1.2, 2, 55, fw)  # lit and shaded masses, metres across
    tone = (0.55 + 0.7 * leaf) * (0.2 + 1.4 * cluster) * (0.4 + 1.2 * sprigs) * (0.3 + 1.4 * canopy) * (1.0 - 0.6 * gap)
    hue = np.stack([0.9 + 0.3 * leaf, np.ones_like(leaf), 0.9 + 0.2 * (1 - leaf)], 1)
    return base * hue * tone[:, None]


def _facade(u, v, wall, base, inst, x, y, n, view, fw):
    """Walls: storeys of framed windows (glass reflecting the environment), a ground floor with
    larger shop windows, in one of three materials per building (brick in running bond, plaster
    with stains, concrete panels); roofs: gravel. Layout and material vary per building."""
    out = base.copy()
    storey = 3.2 + 0.4 * _hash(inst, inst * 7, 13)
    pitch = 2.4 + 1.2 * _hash(inst, inst * 3, 14)
    wwidth = pitch * (0.45 + 0.2 * _hash(inst, inst * 5, 15))
    material = np.floor(_hash(inst, inst * 11, 19) * 3)  # 0 brick, 1 plaster, 2 concrete panels
    fu = (u % pitch) / pitch
    fz = (v % storey) / storey
    floor_no = np.floor(v / storey)
    half = 0.5 * wwidth / pitch
    # the openings as coverage of the pixel footprint, so distant windows blend into the wall
    across = (fu - 0.5) * pitch
    in_win = _box(across, -half * pitch, half * pitch, fw) * _box(fz * storey, 0.3 * storey, 0.85 * storey, fw) \
        * (floor_no >= 1)
    shop = (floor_no < 1) * _box(v, 0.5, 2.6, fw) * _box(across, -0.42 * pitch, 0.42 * pitch, fw)
    # the frame: a 7 cm border and a mullion, measured in metres from the opening's edges
    du = np.minimum(np.abs(fu - 0.5 + half), np.abs(fu - 0.5 - half)) * pitch
    dz = np.minimum(np.abs(fz - 0.3), np.abs(fz - 0.85)) * storey
    mullion = np.abs(fu - 0.5) * pitch
    frame = np.maximum(np.maximum(_box(du, 0, 0.07, fw), _box(dz, 0, 0.07, fw)), _box(mullion, 0, 0.035, fw))
    sill = (floor_no >= 1) & (np.abs(fu - 0.5) < half + 0.05) & (fz > 0.26) & (fz <= 0.3)

    brick = _brick(u, v, out, fw)
    plaster = out * ((0.82 + 0.3 * fbm(u, v, 0.8, 4, 61, fw)) * (0.85 + 0.25 * noise(u, v, 0.02, 62, fw))
                     * (1.0 - 0.25 * np.clip((fbm(u * 3.0, v * 0.3, 1.0, 2, 63, fw) - 0.6) * 3, 0, 1)))[:, None]
    panel_joint = 1.0 - (1.0 - lines(u, 1.5, 0.02, fw)) * (1.0 - lines(v, 1.1, 0.02, fw))
    concrete = out * ((0.85 + 0.2 * _cells(u, v, 1.5, 1.1, 64, fw)[0]) * (0.8 + 0.35 * noise(u, v, 0.015, 65, fw))
                      * (0.9 + 0.2 * fbm(u, v, 0.5, 2, 66, fw)) * (1.0 - 0.5 * panel_joint))[:, None]
    wallc = np.where((material == 0)[:, None], brick, np.where((material == 1)[:, None], plaster, concrete))
    wallc = np.where(sill[:, None], wallc * 1.25 + 0.05, wallc)

    lit = _hash(np.floor(u / pitch) + 1000 * inst, floor_no, 16)
    tint = np.stack([0.5 + 0.5 * lit, 0.6 + 0.5 * lit, 0.7 + 0.6 * lit], 1)
    opening = wall * np.maximum(in_win, shop)
    o = opening > 0  # glass and its reflection only where a window covers part of the pixel
    glass = np.zeros_like(base)
    glass[o] = _glass(None if view is None else view[o], n[o], tint[o], dark=0.25)
    s = o & (shop > 0)
    glass[s] = glass[s] * 0.8 + 0.1 * tint[s] * fbm(u[s], v[s], 0.4, 2, 67, fw[s])[:, None]
    frame_col = np.where((_hash(inst, 5, 68) > 0.5), 0.85, 0.25)[:, None] * np.array([1.0, 1.0, 0.98])
    res = _mix(wallc, _mix(glass, frame_col, frame), opening)
    roof = ~wall
    if roof.any():
        xr, yr, fr = x[roof], y[roof], fw[roof]
        gravel = 0.55 + 0.5 * noise(xr, yr, 0.015, 69, fr) + 0.2 * (fbm(xr, yr, 1.0, 2, 18, fr) - 0.5)
        res[roof] = base[roof] * gravel[:, None]
    return res


def _brick(u, v, base, fw):
    """Brick in running bond: 24 x 7.5 cm courses with 1 cm mortar, each brick its own tone."""
    tone, bu, bv = _cells(u, v, 0.24, 0.075, 71, fw, stagger=0.5)
    row = np.floor(v / 0.075)
    mortar = 1.0 - (1.0 - lines(v, 0.075, 0.01, fw)) * (1.0 - lines(u + 0.12 * (row % 2), 0.24, 0.01, fw))
    surface = 0.85 + 0.3 * noise(u, v, 0.02, 72, fw)
    brick = base * ((0.75 + 0.5 * tone) * surface)[:, None]
    return _mix(brick, np.tile([0.72, 0.7, 0.66], (len(u), 1)), mortar * 0.85)


def _vehicle(q, n, size, base, lab, view, fw):
    """A vehicle in its own frame (x forward, z up from the ground): paint with panel seams and
    a sill line, dark glass all round the cabin with pillars, head and tail lights, a grille,
    number plates front and back, tyres with rims. Positions follow `generator.vehicle_mesh`'s
    construction (the body's underside at 0.43 m on cars and vans)."""
    out = base.copy()
    length, width = size[:, 0], size[:, 1]
    truck = lab == _TRUCK
    bottom = np.where(truck, 2 * _WHEEL_R["truck"] * 0.8, 2 * _WHEEL_R["car"] * 0.8 - 0.1)
    z = q[:, 2] - bottom  # height above the body's underside
    a, b = q[:, 0] + q[:, 1], q[:, 2] + 0.5 * q[:, 1]  # a 2D coordinate on every face
    flake = (0.9 + 0.2 * noise(a, b, 0.01, 81, fw)) * (0.8 + 0.4 * noise(a, b, 0.025, 87, fw))
    # a truck's box: corrugated sides, a rib every 0.3 m
    flake = flake * np.where(truck, 1.0 - 0.35 * lines(q[:, 0], 0.3, 0.06, fw), 1.0)
    dust = (0.6 + 0.8 * fbm(a, b, 0.12, 3, 85, fw)) * (0.55 + 0.9 * fbm(a, b, 0.4, 2, 86, fw))  # dust, wear, 3-40 cm
    dirt = 1.0 - 0.35 * np.clip((bottom + 0.35 - q[:, 2]) / 0.35, 0, 1) * fbm(q[:, 0], q[:, 2], 0.2, 3, 82, fw)
    # the sides' shoulder catches the sky, the flank under the crease the road
    shoulder = 1.0 + np.abs(n[:, 1]) * (0.35 * _box(z, 0.3, 10.0, fw) - 0.15)
    paint = out * (flake * dust * dirt * shoulder)[:, None]
    if view is not None:  # the clear coat mirrors the environment, weakly
        cos = np.clip(-np.sum(view * n, axis=1), 0.0, 1.0)
        coat = (0.1 + 0.5 * (1.0 - cos) ** 5)[:, None]
        paint = paint * (1.0 - coat) + coat * environment(view + 2.0 * cos[:, None] * n)
    cabin = np.all(np.abs(base - _CABIN_RGB) < 1e-3, axis=1)
    tyre = np.all(np.abs(base - _TYRE_RGB) < 1e-3, axis=1)
    side = np.abs(n[:, 1]) > 0.9
    front = n[:, 0] > 0.9
    rear = n[:, 0] < -0.9

    # seams: door gaps on the sides, a sill line, the bonnet's front edge
    seams = np.zeros(len(q))
    for frac in (-0.22, 0.05, 0.25):
        seams = np.maximum(seams, _box(q[:, 0] - frac * length, -0.006, 0.006, fw) * side)
    seams = np.maximum(seams, _box(z, 0.10, 0.115, fw) * side)
    # a handle near the rear edge of each front and rear door
    handles = side * _box(z, 0.38, 0.42, fw) * np.maximum(_box(q[:, 0] - 0.05 * length, -0.17, -0.04, fw),
                                                          _box(q[:, 0] - 0.25 * length, -0.17, -0.04, fw))
    paint = paint * ((1.0 - 0.75 * seams) * (1.0 - 0.45 * handles))[:, None]

    # lights, grille and plate on the body's front and rear faces
    ay = np.abs(q[:, 1])
    half_w = width / 2
    lamp_z = (_box(z, 0.24, 0.40, fw))
    lamp_y = _box(ay, half_w - 0.42, half_w - 0.08, fw)
    head = front * lamp_z * lamp_y
    tail = rear * lamp_z * lamp_y
    grille_m = front * _box(z, 0.18, 0.36, fw) * _box(ay, 0.0, half_w - 0.5, fw)
    slats = 0.5 + 0.5 * lines(q[:, 2], 0.03, 0.012, fw)
    plate = (front | rear) * _box(z, 0.04, 0.16, fw) * _box(ay, 0.0, 0.26, fw)
    chars = 1.0 - 0.8 * lines(q[:, 1], 0.055, 0.012, fw) * _box(z, 0.065, 0.135, fw)
    paint = _mix(paint, np.tile([0.95, 0.93, 0.85], (len(q), 1)), head)
    paint = _mix(paint, np.tile([0.75, 0.08, 0.06], (len(q), 1)), tail)
    paint = _mix(paint, np.tile([0.06, 0.06, 0.07], (len(q), 1)) * (0.6 + 0.8 * slats)[:, None], grille_m)
    paint = _mix(paint, np.tile([0.92, 0.92, 0.9], (len(q), 1)) * chars[:, None], plate)

    # the cabin: glass between pillars on the sides, windscreen front and back, dark roof
    pillar = side * np.maximum(_box(np.abs(q[:, 0] + 0.15 * length), 0.0, 0.05, fw),
                               lines(q[:, 0] + 0.15 * length + 0.25 * length, 0.25 * length + 1e-6, 0.08, fw))
    glass = np.zeros_like(base)  # reflections only on the cabin
    glass[cabin] = _glass(None if view is None else view[cabin], n[cabin],
                          np.tile([0.5, 0.6, 0.7], (int(cabin.sum()), 1)), dark=0.15)
    roof = n[:, 2] > 0.7
    cab = np.where(roof[:, None], out * (0.8 + 0.3 * noise(q[:, 0], q[:, 1], 0.02, 83, fw))[:, None],
                   _mix(glass, out * 0.6, pillar))

    # wheels: a grey rim with five spokes inside a black tyre, on the wheel's side faces
    wx = np.where(q[:, 0] > 0, 0.32, -0.32) * length
    r = np.where(truck, _WHEEL_R["truck"], _WHEEL_R["car"])
    dx, dz = q[:, 0] - wx, q[:, 2] - r
    rho = np.hypot(dx, dz) / r
    spokes = 0.5 + 0.5 * np.cos(5.0 * np.arctan2(dz, dx))
    rim = side * _box(rho, 0.0, 0.62, fw / r)
    tyre_c = np.tile([0.06, 0.06, 0.065], (len(q), 1)) * (0.8 + 0.4 * noise(dx, dz, 0.01, 84, fw))[:, None]
    wheel = _mix(tyre_c, np.tile([0.55, 0.56, 0.58], (len(q), 1)) * (0.5 + 0.6 * spokes)[:, None], rim)

    return np.where(cabin[:, None], cab, np.where(tyre[:, None], wheel, paint))
