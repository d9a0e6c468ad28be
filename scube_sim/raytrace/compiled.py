"""The compiled trace core (`_core.cpp`): one Embree traversal per ray over user-geometry
Gaussians with the exact float64 test inside, multithreaded over rays, the same bytes for any
thread count. The default `TraceCore` wherever the extension was built; `reference.py` is what
it is tested against.

`available()` tells whether it imports; `load_error()` why not. Where it does not, `Tracer` falls
back to the NumPy walk and says so once (`CoreUnavailableWarning`).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass

import numpy as np

from ..cpus import resolve_threads
from ..errors import InputError, ScubeSimError
from .contracts import SceneGaussians, SoftMode, TraceMode
from .hits import Hits, TraceStats

try:
    from . import _core
    _LOAD_ERROR: str | None = None
except ImportError as exc:  # the extension was not built on this install
    _core = None
    _LOAD_ERROR = f"{type(exc).__name__}: {exc}"

_MODE_CODES = {"entry": 0, "max_response": 1, "soft": 2}
CORE_ENV = "SCUBE_SIM_CORE"  # 'compiled' | 'reference' | 'auto' (default): the default core
CORES = ("auto", "compiled", "reference")


class CoreUnavailable(ScubeSimError, RuntimeError):
    """The compiled core was asked for by name and is not built."""


class CoreUnavailableWarning(UserWarning):
    pass


def available() -> bool:
    return _core is not None


def load_error() -> str | None:
    """Why the compiled core does not import (None when it does)."""
    return _LOAD_ERROR


def embree_version() -> str | None:
    return _core.EMBREE_VERSION if _core is not None else None


def threads_for(threads: int) -> int:
    """The extension's thread count for a request: 0 is the process's (`cpus.resolve_threads`:
    SCUBE_SIM_THREADS, else the CPUs the process may use), never the machine's core count."""
    return resolve_threads(int(threads) or None)


def device() -> None:
    """Size the Embree device's BVH build pool before its first scene (`threads_for(0)`); later
    calls change nothing (a process has one device)."""
    if _core is not None:
        _core.set_device_threads(threads_for(0))


_WARNED: set[str] = set()  # the extensions whose absence was said


def choose_core(what: str, built: bool, load_error: str | None, fallback: str) -> str:
    """'compiled' or 'reference' for one of our compiled extensions (`what`, e.g. 'tracer core'):
    `SCUBE_SIM_CORE` if set ('compiled' where the extension is not `built`: CoreUnavailable), else
    the compiled one where built, else the reference, said once per extension with `fallback`
    (what then runs instead, and how to build it)."""
    name = os.environ.get(CORE_ENV, "auto").strip().lower() or "auto"
    if name not in CORES:
        raise InputError(f"{CORE_ENV}: expected one of {CORES}, got {name!r}")
    if name == "compiled" and not built:
        raise CoreUnavailable(f"{CORE_ENV}=compiled: the compiled {what} is not built ({load_error})")
    if name != "auto":
        return name
    if built:
        return "compiled"
    if what not in _WARNED:
        _WARNED.add(what)
        warnings.warn(f"scube-sim: the compiled {what} is not built ({load_error}); {fallback}",
                      CoreUnavailableWarning, stacklevel=3)
    return "reference"


def default_core_name() -> str:
    """The core a `Tracer` uses when none is given (`choose_core`)."""
    return choose_core("tracer core", available(), _LOAD_ERROR,
                       "tracing runs on the NumPy reference walk, several times slower. Install libembree-dev and "
                       "a C++ compiler, then reinstall the package.")


