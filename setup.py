"""The compiled trace core (scube_sim/raytrace/_core.cpp) against Debian's Embree 3 (libembree-dev).

Everything else about the package is in pyproject.toml. The extension is optional: where it cannot
be built (no compiler, no Embree headers) the package still installs, and the tracer says once
that it runs on the NumPy reference walk instead.
"""

from pybind11.setup_helpers import Pybind11Extension, build_ext
from setuptools import setup

core = Pybind11Extension(
    "scube_sim.raytrace._core",
    ["scube_sim/raytrace/_core.cpp"],
    libraries=["embree3"],
    cxx_std=17,
    extra_compile_args=["-O3"],
    optional=True,
)

setup(ext_modules=[core], cmdclass={"build_ext": build_ext})
