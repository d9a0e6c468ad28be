"""Semi-global cost aggregation (Hirschmüller 2008) over a plane-sweep cost volume.

A window cost alone decides each pixel on its 7 x 7 patch; where the patch is distorted between
views (the side of a parked car seen from a camera driving past it changes scale and slant), weakly
textured or partly occluded, its curve's minimum is shallow and the peak ratio low. Semi-global
aggregation adds, along several straight paths through the image, the cost of the best path
arriving at each (pixel, hypothesis), with a small penalty `p1` for a one-hypothesis step between
neighbours and a large one `p2` for any larger jump:

    L_r(p, d) = C(p, d) + min(L_r(p - r, d), L_r(p - r, d +- 1) + p1, min_k L_r(p - r, k) + p2)
                - min_k L_r(p - r, k)

and the aggregated cost is the mean of L_r over the paths (4: left, right, up, down; 8 adds the
diagonals). Surfaces whose depth varies smoothly in inverse depth (planes, most of a street) get
support from their neighbours; depth edges cost `p2` once.

Units: the volume's own (census: the share of differing bits, in [0, 1]). NaN entries (a
hypothesis no source sees at that pixel) enter the recursion as `fill` and come back NaN, so the
winner-take-all still ignores them.

Deterministic: each path is a fixed sequence of elementwise operations (no reductions across
threads), the same bytes whatever the thread count.

`semi_global` runs in the compiled sweep (`compiled.semi_global`, `_sweep.cpp`: the same
operations in the same order, the same bytes) where it is built, unless `SCUBE_SIM_CORE=reference`;
`semi_global_reference` is the torch version it is tested against.
"""

from __future__ import annotations

import torch

from ...errors import InputError
from . import compiled

__all__ = ["semi_global", "semi_global_reference"]


def _scan(cost: torch.Tensor, p1: float, p2: torch.Tensor) -> torch.Tensor:
    """cost (B, D, H, W), p2 (B, 1, H, W) per pixel (the penalty into that pixel) -> L (B, D, H, W)
    aggregated along +W (each of the B volumes scanned left to right)."""
    c = cost.permute(3, 0, 1, 2).contiguous()  # (W, B, D, H): each step reads one contiguous slice
    pen = p2.permute(3, 0, 1, 2).contiguous()
    out = torch.empty_like(c)
    prev = c[0]
    out[0] = prev
    step = torch.empty_like(prev)
    for x in range(1, c.shape[0]):
        m = prev.amin(1, keepdim=True)
        # the best neighbour hypothesis (d - 1 or d + 1) plus p1
        step[:, 0] = prev[:, 1]
        step[:, -1] = prev[:, -2]
        torch.minimum(prev[:, :-2], prev[:, 2:], out=step[:, 1:-1])
        best = torch.minimum(torch.minimum(prev, step + p1), m + pen[x])
        prev = out[x]
        torch.add(c[x], best - m, out=prev)
    return out.permute(1, 2, 3, 0)


def _paths(cost: torch.Tensor, p1: float, p2: torch.Tensor) -> torch.Tensor:
    """The sum of L over the +W and -W paths of cost (D, H, W) with p2 (2, 1, H, W) (into each pixel
    from the left, from the right)."""
    agg = _scan(torch.stack([cost, cost.flip(-1)]), p1, torch.stack([p2[0], p2[1].flip(-1)]))
    return agg[0] + agg[1].flip(-1)


def _diagonal(cost: torch.Tensor, shift: int) -> torch.Tensor:
    """Shear (D, H, W) into (D, H, W + H) so that a diagonal becomes a column: row y starts at column
    y (shift 1: the anti-diagonals x + y constant) or H - 1 - y (shift -1: the diagonals x - y
    constant); the cells outside the image are NaN."""
    d, h, w = cost.shape
    out = torch.full((d, h, w + h), float("nan"), dtype=cost.dtype)
    for y in range(h):
        o = y if shift > 0 else h - 1 - y
        out[:, y, o:o + w] = cost[:, y]
    return out


def _undiagonal(sheared: torch.Tensor, shift: int, w: int) -> torch.Tensor:
    h = sheared.shape[1]
    rows = []
    for y in range(h):
        o = y if shift > 0 else h - 1 - y
        rows.append(sheared[:, y, o:o + w])
    return torch.stack(rows, 1)


def _check(cost: torch.Tensor, p1: float, p2: float, paths: int) -> None:
    if paths not in (4, 8):
        raise InputError(f"semi_global: paths must be 4 or 8, got {paths}")
    if not 0 <= p1 <= p2:
        raise InputError(f"semi_global: penalties must satisfy 0 <= p1 <= p2, got p1={p1}, p2={p2}")
    if cost.dim() != 3:
        raise InputError(f"semi_global: cost must be (D, H, W), got shape {tuple(cost.shape)}")


def semi_global(cost: torch.Tensor, p1: float, p2: float, *, paths: int = 4, fill: float = 0.5) -> torch.Tensor:
    """cost (D, H, W) float32 (NaN: no candidate) -> (D, H, W) float32, the mean of the path costs
    L_r over `paths` (4 or 8) directions (module docstring); NaN where the input is NaN. The
    compiled version where it is built and chosen (module docstring), else `semi_global_reference`."""
    _check(cost, p1, p2, paths)
    if cost.dtype == torch.float32 and cost.shape[0] >= 2 and compiled.default_core_name() == "compiled":
        return compiled.semi_global(cost, p1, p2, paths=paths, fill=fill)
    return semi_global_reference(cost, p1, p2, paths=paths, fill=fill)


def semi_global_reference(cost: torch.Tensor, p1: float, p2: float, *, paths: int = 4, fill: float = 0.5
                          ) -> torch.Tensor:
    """`semi_global` in torch: cost (D, H, W) (NaN: no candidate) -> (D, H, W), NaN where the input
    is NaN."""
    _check(cost, p1, p2, paths)
    nan = torch.isnan(cost)
    c = torch.where(nan, torch.full_like(cost, fill), cost)
    _, h, w = c.shape
    pen = torch.full((2, 1, h, w), float(p2))  # into each pixel, forward and backward along a path
    total = _paths(c, p1, pen)
    total = total + _paths(c.transpose(1, 2), p1, pen.transpose(2, 3)).transpose(1, 2)
    if paths == 8:
        for shift in (1, -1):
            # a diagonal path is a row of the sheared volume; sheared padding (NaN) is filled too
            sh = _diagonal(c, shift)
            sh = torch.where(torch.isnan(sh), torch.full_like(sh, fill), sh)
            pen = torch.full((2, 1, sh.shape[1], sh.shape[2]), float(p2))
            agg = _paths(sh.transpose(1, 2), p1, pen.transpose(2, 3)).transpose(1, 2)
            total = total + _undiagonal(agg, shift, w)
    return torch.where(nan, torch.full_like(total, float("nan")), total / paths)
