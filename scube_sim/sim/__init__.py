"""The simulator engine: sensors on an ego in a scene, stepping in time, frames out to sinks.
Scenario files, replay and batches drive it from `scube_sim.runs`.

- `Simulator` (`simulator`): host-driven `step(t, ego_pose)` or self-driven `run(source)`;
  `LidarSensor` places a LiDAR model on the rig. Each tick gives a `Frame` (`frame`).
- `SimScene` (`scene`): static `Part`s, moving actors traced as instances, `ChunkSet`s of
  VoxSplat chunks loaded near the ego; `StaticScene` wraps a bare `Tracer`.
- Pose sources (`sources`, `can`): `TrajectorySource`, `EditedTrajectory`, `HeldPoses`,
  `CanPoseSource` / `CanTrajectory`; the vehicle model in `vehicle`.
- Sinks (`sinks`): files, a USD stage, CAN "frame ready" messages, in-process callbacks.
- The contracts between them (`contracts`): `SimulatedScene`, `PoseSource`; sinks derive from
  `sinks.Sink`.

pxr, cantools and python-can are imported only when a USD stage, a DBC or a bus is used.
"""

from .can import CanPoseSource, CanTrajectory
from .contracts import PoseSource, SimulatedScene
from .frame import Frame, SensorFrame
from .scene import ChunkSet, ChunkSpec, Part, SimScene, StaticScene
from .simulator import LidarSensor, Simulator
from .sinks import CallbackSink, CanFrameSink, FileSink, QueueSink, RunInfo, Sink, SinkError, SinkRunner, UsdSink
from .sources import EditedTrajectory, HeldPoses, TrajectorySource, track_pose_fn
from .vehicle import DeadReckoner

__all__ = [
    "Simulator", "LidarSensor", "Frame", "SensorFrame",
    "SimulatedScene", "PoseSource",
    "SimScene", "StaticScene", "Part", "ChunkSet", "ChunkSpec",
    "TrajectorySource", "EditedTrajectory", "HeldPoses", "track_pose_fn",
    "CanPoseSource", "CanTrajectory", "DeadReckoner",
    "Sink", "RunInfo", "SinkRunner", "SinkError", "FileSink", "UsdSink", "CanFrameSink", "CallbackSink",
    "QueueSink",
]
