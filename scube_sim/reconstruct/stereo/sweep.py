"""Plane-sweep stereo in inverse depth, on the CPU in PyTorch, deterministic.

A reference image and one or more source images of a static scene with known relative poses:
for each depth hypothesis d (fronto-parallel planes z = d in the reference camera, uniform in
1/d: `inverse_depth_hypotheses`) the source is warped into the reference view through the
plane's homography (`warp_to_reference`), a matching cost compares it with the reference per
pixel (`cost_ad`, `cost_ncc`, `cost_census`; lower is better) and the winner takes all
(`winner.py`: the best hypothesis, refined by a parabola in inverse depth, and a peak-ratio
confidence, whose floor CONF_EPS is here). `sweep_cost` runs the warp and one cost over the
hypotheses in chunks (memory stays bounded by the chunk, not by the number of hypotheses);
`combine_costs` averages the costs of several sources where they see the pixel.

Frames and units: OpenCV cameras (x right, y down, z forward). K: (3, 3) pinhole intrinsics in
the project's pixel convention (`camera.Intrinsics.K`): pixel (u, v) spans [u, u + 1), its centre
at u + 0.5, so a pixel's ray is K^-1 (u + 0.5, v + 0.5, 1) and a continuous coordinate x maps to
grid_sample's x * 2 / W - 1 with align_corners=False. Lens distortion is not modelled: undistort
first (or render pinhole). ref_to_src: (4, 4) rigid transform taking reference-camera
coordinates to source-camera coordinates (``inv(src.cam_to_world) @ ref.cam_to_world``). Depths:
metres along the reference camera's optical axis. Images: (C, H, W) float32, any fixed intensity
scale (the costs' thresholds assume [0, 1]).

Invalid pixels: a warped pixel is valid where the plane point lies in front of the source camera
and projects inside the source image ([0, Ws] x [0, Hs]). Costs are NaN where the centre pixel is
invalid; every cost's window averages over its valid pixels only, and the census counts only
bits whose neighbour is valid.

Census: computed on the warped image (for every hypothesis), not once on the source and then
warped with nearest sampling (``census_source`` in `sweep_cost`, the cheaper alternative).
The warp with a fronto-parallel plane maps the source's neighbourhood onto the reference's
window geometry (scale and perspective), so the two bit strings describe the same patch of the
surface; the source's own census describes a window of source pixels, which under forward motion
covers a different extent of the surface, and nearest sampling snaps sub-pixel shifts (the cost
curve becomes a staircase: under a translation every pixel of a fronto-parallel plane snaps by
the same fraction, so aggregation does not smooth it). experiments/stereo_costs.py compares the
two (experiments/results/stereo_costs_before.md).
The per-pixel Hamming distance is averaged over the same window as `cost_ad`'s differences: alone
(B = 48 bits per pixel, a cost in steps of 1/48) its curve has flat bottoms and outliers, which
the window's mean smooths.

Speed: the census compares each offset's neighbours on the slice where they lie on the image
(no shifted copies; counts in uint8) and the box filter runs as a row then a column pass, equal
to shifted copies and a 2D box within float rounding (1e-7).

Determinism: no atomics and no reductions whose order depends on the thread count (grid_sample's
forward, average pooling and elementwise operations compute each output from a fixed sequence of
inputs), so the bytes are the same whatever `torch.set_num_threads`.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ...errors import InputError
from ...transforms import check_pose

COSTS = ("ad", "ncc", "census", "census_source")
DEFAULT_WINDOW = 7
DEFAULT_CHUNK = 8
# NCC's variance floor (intensity^2, images in [0, 1]): under one 8-bit grey level's variance
# ((1/255)^2 ~ 1.5e-5), so a flat patch (sky, a uniform wall) correlates with nothing instead of
# with its rounding noise.
NCC_EPS = 1e-5
# Confidence's floor (cost units): two costs that differ by much less than this are a flat curve
# (rounding of the warp, identical views), not a peak.
CONF_EPS = 1e-3
MIN_SOURCE_Z = 1e-6  # metres: plane points at or behind the source camera are invalid
LUMA = (0.299, 0.587, 0.114)  # ITU-R BT.601 grey of RGB

__all__ = ["CONF_EPS", "COSTS", "DEFAULT_CHUNK", "DEFAULT_WINDOW", "NCC_EPS", "census_codes", "combine_costs",
           "cost_ad", "cost_census", "cost_hamming", "cost_ncc", "grey", "inverse_depth_hypotheses", "plane_terms",
           "sweep_cost", "warp_to_reference"]


# --- hypotheses and warping -----------------------------------------------------------------------


def inverse_depth_hypotheses(near: float = 0.5, far: float = 90.0, count: int = 128) -> torch.Tensor:
    """(count,) float64 depths in metres from `near` to `far` (ascending), uniform in 1/depth: equal
    steps of image motion for a sideways baseline, so far depths get few hypotheses and near ones many."""
    if not (0 < near < far < np.inf) or int(count) != count or count < 2:
        raise InputError(f"hypotheses: need 0 < near < far (finite) and count >= 2, got near={near}, far={far}, "
                         f"count={count}")
    return 1.0 / torch.linspace(1.0 / near, 1.0 / far, int(count), dtype=torch.float64)


def _matrix(k, name: str) -> torch.Tensor:
    k = torch.as_tensor(np.asarray(k, np.float64))
    if k.shape != (3, 3) or not bool(torch.isfinite(k).all()):
        raise InputError(f"{name}: expected a finite (3, 3) pinhole matrix, got shape {tuple(k.shape)}")
    return k


def _image(x, name: str) -> torch.Tensor:
    x = torch.as_tensor(x)
    if x.ndim != 3 or x.dtype != torch.float32:
        raise InputError(f"{name}: expected a (C, H, W) float32 image, got {tuple(x.shape)} {x.dtype}")
    return x


def _pixel_rays(k_ref: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(3, H*W) float64 rays K^-1 (u + 0.5, v + 0.5, 1) of the pixel centres, row-major (z = 1)."""
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5,
                          indexing="ij")
    pix = torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(h * w, dtype=torch.float64)])
    return torch.linalg.inv(k_ref) @ pix


