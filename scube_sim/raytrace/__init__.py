"""Ray tracing of VoxSplats and meshes with Embree (embreex or open3d) behind one `Tracer`.

`Tracer` builds the proxies once per static scene; the traversal is a `TraceCore` (the NumPy
reference in `reference.py`); every traceable thing follows `TraceableScene` (contracts.py).
"""

from .compose import nearest_hits
from .contracts import BoundedScene, TraceableScene, TraceCore, TracerBackend
from .hits import Hits, TraceStats
from .tracer import DEFAULT_BACKEND, MODES, Tracer

__all__ = ["DEFAULT_BACKEND", "MODES", "BoundedScene", "Hits", "TraceCore", "TraceStats", "TraceableScene", "Tracer",
           "TracerBackend", "nearest_hits"]
