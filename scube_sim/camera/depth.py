"""LiDAR returns as a camera's depth map, with the returns the camera cannot see removed.

`lidar_depth(points_world, image)` projects world-frame returns into one `CameraImage` (its
`Intrinsics`, OpenCV distortion included, and its ``cam_to_world`` pose) and gives an (H, W)
float32 map of depth along the optical axis (camera z, metres), NaN where no return lands.
Returns behind the camera (z <= `MIN_DEPTH_M`), outside the image, or so far off-axis that the
lens model folds back (`Intrinsics.project`) are dropped. `lidar_depth_index` gives the same map
and, per pixel, the index of the return it holds (-1: none), so a caller can carry per-return
attributes (a ground flag, an intensity) into the image.

Occlusion. The LiDAR sits apart from the camera and a sweep is sparse, so a return the LiDAR saw
on a far surface can land in the camera image inside a nearer object's silhouette, between that
object's own returns. Two rules remove such returns, both deterministic:

1. z-buffer: of the returns in one pixel, only the nearest is kept;
2. window: a pixel's return is dropped if some return in the `window` (rows x columns, centred on
   the pixel; an int k means k x k) is nearer by more than the relative `margin`:
   ``z > (1 + margin) * min(z in window)``;
3. gap: a return is also dropped if it is sandwiched between nearer ones across a vertical gap:
   within `gap_reach` rows above it and within `gap_reach` rows below it (each over `GAP_COLUMNS`
   columns centred on it) lie returns nearer by more than `margin` (gap_reach 0: rule off).

Constants (`DEFAULT_WINDOW` = 7, `DEFAULT_MARGIN` = 0.1) and what they trade: the window must
span the gaps between a near surface's returns in the image to catch what leaks through them:
horizontally a spinning LiDAR's returns are f x (azimuth step) apart (about 2 pixels for KITTI's
HDL-64E in its 1242-pixel camera, 7 for nuScenes' HDL-32E in its 1600-pixel ones), but its scan
lines are f x (beam spacing) apart vertically (about 5 pixels for KITTI, 12 to 30 for nuScenes),
so a 7-pixel window removes far returns within 3 pixels of a near
return and lets through those in the middle of a wide gap between scan lines. A taller window would
remove those too, but also the farther of two ground scan lines whenever both fall in one window
(adjacent ground lines differ in range by a share r x (beam spacing) / (sensor height), more than
10 % beyond about 8 m for nuScenes' HDL-32E), so the window stays square and small, and rule 3
(`DEFAULT_GAP_REACH` = 32 rows, above the widest scan-line gap of the shared logs' cameras, over
`GAP_COLUMNS` = 9 columns, wider than nuScenes' azimuth step)
closes the gaps instead: a far return between a near surface's scan lines has nearer returns both
above and below it, while a ground line has its nearer neighbour only below it (the line above is
farther), so the ground survives. What rule 3 gives up: a far return truly seen through a hole
narrower than the reach (under a vehicle, through foliage) is dropped. The 10 % margin
keeps returns on surfaces seen obliquely (a road's camera depth z changes by a share 3 z / (f h)
over 3 pixel rows: under 10 % up to about 60 m for a camera h = 1.5 m up with f = 1266 px) and
drops returns farther than a near surface by more than that.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..transforms import invert_pose, transform_points
from .frames import CameraImage

DEFAULT_WINDOW = 7
DEFAULT_MARGIN = 0.1
DEFAULT_GAP_REACH = 32
GAP_COLUMNS = 9
MIN_DEPTH_M = 1e-3

__all__ = ["DEFAULT_GAP_REACH", "DEFAULT_MARGIN", "DEFAULT_WINDOW", "GAP_COLUMNS", "MIN_DEPTH_M", "lidar_depth", "lidar_depth_index",
           "min_filter", "project_to_pixels"]


def _window(window) -> tuple[int, int]:
    rows, cols = (window, window) if np.isscalar(window) else tuple(window)
    if int(rows) != rows or int(cols) != cols or rows < 1 or cols < 1 or rows % 2 == 0 or cols % 2 == 0:
        raise InputError(f"window: expected an odd number of pixels >= 1 (or a (rows, columns) pair of them), "
                         f"got {window!r}")
    return int(rows), int(cols)


def project_to_pixels(points_world: np.ndarray, image: CameraImage) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 3) world-frame points -> (kept (M,) int64 indices into the points, flat pixel index
    (M,) int64 = row * W + column, z (M,) float64 camera-z depth) of the points in front of the
    camera (z > MIN_DEPTH_M) whose projection lies in the image (pixel (u, v) spans [u, u + 1))."""
    p = np.asarray(points_world, np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"points_world: expected (N, 3), got {p.shape}")
    intr = image.intrinsics
    cam = transform_points(invert_pose(image.cam_to_world), p)
    front = np.flatnonzero(np.isfinite(cam).all(axis=1) & (cam[:, 2] > MIN_DEPTH_M))
    uv, z = intr.project(cam[front])
    with np.errstate(invalid="ignore"):
        col, row = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        inside = (col >= 0) & (col < intr.width) & (row >= 0) & (row < intr.height)
    flat = row[inside].astype(np.int64) * intr.width + col[inside].astype(np.int64)
    return front[inside], flat, z[inside]


