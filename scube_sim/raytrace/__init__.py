"""Ray tracing of VoxSplats and meshes with Embree (embreex or open3d) behind one `Tracer`.

`Tracer` hands a scene's Gaussians once to a `TraceCore` (the compiled Embree core in
`compiled.py`, or the NumPy reference walk in `reference.py`); every traceable thing follows
`TraceableScene` (contracts.py).
"""

from .backends import DEFAULT_BACKEND, MeshEngine
from .compiled import CompiledCore
from .compose import nearest_hits
from .contracts import MODES, BoundedScene, HardMode, SoftMode, TraceableScene, TraceCore, TracerBackend, trace_mode
from .hits import Hits, TraceStats
from .reference import ReferenceCore
from .tracer import Tracer

__all__ = ["DEFAULT_BACKEND", "MODES", "BoundedScene", "CompiledCore", "HardMode", "Hits", "MeshEngine",
           "ReferenceCore", "SoftMode", "TraceCore", "TraceStats", "TraceableScene", "Tracer", "TracerBackend",
           "nearest_hits", "trace_mode"]
