"""Ray tracing of VoxSplats and meshes with Embree (embreex or open3d) behind one `Tracer`."""

from .tracer import DEFAULT_BACKEND, Hits, Tracer

__all__ = ["DEFAULT_BACKEND", "Hits", "Tracer"]
