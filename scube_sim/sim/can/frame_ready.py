"""The simulator's "frame ready" CAN message: its default layout, as bytes and as a DBC.

A host (or the bus's other nodes) reads it with `unpack_frame_ready` or any DBC tool loading
`FRAME_READY_DBC`; `sinks.can.CanFrameSink` sends it.
"""

from __future__ import annotations

import struct

FRAME_READY_ID = 0x5F0

#: The default "frame ready" layout as a DBC (load with ``cantools.database.load_string``).
#: 8 data bytes, little-endian (Intel): bytes 0-1 COUNTER uint16 (0, 1, 2, ... rolling over after
#: 65535), byte 2 SWEEPS uint8 (LiDAR sweeps in the frame, saturating at 255), byte 3 reserved
#: (0), bytes 4-7 TIME_MS uint32 (frame time in ms on the simulator clock, rounded, wrapping
#: after 2**32 ms = 49.7 days).
FRAME_READY_DBC = """VERSION ""

NS_ :

BS_:

BU_: SCUBE_SIM

BO_ 1520 SCUBE_FRAME_READY: 8 SCUBE_SIM
 SG_ COUNTER : 0|16@1+ (1,0) [0|65535] "" Vector__XXX
 SG_ SWEEPS : 16|8@1+ (1,0) [0|255] "" Vector__XXX
 SG_ RESERVED : 24|8@1+ (1,0) [0|255] "" Vector__XXX
 SG_ TIME_MS : 32|32@1+ (1,0) [0|4294967295] "ms" Vector__XXX

CM_ BO_ 1520 "scube_sim: one simulator frame is ready";
"""

_LAYOUT = struct.Struct("<HBBI")


def pack_frame_ready(counter: int, sweeps: int, time_ms: int) -> bytes:
    """8 bytes of the default layout (see `FRAME_READY_DBC`); counter and time wrap, sweeps
    saturate."""
    return _LAYOUT.pack(int(counter) & 0xFFFF, min(max(int(sweeps), 0), 255), 0,
                        int(time_ms) & 0xFFFFFFFF)


def unpack_frame_ready(data: bytes) -> tuple[int, int, int]:
    """(counter, sweeps, time_ms) from 8 bytes of the default layout."""
    counter, sweeps, _reserved, time_ms = _LAYOUT.unpack(bytes(data[:8]))
    return counter, sweeps, time_ms