def carve_misses(origin: np.ndarray, direction: np.ndarray, reach: np.ndarray, confidence: np.ndarray,
                 grid_origin: np.ndarray, voxel_size: float, step: float, batch: int, candidates: np.ndarray,
                 threads: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The voxels rays cross short of their ends, in the compiled core (the fusion's free-space walk).

    Each ray from `origin` (3,) metres along unit `direction` (R, 3) is sampled at (s + 0.5) * `step`
    up to `reach` (R,) metres; a sample's voxel is floor((p - grid_origin) / voxel_size), a run of
    samples in one voxel counted once, looked up in the sorted `candidates` (K,) int64 voxel keys
    (`voxsplat.voxel_keys`). Returns per candidate (hit (K,) bool, summed `confidence` (K,) float64 of
    the rays that crossed it, their count (K,) float64). Sums are added per batch of `batch` rays in
    batch order, so the bytes do not depend on `threads` (0: `threads_for`)."""
    if _core is None:
        raise CoreUnavailable(f"the compiled core is not built ({_LOAD_ERROR})")
    n = len(candidates)
    hit, conf_sum, conf_cnt = np.zeros(n, bool), np.zeros(n), np.zeros(n)
    if n and len(direction):
        ok = _core.carve_misses(np.asarray(origin, np.float64), np.ascontiguousarray(direction, np.float64),
                                np.ascontiguousarray(reach, np.float64), np.ascontiguousarray(confidence, np.float64),
                                np.asarray(grid_origin, np.float64), float(voxel_size), float(step), int(batch),
                                np.ascontiguousarray(candidates, np.int64), conf_sum, conf_cnt, hit, threads_for(threads))
        if not ok:
            raise InputError("voxel indices beyond +-2^20: the scene is too large for this voxel size")
    return hit, conf_sum, conf_cnt


def voxel_first_hit(origins: np.ndarray, dirs: np.ndarray, grid_origin: np.ndarray, voxel_size: float,
                    lo: np.ndarray, dims: np.ndarray, keys: np.ndarray, order: np.ndarray, block_distance: np.ndarray,
                    max_t: float, index: np.ndarray, t_hit: np.ndarray) -> None:
    """The first voxel of a sparse grid each ray enters, in the compiled core (`model.nn.voxel_rays`).

    origins, dirs (R, 3) float64 metres in the grid's frame; grid_origin (3,) metres, voxel_size
    metres; lo (3,), dims (3,) int64 the grid's low corner and size in voxels; keys (V,) int64 the
    voxels' sorted linear keys and order (V,) their rows; block_distance: the chessboard distance
    in blocks to the nearest occupied block (the empty-space skip). Writes index (R,) int64 (-1:
    none within max_t) and t_hit (R,) float64 (inf: none) in place."""
    if _core is None:
        raise CoreUnavailable(f"the compiled core is not built ({_LOAD_ERROR})")
    _core.voxel_first_hit(np.ascontiguousarray(origins, np.float64), np.ascontiguousarray(dirs, np.float64),
                          grid_origin, float(voxel_size), lo, dims, keys, order, block_distance, float(max_t),
                          index, t_hit, threads_for(0))


@dataclass
class CompiledScene:
    """The core's BVH and what the hits are filled from. lo, hi (3,): the search box (the k-sigma
    bounds). `handle` answers every mode; a scene prepared for soft mode holds instead a
    `soft_handle` whose boxes end where each Gaussian's response reaches `soft_alpha_min`, and
    builds `handle` only if a hard mode is asked."""

    scene: SceneGaussians
    lo: np.ndarray
    hi: np.ndarray
    handle: object = None
    soft_handle: object = None

    def handle_for(self, mode: TraceMode):
        """The BVH that answers `mode` exactly (soft boxes only for soft mode at an alpha floor
        at or above theirs), built on first use."""
        soft = self.soft_handle
        if soft is not None and isinstance(mode, SoftMode) and mode.alpha_min >= soft.alpha_min:
            return soft
        if self.handle is None:
            self.handle = _build(self.scene, 0.0)
        return self.handle


def _build(scene: SceneGaussians, alpha_min: float, morton: bool = True):
    """The extension's scene; morton=False stores the Gaussians as given (benchmarks only)."""
    g = scene.gaussians
    c64 = [np.ascontiguousarray(x, np.float64) for x in (g.means, g.quats, g.scales, g.opacities)]
    device()
    return _core.GaussianScene(*c64, float(scene.k), float(scene.pad), float(alpha_min), bool(morton))


class CompiledCore:
    """The compiled `TraceCore`: one Embree traversal per ray with the exact test inside.

    threads: the extension's threads (0: `threads_for`, the CPUs the process may use); k_buffer: soft contributions gathered per
    traversal (3DGRT's k-buffer: a small one re-traverses more, and re-tests every Gaussian it
    straddles); max_iterations: soft re-traversals per ray at most."""

    name = "compiled"

    def __init__(self, threads: int = 0, k_buffer: int = 256, max_iterations: int = 1000):
        if int(threads) < 0:
            raise InputError(f"threads: expected 0 (all usable CPUs) or a positive count, got {threads}")
        if int(k_buffer) < 1:
            raise InputError(f"k_buffer: expected at least 1, got {k_buffer}")
        if int(max_iterations) < 1:
            raise InputError(f"max_iterations: expected at least 1, got {max_iterations}")
        self.threads, self.k_buffer, self.max_iterations = int(threads), int(k_buffer), int(max_iterations)
        if _core is None:
            raise CoreUnavailable(f"the compiled tracer core is not built ({_LOAD_ERROR}); install libembree-dev "
                                  "and a C++ compiler, then reinstall scube-sim, or use core='reference'")

    def prepare(self, scene: SceneGaussians) -> CompiledScene:
        soft = scene.soft_alpha_min is not None and scene.soft_alpha_min > 0
        handle = _build(scene, scene.soft_alpha_min if soft else 0.0)
        # Attributes the hits copy, in the dtypes the extension reads without a copy per call.
        scene.voxel = np.ascontiguousarray(scene.voxel, np.int64)
        scene.labels = np.ascontiguousarray(scene.labels, np.int16)
        scene.colors = np.ascontiguousarray(scene.colors, np.float32)
        lo, hi = (np.array(b, np.float64) for b in handle.bounds())
        # The search box reaches beyond the padded boxes, so a clipped ray never starts inside a
        # box it cannot then leave.
        return CompiledScene(scene, lo - 2.0 * scene.pad, hi + 2.0 * scene.pad,
                             handle=None if soft else handle, soft_handle=handle if soft else None)

    def trace(self, prepared: CompiledScene, mode: TraceMode, o, d, tmin, tmax, stats: TraceStats) -> Hits:
        n = o.shape[0]
        # Every element is written by the extension, misses included (as `Hits.empty`).
        out = Hits(hit=np.empty(n, bool), t=np.empty(n), points=np.empty((n, 3)), normals=np.empty((n, 3), np.float32),
                   gaussian=np.empty(n, np.int64), voxel=np.empty(n, np.int64), face=np.full(n, -1, np.int64),
                   label=np.empty(n, np.int16), instance=np.zeros(n, np.int32), color=np.empty((n, 3), np.float32),
                   alpha=np.empty(n, np.float32), reflectance=np.full(n, np.nan, np.float32),
                   observed=np.ones(n, np.uint8), confidence=np.ones(n, np.float32))
        s = prepared.scene
        soft = mode if isinstance(mode, SoftMode) else SoftMode()  # a hard mode reads none of these
        f64 = [np.ascontiguousarray(x, np.float64) for x in (o, d, tmin, tmax, prepared.lo, prepared.hi)]
        casts, tests, unfinished = _core.trace(
            prepared.handle_for(mode), _MODE_CODES[mode.name], *f64, s.voxel, s.labels, s.colors,
            out.hit, out.t, out.points, out.normals, out.gaussian, out.voxel, out.label, out.color, out.alpha,
            float(soft.min_transmittance), float(soft.alpha_min), float(soft.hit_alpha),
            self.k_buffer, self.max_iterations, threads_for(self.threads))
        stats.casts += 1
        stats.rays_cast += int(casts)
        stats.exact_tests += int(tests)
        stats.unfinished += int(unfinished)
        return out
