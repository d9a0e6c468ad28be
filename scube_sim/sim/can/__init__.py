"""CAN bus in the loop: ego motion from a vehicle's CAN traffic, and "frame ready" messages out.

- `dbc`: `CanVehicleDecoder` turns python-can `Message`s into speed / steering-wheel angle /
  yaw-rate samples with a cantools DBC (defaults: the 2017 Toyota RAV4 powertrain DBC of opendbc).
- `source`: `CanPoseSource` dead-reckons those samples (`sim.vehicle.DeadReckoner`, a kinematic
  bicycle model) from a live bus or a CAN log, optionally paced in real time; `CanTrajectory`
  makes it a simulator pose source.
- `frame_ready`: the layout of the "frame ready" message that `sim.sinks.CanFrameSink` sends.

cantools and python-can are imported only when a DBC, a bus or a log is used.
"""

from .dbc import RAV4_SPEED, RAV4_STEER, CanVehicleDecoder
from .frame_ready import FRAME_READY_DBC, FRAME_READY_ID, pack_frame_ready, unpack_frame_ready
from .source import CanPoseSource, CanTrajectory

__all__ = [
    "CanVehicleDecoder", "RAV4_SPEED", "RAV4_STEER",
    "CanPoseSource", "CanTrajectory",
    "FRAME_READY_DBC", "FRAME_READY_ID", "pack_frame_ready", "unpack_frame_ready",
]
