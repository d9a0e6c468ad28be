"""The tracer's engines, as trimesh loops its ray tests over its engines: the compiled core and
the NumPy reference walk on both Embree backends. Every analytic test runs on each.

The compiled core is required: where it does not import the tests fail, unless
SCUBE_SIM_ALLOW_NO_CORE=1 (a user who cannot build it), which skips its cases with the reason."""

from __future__ import annotations

import os

import pytest

from scube_sim.raytrace import compiled

ENGINES = {
    "compiled": {"core": "compiled"},
    "reference-open3d": {"core": "reference", "backend": "open3d"},
    "reference-embreex": {"core": "reference", "backend": "embreex"},
}
ALLOW_NO_CORE = os.environ.get("SCUBE_SIM_ALLOW_NO_CORE", "") == "1"


def engine_kw(name: str) -> dict:
    """Tracer keyword arguments of an engine (skips the compiled one where allowed to be absent)."""
    if name == "compiled" and not compiled.available() and ALLOW_NO_CORE:
        pytest.skip(f"SCUBE_SIM_ALLOW_NO_CORE=1 and the compiled core is not built: {compiled.load_error()}")
    return dict(ENGINES[name])


def backend_kw(name: str) -> dict:
    """Tracer keyword arguments of a mesh engine (skips the compiled one where allowed to be absent)."""
    if name == "compiled":
        engine_kw("compiled")
    return {"backend": name}