def min_filter(a: np.ndarray, window) -> np.ndarray:
    """(H, W) float -> the minimum over the `window` (rows, columns; odd) centred on each pixel,
    +inf beyond the image's edges (a rectangle's minimum is separable: rows, then columns)."""
    rows, cols = _window(window)
    out = np.asarray(a)
    for axis, k in ((0, rows), (1, cols)):
        if k == 1:
            continue
        r = k // 2
        pad = [(0, 0), (0, 0)]
        pad[axis] = (r, r)
        padded = np.pad(out, pad, constant_values=np.inf)
        n = out.shape[axis]
        m = np.take(padded, np.arange(0, n), axis=axis)
        for d in range(1, k):
            np.minimum(m, np.take(padded, np.arange(d, d + n), axis=axis), out=m)
        out = m
    return out


def _rows_min(a: np.ndarray, reach: int, side: int) -> np.ndarray:
    """(H, W) -> the minimum over rows v + side * 1 .. v + side * reach of each column (+inf
    beyond the image)."""
    h = a.shape[0]
    padded = np.pad(a, ((reach, reach), (0, 0)), constant_values=np.inf)
    out = np.full(a.shape, np.inf)
    for d in range(1, reach + 1):
        s = reach + side * d
        np.minimum(out, padded[s:s + h], out=out)
    return out


def lidar_depth_index(points_world: np.ndarray, image: CameraImage, *, window=DEFAULT_WINDOW,
                      margin: float = DEFAULT_MARGIN, gap_reach: int = DEFAULT_GAP_REACH
                      ) -> tuple[np.ndarray, np.ndarray]:
    """`lidar_depth` and (H, W) int64 the index into `points_world` of the return each pixel
    holds (-1 where none)."""
    if not (np.isfinite(margin) and margin >= 0):
        raise InputError(f"margin: expected a relative depth margin >= 0, got {margin!r}")
    if int(gap_reach) != gap_reach or gap_reach < 0:
        raise InputError(f"gap_reach: expected a number of pixel rows >= 0, got {gap_reach!r}")
    _window(window)
    h, w = image.intrinsics.height, image.intrinsics.width
    kept, flat, z = project_to_pixels(points_world, image)
    order = np.lexsort((z, flat))  # by pixel, nearest first (stable: ties keep the input order)
    fs = flat[order]
    first = order[np.r_[True, fs[1:] != fs[:-1]]] if len(fs) else order
    zbuf = np.full(h * w, np.inf)
    index = np.full(h * w, -1, np.int64)
    zbuf[flat[first]] = z[first]
    index[flat[first]] = kept[first]
    zbuf, index = zbuf.reshape(h, w), index.reshape(h, w)
    hidden = zbuf > (1.0 + margin) * min_filter(zbuf, window)  # inf > inf is False: empty pixels stay empty
    if gap_reach:
        across = min_filter(zbuf, (1, GAP_COLUMNS))
        hidden |= ((zbuf > (1.0 + margin) * _rows_min(across, int(gap_reach), -1))
                   & (zbuf > (1.0 + margin) * _rows_min(across, int(gap_reach), 1)))
    index[hidden] = -1
    depth = np.where(index >= 0, zbuf, np.nan).astype(np.float32)
    return depth, index


def lidar_depth(points_world: np.ndarray, image: CameraImage, *, window=DEFAULT_WINDOW,
                margin: float = DEFAULT_MARGIN, gap_reach: int = DEFAULT_GAP_REACH) -> np.ndarray:
    """(N, 3) float64 world-frame LiDAR returns -> (H, W) float32 camera-z depth in metres of the
    returns `image` sees (NaN where none), occluded returns removed (module docstring: z-buffer per
    pixel; a return farther than its `window`'s nearest by more than `margin` is dropped, and one
    with such nearer returns both within `gap_reach` rows above and below it)."""
    return lidar_depth_index(points_world, image, window=window, margin=margin, gap_reach=gap_reach)[0]
