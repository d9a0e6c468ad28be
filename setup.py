"""The compiled trace core (scube_sim/raytrace/_core.cpp) against Embree 4 where its headers are
found (Debian 13's libembree-dev), else Embree 3 (Debian 12's); the compiled plane sweep of the
stereo (scube_sim/reconstruct/stereo/_sweep.cpp), which needs nothing but a C++17 compiler.

EMBREE_INCLUDE_DIR / EMBREE_LIBRARY_DIR point the build at another Embree (searched first; the
library directory also goes into the extension's run path). Everything else about the package is
in pyproject.toml. The extension is optional: where it cannot be built (no compiler, no Embree
headers) the package still installs, and the tracer says once that it runs on the NumPy
reference walk instead (the stereo, on its torch reference path).
"""

import os
from pathlib import Path

from pybind11.setup_helpers import Pybind11Extension, build_ext
from setuptools import setup

include_dirs = [d for d in (os.environ.get("EMBREE_INCLUDE_DIR"),) if d]
library_dirs = [d for d in (os.environ.get("EMBREE_LIBRARY_DIR"),) if d]
embree4 = any(Path(d, "embree4", "rtcore.h").exists() for d in include_dirs + ["/usr/include", "/usr/local/include"])

core = Pybind11Extension(
    "scube_sim.raytrace._core",
    ["scube_sim/raytrace/_core.cpp"],
    include_dirs=include_dirs,
    library_dirs=library_dirs,
    runtime_library_dirs=library_dirs,
    libraries=["embree4" if embree4 else "embree3"],
    define_macros=[("SCUBE_EMBREE4", "1")] if embree4 else [],
    cxx_std=17,
    extra_compile_args=["-O3", "-ffp-contract=off"],
    optional=True,
)

# -fno-trapping-math: lets the compiler vectorise the sweep's branch-free selects (no value changes)
sweep = Pybind11Extension(
    "scube_sim.reconstruct.stereo._sweep",
    ["scube_sim/reconstruct/stereo/_sweep.cpp"],
    cxx_std=17,
    extra_compile_args=["-O3", "-ffp-contract=off", "-fno-trapping-math"],
    optional=True,
)

setup(ext_modules=[core, sweep], cmdclass={"build_ext": build_ext})
