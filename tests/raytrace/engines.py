"""The tracer's engines, as trimesh loops its ray tests over its engines: the compiled core and
the NumPy reference walk on both Embree backends. Every analytic test runs on each.

The compiled core is required: where it does not import the tests fail, unless
SCUBE_SIM_ALLOW_NO_CORE=1 (a user who cannot build it), which skips its cases with the reason."""

from __future__ import annotations

import os

import pytest

from scube_sim.raytrace import CompiledCore, MeshEngine, ReferenceCore, compiled

ENGINES = ("compiled", "reference-open3d", "reference-embreex")
ALLOW_NO_CORE = os.environ.get("SCUBE_SIM_ALLOW_NO_CORE", "") == "1"


def require_compiled() -> None:
    """Skip where SCUBE_SIM_ALLOW_NO_CORE=1 and the compiled core is not built; else nothing."""
    if not compiled.available() and ALLOW_NO_CORE:
        pytest.skip(f"SCUBE_SIM_ALLOW_NO_CORE=1 and the compiled core is not built: {compiled.load_error()}")


def core_of(name: str, proxy: str = "octahedron", **compiled_settings):
    """The `TraceCore` of an engine of ENGINES: the reference walk with `proxy` on its backend,
    or the compiled core with `compiled_settings` (it has no proxies)."""
    if name == "compiled":
        require_compiled()
        return CompiledCore(**compiled_settings)
    return ReferenceCore(name.removeprefix("reference-"), proxy)


def mesh_engine(name: str, threads: int = 0) -> MeshEngine:
    """A mesh engine on the backend `name` (skips the compiled one where allowed to be absent)."""
    if name == "compiled":
        require_compiled()
    return MeshEngine(name, threads)
