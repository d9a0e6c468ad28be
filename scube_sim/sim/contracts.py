"""The simulator's contracts, written down as Protocols.

- `SimulatedScene`: what the `Simulator` steps and traces. `SimScene` (static parts, actors,
  chunks) is one; `StaticScene` wraps a plain `TraceableScene` (a bare `Tracer`, a list of them).
- `PoseSource`: where the ego is in a self-driven run (`Simulator.run`): `TrajectorySource`,
  `EditedTrajectory`, `CanTrajectory`.

Sinks have their base class in `sinks.base.Sink`.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from ..boxes import Box
from ..raytrace.contracts import TraceableScene
from ..raytrace.hits import Hits


@runtime_checkable
class SimulatedScene(TraceableScene, Protocol):
    """A `TraceableScene` that lives in time.

    time: seconds, the default fire time of rays traced without `times` (the simulator sets it
    to each sweep's end); `update(time, ego_position)` advances to a tick (ego_position (3,)
    float64 world metres, e.g. for loading chunks near the ego); `boxes_at(t)` every actor's box
    at time t (world frame); `trace_world(..., times=None)` takes per-ray fire times (N,) where
    `accepts_times` is True."""

    time: float

    def update(self, time: float, ego_position: np.ndarray | None = None) -> None: ...

    def boxes_at(self, t: float) -> list[Box]: ...

    def trace_world(self, origins, dirs, t_min=0.0, t_max=np.inf, times=None) -> Hits: ...


@runtime_checkable
class PoseSource(Protocol):
    """Ego poses over a time span: `t_start`, `t_end` seconds (`Simulator.run`'s default span);
    `poses_at(times (N,) seconds)` -> (N, 4, 4) float64 ego-to-world poses."""

    @property
    def t_start(self) -> float: ...

    @property
    def t_end(self) -> float: ...

    def poses_at(self, times) -> np.ndarray: ...
