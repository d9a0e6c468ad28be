"""Winner-take-all over a plane-sweep cost volume: each pixel's lowest-cost hypothesis refined by
a parabola to a depth, and its peak ratio as confidence (`winner_take_all_reference` says how).

`winner_take_all` runs the compiled version (`compiled.winner_take_all`: the same operations, the
same bytes) wherever the extension is built, unless `SCUBE_SIM_CORE=reference`; the torch
reference is what it is tested against.

Units: depths in metres along the reference camera's axis; costs in the volume's own units.
"""

from __future__ import annotations

import torch

from ...errors import InputError
from . import compiled
from .sweep import CONF_EPS


def winner_take_all(cost: torch.Tensor, depths) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """cost (D, H, W) (lower is better, NaN: no candidate), depths (D,) metres, monotonic ->
    depth (H, W) float32 metres, best cost (H, W) float32 and confidence (H, W) float32 in [0, 1]
    (`winner_take_all_reference` says how). The compiled version (`compiled.winner_take_all`: the
    same operations, the same bytes) where it is built, unless `SCUBE_SIM_CORE=reference`."""
    return _winner_take_all(cost, depths)[:3]


def _winner_take_all(cost: torch.Tensor, depths):
    """`winner_take_all`'s (depth, best, confidence) and the winning hypothesis (H, W) int64 (the
    first lowest cost, NaN as +inf; 0 where every hypothesis is NaN)."""
    d_count = cost.shape[0]
    depths = torch.as_tensor(depths, dtype=torch.float64).reshape(-1)
    if depths.shape[0] != d_count or d_count < 2:
        raise InputError(f"winner_take_all: cost has {d_count} hypotheses, depths {depths.shape[0]}")
    if cost.dim() == 3 and cost.dtype == torch.float32 and compiled.default_core_name() == "compiled":
        return compiled.winner_take_all(cost, depths)
    depth, best, conf = winner_take_all_reference(cost, depths)
    inf = torch.tensor(float("inf"), dtype=cost.dtype)
    return depth, best, conf, torch.where(torch.isnan(cost), inf, cost).argmin(0)


def winner_take_all_reference(cost: torch.Tensor, depths) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """cost (D, H, W) (lower is better, NaN: no candidate), depths (D,) metres, monotonic ->
    depth (H, W) float32 metres, best cost (H, W) float32 and confidence (H, W) float32 in [0, 1].

    Depth: the lowest-cost hypothesis (the first of equal ones), refined by the parabola through it
    and its two neighbours, in hypothesis index, mapped linearly to inverse depth between the
    neighbours (uniform in 1/depth: the parabola's vertex in 1/depth); the offset is clamped to half
    a step and skipped at the ends, next to a NaN or where the parabola does not open upwards.

    Confidence (peak ratio, Hu and Mordohai 2012's PKRN on local minima): with c1 the best cost and
    c2 the lowest other local minimum (the first of a run of equal costs) more than one hypothesis
    away (where there is none, the curve's highest cost: it rises all the way),
    1 - (c1 + CONF_EPS) / (c2 + CONF_EPS): 0 for a flat curve or a second minimum as good, towards 1
    for one sharp unique minimum. NaN depth and cost, 0 confidence, where every hypothesis is NaN."""
    d_count = cost.shape[0]
    depths = torch.as_tensor(depths, dtype=torch.float64).reshape(-1)
    if depths.shape[0] != d_count or d_count < 2:
        raise InputError(f"winner_take_all: cost has {d_count} hypotheses, depths {depths.shape[0]}")
    inf = torch.tensor(float("inf"), dtype=cost.dtype)
    c = torch.where(torch.isnan(cost), inf, cost)
    k = c.argmin(0)  # (H, W): the first minimum
    best = c.gather(0, k[None])[0]
    found = torch.isfinite(best)
    # parabola through (k - 1, k, k + 1)
    km, kp = (k - 1).clamp(min=0), (k + 1).clamp(max=d_count - 1)
    c_m, c_p = c.gather(0, km[None])[0], c.gather(0, kp[None])[0]
    curv = c_m - 2.0 * best + c_p
    fit = found & (k > 0) & (k < d_count - 1) & torch.isfinite(c_m) & torch.isfinite(c_p) & (curv > 0)
    off = torch.where(fit, 0.5 * (c_m - c_p) / torch.where(fit, curv, torch.ones_like(curv)), torch.zeros_like(curv))
    off = off.clamp(-0.5, 0.5).to(torch.float64)
    inv = 1.0 / depths
    step = torch.where(off >= 0, inv[kp] - inv[k], inv[k] - inv[km])
    depth = 1.0 / (inv[k] + off * step)
    # confidence: the lowest local minimum away from the winner
    left = torch.cat([inf.expand(1, *c.shape[1:]), c[:-1]])
    right = torch.cat([c[1:], inf.expand(1, *c.shape[1:])])
    index = torch.arange(d_count)[:, None, None]
    # a local minimum is the first hypothesis of a run of equal costs (a plateau counts once, so
    # the winner's own flat bottom is not a second minimum)
    other = (c < left) & (c <= right) & torch.isfinite(c) & ((index - k[None]).abs() > 1)
    second = torch.where(other, c, inf).min(0).values
    highest = torch.where(torch.isfinite(c), c, -inf).max(0).values
    second = torch.where(torch.isfinite(second), second, highest)
    conf = 1.0 - (best + CONF_EPS) / (second + CONF_EPS)
    nan = torch.full_like(best, float("nan"))
    return (torch.where(found, depth.to(torch.float32), nan), torch.where(found, best, nan),
            torch.where(found, conf.clamp(0.0, 1.0), torch.zeros_like(conf)))
