"""Several tracers as one scene: the nearest hit over all of them (a static scene built once plus
small per-tick actor scenes, or VoxSplat chunks)."""

from __future__ import annotations

import numpy as np

from .contracts import TraceableScene
from .hits import Hits


def nearest_hits(tracers: list[TraceableScene], origins, dirs, t_min=0.0, t_max=np.inf) -> Hits:
    """Trace world-frame rays (float64 origins (N, 3), dirs (N, 3)) through every tracer and keep
    the nearest hit per ray. Hit points are returned in the world frame."""
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    best = None
    for tr in tracers:
        h = tr.trace_world(o, dirs, t_min, t_max)
        h.points = h.points + tr.origin
        if best is None:
            best = h
            continue
        take = h.hit & (h.t < best.t)
        for name in best.__dataclass_fields__:
            getattr(best, name)[take] = getattr(h, name)[take]
    if best is None:
        best = Hits.empty(o.shape[0])
    return best
