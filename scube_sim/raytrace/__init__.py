"""Ray tracing of VoxSplats and meshes with Embree (embreex or open3d) behind one `Tracer`.

`Tracer` hands a scene's Gaussians once to a `TraceCore` (the compiled Embree core in
`compiled.py`, or the NumPy reference walk in `reference.py`); every traceable thing follows
`TraceableScene` (contracts.py).
"""

from .backends import DEFAULT_BACKEND
from .compose import nearest_hits
from .contracts import BoundedScene, TraceableScene, TraceCore, TracerBackend
from .hits import Hits, TraceStats
from .tracer import MODES, Tracer

__all__ = ["DEFAULT_BACKEND", "MODES", "BoundedScene", "Hits", "TraceCore", "TraceStats", "TraceableScene", "Tracer",
           "TracerBackend", "nearest_hits"]
