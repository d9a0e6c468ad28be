"""Step 9 of `mvs`: the gaps between confident pixels of a depth map filled along rows and columns
where the two ends agree (or lie on one plane with the pixels beyond them). Depths in metres along
the camera's z, NaN where none; confidences in [0, 1].
"""

from __future__ import annotations

import numpy as np

__all__ = ["fill_gaps"]


def _fill_rows(depth: np.ndarray, conf: np.ndarray, max_gap: int, tol: float,
               sure_above: float = 0.0, coplanar: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of each row: the depth interpolated (in inverse depth) between the nearest confident
    pixels (confidence above `sure_above`) left and right of it, and the smaller of their
    confidences, where both exist, lie at most `max_gap` + 1 apart and agree within `tol`, or (with
    `coplanar`) where the line through them in (column, inverse depth), extended `coplanar` times
    their distance (at least 2 pixels) beyond each, meets confident pixels within `tol` of their
    depth; NaN and 0 elsewhere (confident pixels included)."""
    h, w = depth.shape
    cols = np.broadcast_to(np.arange(w), (h, w))
    sure = conf > sure_above
    left = np.maximum.accumulate(np.where(sure, cols, -1), axis=1)
    right = np.minimum.accumulate(np.where(sure, cols, w)[:, ::-1], axis=1)[:, ::-1]
    ok = ~sure & (left >= 0) & (right < w) & (right - left <= max_gap + 1)
    rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
    li, ri = np.where(ok, left, 0), np.where(ok, right, 0)
    z0, z1 = depth[rows, li], depth[rows, ri]
    agree = np.abs(z0 - z1) <= tol * np.minimum(z0, z1)
    if coplanar is not None:
        span = np.maximum(ri - li, 1)
        reach = np.maximum(2, (coplanar * span).astype(np.int64))
        lo, hi = li - reach, ri + reach
        inside = (lo >= 0) & (hi < w)
        lo, hi = np.clip(lo, 0, w - 1), np.clip(hi, 0, w - 1)
        zl, zh = depth[rows, lo], depth[rows, hi]
        with np.errstate(divide="ignore", invalid="ignore"):
            slope = (1.0 / z1 - 1.0 / z0) / span  # inverse depth per pixel
            pl, ph = 1.0 / (1.0 / z0 - slope * reach), 1.0 / (1.0 / z1 + slope * reach)
            agree |= (inside & sure[rows, lo] & sure[rows, hi] & (pl > 0) & (ph > 0)
                      & (np.abs(pl - zl) <= tol * zl) & (np.abs(ph - zh) <= tol * zh))
    ok &= agree
    t = (cols - li) / np.maximum(ri - li, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        filled = 1.0 / ((1 - t) / z0 + t / z1)
    c = np.minimum(conf[rows, li], conf[rows, ri])
    return np.where(ok, filled, np.nan).astype(np.float32), np.where(ok, c, 0).astype(np.float32)


def fill_gaps(depth: np.ndarray, conf: np.ndarray, max_gap_px: int, tol: float,
              allowed: np.ndarray | None = None, sure_above: float = 0.0,
              coplanar: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Step 9 (module docstring): (H, W) depth (metres, NaN where none) and confidence with the
    unsure pixels (confidence at most `sure_above`: 0, or a weak pixel's cap) of `allowed` (H, W)
    bool (default all) that a row or column gap of at most `max_gap_px` pixels fills (its ends
    agreeing, or with `coplanar` in line with the pixels beyond them: `_fill_rows`), each with the
    smaller of its ends' confidences (the mean of the row's and the column's where both fill it);
    confident pixels keep theirs."""
    if max_gap_px < 1:
        return depth, conf
    dr, cr = _fill_rows(depth, conf, max_gap_px, tol, sure_above, coplanar)
    dc, cc = (a.T for a in _fill_rows(depth.T, conf.T, max_gap_px, tol, sure_above, coplanar))
    both = np.isfinite(dr) & np.isfinite(dc)
    d = np.where(both, 0.5 * (dr + dc), np.where(np.isfinite(dr), dr, dc))
    c = np.where(both, 0.5 * (cr + cc), np.where(np.isfinite(dr), cr, cc))
    take = np.isfinite(d) & (conf <= sure_above) & (True if allowed is None else allowed)
    return (np.where(take, d, depth).astype(np.float32), np.where(take, c, conf).astype(np.float32))
