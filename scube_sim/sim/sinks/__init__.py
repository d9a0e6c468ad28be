"""Where the simulator's frames go.

- `base`: the `Sink` base class, `RunInfo`, and the `SinkRunner` writer thread (`SinkError`).
- `files`: `FileSink`, per-sweep point-cloud files with JSON-lines manifests.
- `usd`: `UsdSink`, the whole run as one animated USD stage (pxr imported when it opens).
- `can`: `CanFrameSink`, a "frame ready" message per frame on a CAN bus.
- `inprocess`: `CallbackSink` and `QueueSink`, frames to the host's own code.
- `rosbag`: `RosbagSink`, the run as a ROS 2 bag (MCAP storage; rosbags imported when it opens).
- `viewer`: `ViewerSink`, the run as a Foxglove MCAP (protobuf schemas), and a bird's-eye plot of one.
"""

from .base import RunInfo, Sink, SinkError, SinkRunner
from .can import CanFrameSink
from .files import FileSink
from .inprocess import CallbackSink, QueueSink
from .rosbag import RosbagConfig, RosbagSink
from .usd import UsdSink
from .viewer import ViewerConfig, ViewerSink

__all__ = ["Sink", "RunInfo", "SinkRunner", "SinkError", "FileSink", "UsdSink", "CanFrameSink",
           "CallbackSink", "QueueSink", "RosbagSink", "RosbagConfig", "ViewerSink", "ViewerConfig"]