def _plane_terms(k_src: torch.Tensor, k_ref: torch.Tensor, pose: torch.Tensor, h: int, w: int
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """The plane point of reference pixel p at depth d in the source's homogeneous pixels,
    K_src (R d ray_p + t) = d a[:, p] + b: a (3, H*W) and b (3, 1) float64 (k_src, k_ref (3, 3) and
    pose (4, 4) reference -> source, float64 tensors). The compiled sweep (`compiled.py`) takes
    the same terms."""
    a = k_src @ pose[:3, :3] @ _pixel_rays(k_ref, h, w)  # (3, H*W)
    b = k_src @ pose[:3, 3:]  # (3, 1)
    return a, b


def plane_terms(k_src, k_ref, ref_to_src, ref_hw: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """`warp_to_reference`'s homography terms of a source: k_src, k_ref (3, 3) pinhole, ref_to_src
    (4, 4), ref_hw (H, W) -> a (3, H*W), b (3, 1) float64 with the plane point of reference pixel p
    at depth d (metres) at d a[:, p] + b in the source's homogeneous pixels."""
    pose = torch.as_tensor(check_pose(ref_to_src, "ref_to_src"))
    h, w = (int(s) for s in ref_hw)
    return _plane_terms(_matrix(k_src, "k_src"), _matrix(k_ref, "k_ref"), pose, h, w)


def warp_to_reference(src, k_src, k_ref, ref_to_src, depths, ref_hw: tuple[int, int], *, mode: str = "bilinear",
                      chunk: int = DEFAULT_CHUNK) -> tuple[torch.Tensor, torch.Tensor]:
    """The source image seen through each fronto-parallel plane z = depth of the reference camera.

    src (C, Hs, Ws) float32; k_src, k_ref (3, 3) pinhole (module docstring's pixel convention);
    ref_to_src (4, 4) reference-camera -> source-camera; depths (D,) metres; ref_hw (H, W) of the
    reference. Returns warped (D, C, H, W) float32 (`mode`: grid_sample's 'bilinear' or 'nearest',
    border padding) and valid (D, H, W) bool (the plane point is in front of the source and lands
    in its image). The homography is applied per pixel in float64 (a plane point d K_ref^-1 p,
    moved and projected by K_src), `chunk` depths at a time.
    depths may also be (D, H, W) per-pixel depth maps (hypothesis k of pixel p at depths[k, p]: a
    narrow band around a coarse estimate); non-finite or non-positive depths are invalid."""
    src = _image(src, "src")
    _, hs, ws = src.shape
    h, w = (int(s) for s in ref_hw)
    pose = torch.as_tensor(check_pose(ref_to_src, "ref_to_src"))
    k_src = _matrix(k_src, "k_src")
    depths = torch.as_tensor(depths, dtype=torch.float64)
    per_pixel = depths.ndim == 3
    if per_pixel:
        if tuple(depths.shape[1:]) != (h, w):
            raise InputError(f"warp_to_reference: depth maps {tuple(depths.shape)}, reference {(h, w)}")
        usable = torch.isfinite(depths) & (depths > 0)
        depths = torch.where(usable, depths, torch.ones_like(depths)).reshape(-1, 1, h * w)
        usable = usable.reshape(-1, h * w)
    else:
        depths = depths.reshape(-1)
    a, b = _plane_terms(k_src, _matrix(k_ref, "k_ref"), pose, h, w)
    warped, valid = [], []
    for c, d in enumerate(depths.split(max(1, int(chunk)))):
        p = (d if per_pixel else d[:, None, None]) * a[None] + b[None]  # (Dc, 3, H*W)
        z = p[:, 2]
        front = z > MIN_SOURCE_Z
        if per_pixel:
            front = front & usable[c * max(1, int(chunk)):c * max(1, int(chunk)) + len(d)]
        zs = torch.where(front, z, torch.ones_like(z))
        x, y = p[:, 0] / zs, p[:, 1] / zs
        ok = front & (x >= 0) & (x <= ws) & (y >= 0) & (y <= hs)
        # continuous pixel coordinate -> [-1, 1] with align_corners=False; invalid points sample a
        # harmless in-range spot (their values are masked by `valid`)
        gx = torch.where(ok, 2.0 * x / ws - 1.0, torch.zeros_like(x))
        gy = torch.where(ok, 2.0 * y / hs - 1.0, torch.zeros_like(y))
        grid = torch.stack([gx, gy], -1).to(torch.float32).reshape(1, len(d) * h, w, 2)
        out = F.grid_sample(src[None], grid, mode=mode, padding_mode="border", align_corners=False)
        warped.append(out[0].reshape(src.shape[0], len(d), h, w).transpose(0, 1))
        valid.append(ok.reshape(len(d), h, w))
    return torch.cat(warped), torch.cat(valid)


# --- matching costs -------------------------------------------------------------------------------


def grey(image: torch.Tensor) -> torch.Tensor:
    """(..., C, H, W) -> (..., H, W) grey: BT.601 luma of RGB, the channel itself of one, else the mean
    (written out channel by channel: a fixed summation order)."""
    c = image.shape[-3]
    if c == 1:
        return image[..., 0, :, :]
    weights = LUMA if c == 3 else (1.0 / c,) * c
    out = image[..., 0, :, :] * weights[0]
    for i in range(1, c):
        out = out + image[..., i, :, :] * weights[i]
    return out


def _box(x: torch.Tensor, window: int) -> torch.Tensor:
    """(N, H, W) -> the mean over the window x window box centred on each pixel (zeros beyond the
    image: callers divide by the box of their mask, which cancels the count)."""
    r = window // 2  # separable: a row pass then a column pass (2 window taps, not window^2)
    x = F.avg_pool2d(x[:, None], (1, window), stride=1, padding=(0, r), count_include_pad=True)
    return F.avg_pool2d(x, (window, 1), stride=1, padding=(r, 0), count_include_pad=True)[:, 0]


def _window_mean(x: torch.Tensor, valid: torch.Tensor, window: int) -> torch.Tensor:
    """(D, H, W) per-pixel costs -> their mean over the valid pixels of the window x window box
    centred on each pixel, NaN where the centre is invalid (x may be anything there)."""
    x = torch.where(valid, x, torch.zeros_like(x))
    return _nan_where_invalid(_box(x, window) / _box(valid.to(torch.float32), window).clamp_min(1e-12), valid)


def _check_window(window: int) -> int:
    if int(window) != window or window < 3 or window % 2 == 0:
        raise InputError(f"window: expected an odd number of pixels >= 3, got {window!r}")
    return int(window)


def _nan_where_invalid(cost: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    return torch.where(valid, cost, torch.full_like(cost, float("nan")))


def cost_ad(ref, warped, valid, window: int = DEFAULT_WINDOW) -> torch.Tensor:
    """Absolute difference of grey, averaged over the valid pixels of a window x window box.
    ref (C, H, W), warped (D, C, H, W), valid (D, H, W) -> (D, H, W) float32, intensity units
    (>= 0), NaN where the centre is invalid."""
    window = _check_window(window)
    return _window_mean((grey(warped) - grey(ref)[None]).abs(), valid, window)


def cost_ncc(ref, warped, valid, window: int = DEFAULT_WINDOW) -> torch.Tensor:
    """1 - zero-mean normalised cross-correlation of grey over the valid pixels of a window x window
    box. ref (C, H, W), warped (D, C, H, W), valid (D, H, W) -> (D, H, W) float32 in [0, 2]
    (0: the patches match up to gain and offset; 1: flat or uncorrelated), NaN where the centre is
    invalid. Variances get NCC_EPS added, so flat patches score 1."""
    window = _check_window(window)
    m = valid.to(torch.float32)
    # centred on mid-grey: smaller squares, less cancellation in E[x^2] - E[x]^2 (float32)
    r, s = grey(ref)[None] - 0.5, grey(warped) - 0.5
    n = _box(m, window).clamp_min(1e-12)
    mr, ms = _box(r * m, window) / n, _box(s * m, window) / n
    cov = _box(r * s * m, window) / n - mr * ms
    vr = (_box(r * r * m, window) / n - mr * mr).clamp_min(0.0)
    vs = (_box(s * s * m, window) / n - ms * ms).clamp_min(0.0)
    ncc = cov / torch.sqrt((vr + NCC_EPS) * (vs + NCC_EPS))
    return _nan_where_invalid((1.0 - ncc).clamp(0.0, 2.0), valid)


def _offsets(window: int) -> list[tuple[int, int]]:
    r = window // 2
    return [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if (dy, dx) != (0, 0)]


def _shift(x: torch.Tensor, dy: int, dx: int, fill) -> torch.Tensor:
    """(..., H, W) -> out[..., i, j] = x[..., i + dy, j + dx], `fill` where that is off the image."""
    out = torch.full_like(x, fill)
    h, w = x.shape[-2:]
    out[..., max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)] = \
        x[..., max(0, dy):h - max(0, -dy), max(0, dx):w - max(0, -dx)]
    return out


def census_codes(image_grey: torch.Tensor, window: int = DEFAULT_WINDOW) -> torch.Tensor:
    """(H, W) grey -> (H, W) int64 census codes: bit b set where the neighbour at offset b (row-major
    over the window, centre skipped) is darker than the centre; neighbours off the image give 0.
    window^2 - 1 bits must fit in 63 (window <= 7)."""
    window = _check_window(window)
    offsets = _offsets(window)
    if len(offsets) > 63:
        raise InputError(f"census codes: a {window}x{window} window has {len(offsets)} bits, over 63")
    nan = float("nan")  # NaN < x is False
    code = torch.zeros(image_grey.shape, dtype=torch.int64)
    for b, (dy, dx) in enumerate(offsets):
        code |= (_shift(image_grey, dy, dx, nan) < image_grey).to(torch.int64) << b
    return code


_BYTE_POPCOUNT = torch.tensor([i.bit_count() for i in range(256)], dtype=torch.int64)


def _popcount(x: torch.Tensor) -> torch.Tensor:
    """int64 (non-negative, < 2^63) -> the number of set bits, a byte at a time through a table."""
    out = torch.zeros_like(x)
    for k in range(8):
        out += _BYTE_POPCOUNT[(x >> (8 * k)) & 255]
    return out


def cost_census(ref, warped, valid, window: int = DEFAULT_WINDOW) -> torch.Tensor:
    """Census of the window x window neighbourhood of grey, computed on the reference and on each
    warped image (module docstring: why on the warped image), compared per pixel by Hamming
    distance over the bits whose neighbour is valid, then averaged over the valid pixels of a
    window x window box like `cost_ad` (module docstring: why aggregated). ref (C, H, W), warped
    (D, C, H, W), valid (D, H, W) -> (D, H, W) float32 in [0, 1] (the share of differing bits),
    NaN where the centre is invalid."""
    window = _check_window(window)
    r, s = grey(ref), grey(warped)
    valid = torch.as_tensor(valid)
    h, w = s.shape[-2:]
    differ = torch.zeros(s.shape, dtype=torch.uint8)  # counts up to window^2 - 1 <= 255 (window <= 15)
    counted = torch.zeros(s.shape, dtype=torch.uint8)
    if window > 15:
        differ, counted = differ.to(torch.int32), counted.to(torch.int32)
    for dy, dx in _offsets(window):  # one offset at a time: memory of one (D, H, W) bit plane
        # only where the neighbour (y + dy, x + dx) is on the image: elsewhere its bit is unset in
        # both and not counted (the `_shift` of NaN and of False), so nothing is added there
        core = (slice(max(0, -dy), h - max(0, dy)), slice(max(0, -dx), w - max(0, dx)))
        nb = (slice(max(0, dy), h - max(0, -dy)), slice(max(0, dx), w - max(0, -dx)))
        bit_r = r[nb] < r[core]
        bit_s = s[(...,) + nb] < s[(...,) + core]
        ok = valid[(...,) + nb]
        differ[(...,) + core] += (bit_r[None] != bit_s) & ok  # integer counts: exact
        counted[(...,) + core] += ok
    differ, counted = differ.to(torch.float32), counted.to(torch.float32)
    return _window_mean(differ / counted.clamp_min(1.0), valid & (counted > 0), window)


def cost_hamming(ref_codes: torch.Tensor, warped_codes: torch.Tensor, valid: torch.Tensor,
                 window: int = DEFAULT_WINDOW) -> torch.Tensor:
    """The share of differing bits between the reference's census codes (H, W) int64 and codes
    taken from the source's (D, H, W) int64 (`census_codes` of a `window` census), averaged over
    the valid pixels of a window x window box like `cost_census`; valid (D, H, W) -> (D, H, W)
    float32 in [0, 1], NaN where the centre is invalid."""
    window = _check_window(window)
    differ = _popcount(warped_codes ^ ref_codes[None]).to(torch.float32)
    return _window_mean(differ / (window * window - 1), valid, window)


def _census_source(ref, src, k_ref, k_src, ref_to_src, depths, window: int, chunk: int) -> torch.Tensor:
    """`sweep_cost`'s 'census_source': the source's census codes, taken at the source pixel each
    plane point lands in (a nearest-sampled warp of the source's pixel indices: float32 holds
    them exactly below 2^24 pixels), against the reference's codes."""
    _, hs, ws = src.shape
    if hs * ws >= 2 ** 24:
        raise InputError(f"census_source: a {ws}x{hs} source has too many pixels to index in float32")
    ref_codes = census_codes(grey(ref), window)
    src_codes = census_codes(grey(src), window).reshape(-1)
    index = torch.arange(hs * ws, dtype=torch.float32).reshape(1, hs, ws)
    out = []
    for d in depths.split(max(1, int(chunk))):
        at, valid = warp_to_reference(index, k_src, k_ref, ref_to_src, d, tuple(ref.shape[-2:]), mode="nearest")
        out.append(cost_hamming(ref_codes, src_codes[at[:, 0].to(torch.int64)], valid, window))
    return torch.cat(out)


_COST_FNS = {"ad": cost_ad, "ncc": cost_ncc, "census": cost_census}


def sweep_cost(ref, src, k_ref, k_src, ref_to_src, depths, *, cost: str = "census", window: int = DEFAULT_WINDOW,
               chunk: int = DEFAULT_CHUNK) -> torch.Tensor:
    """The cost volume of one source: ref (C, H, W), src (C, Hs, Ws) float32, k_ref, k_src (3, 3),
    ref_to_src (4, 4), depths (D,) metres -> (D, H, W) float32 (lower is better, NaN where the
    source does not see the plane point). cost: 'ad', 'ncc', 'census' (`cost_*`) or
    'census_source' (census codes of the source image, warped with nearest sampling, `cost_hamming`;
    window <= 7).
    The hypotheses go `chunk` at a time through warp and cost."""
    if cost not in COSTS:
        raise InputError(f"cost: expected one of {', '.join(COSTS)}, got {cost!r}")
    ref, src = _image(ref, "ref"), _image(src, "src")
    depths = torch.as_tensor(depths, dtype=torch.float64).reshape(-1)
    if cost == "census_source":
        return _census_source(ref, src, k_ref, k_src, ref_to_src, depths, window, chunk)
    out = []
    for d in depths.split(max(1, int(chunk))):
        warped, valid = warp_to_reference(src, k_src, k_ref, ref_to_src, d, tuple(ref.shape[-2:]), chunk=chunk)
        out.append(_COST_FNS[cost](ref, warped, valid, window))
    return torch.cat(out)


def combine_costs(costs: list[torch.Tensor]) -> torch.Tensor:
    """Several sources' (D, H, W) costs -> their mean over the sources that see each pixel at each
    hypothesis (NaN where none does); summed source by source in list order."""
    if not costs:
        raise InputError("combine_costs: no cost volume")
    total = torch.zeros_like(costs[0])
    count = torch.zeros_like(costs[0])
    for c in costs:
        ok = torch.isfinite(c)
        total += torch.where(ok, c, torch.zeros_like(c))
        count += ok.to(c.dtype)
    return torch.where(count > 0, total / count.clamp_min(1.0), torch.full_like(total, float("nan")))
