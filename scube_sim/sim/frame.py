"""What the simulator hands to hosts and sinks each tick.

Times are seconds (float64) on the host's clock. Poses are (4, 4) float64 *-to-world. A LiDAR
sweep's timestamp is the instant its last ray fires (`t_end`): the sweep covers
[t_end - period, t_end], and a sweep is handed out on the first tick at or after its end.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..boxes import Box


@dataclass
class SensorFrame:
    """One sensor's output in a frame.

    points: LiDAR POINT_DTYPE array in the sensor frame (raw: at each point's fire time;
    compensated: at the sweep's reference instant). pose: sensor-to-world at the reference
    instant (`t_ref`); pose_start / pose_end: at the sweep's first and last fire; t_start, t_end:
    the sweep's span. kind: 'lidar' (cameras will add 'camera')."""

    name: str
    kind: str
    points: np.ndarray
    t_start: float
    t_end: float
    t_ref: float
    pose: np.ndarray
    pose_start: np.ndarray
    pose_end: np.ndarray
    sweep_index: int


@dataclass
class Frame:
    """Everything produced at one tick.

    index: tick counter from 0; time: the tick time; ego_pose: ego-to-world at `time`;
    sensors: name -> list of SensorFrame finished in (previous tick, this tick] (a sensor faster
    than the ticks gives several, a slower one none); boxes: the scene's 3D boxes at `time`
    (static objects and actors, world frame)."""

    index: int
    time: float
    ego_pose: np.ndarray
    sensors: dict[str, list[SensorFrame]] = field(default_factory=dict)
    boxes: list[Box] = field(default_factory=list)

    def sweeps(self) -> list[SensorFrame]:
        """All sensor frames of this tick, ordered by end time then name."""
        out = [s for group in self.sensors.values() for s in group]
        return sorted(out, key=lambda s: (s.t_end, s.name))
