"""Shared benchmark helpers: cached scenes, peak-memory probes, timing, result files."""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from scube_sim.memory import peak_mb, reset_peak, rss_mb  # noqa: F401 - the benchmarks' probes

BENCH_DIR = Path(__file__).resolve().parent
CACHE = BENCH_DIR / ".cache"
RESULTS = BENCH_DIR / "results"


def street_voxsplat(voxel_size: float, m: int = 4):
    """The street scene fitted at `voxel_size` (cached on disk: fitting 1e6 Gaussians takes ~10 s)."""
    from scube_sim.fit import FitOptions, fit_voxsplat
    from scube_sim.voxsplat import VoxSplat
    from scube_sim.worlds.street import street_scene

    CACHE.mkdir(exist_ok=True)
    path = CACHE / f"street_{voxel_size:g}_m{m}.npz"
    if path.exists():
        return VoxSplat.load(path)
    mesh = street_scene()
    s = mesh.sample_surface_grid(min(voxel_size / 2, 0.1))
    vs = fit_voxsplat(s["points"], voxel_size, colors=s["colors"], labels=s["labels"], weights=s["weights"],
                      fit=FitOptions(gaussians_per_voxel=m))
    vs.save(path)
    return vs


def timed(fn, repeat: int = 3):
    """Median wall time of `repeat` calls (after one warm-up call) and the last result."""
    out = fn()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out


def best_per_core(fn, repeats: int, cores=("reference", "compiled")) -> tuple[dict, dict]:
    """Run `fn()` `repeats` times under each of the trace cores (`SCUBE_SIM_CORE`), interleaved so
    that load drifts hit both alike: ({core: best seconds}, {core: last result}); the variable is
    restored afterwards."""
    from scube_sim.raytrace import compiled

    before = os.environ.get(compiled.CORE_ENV)
    sec, out = {}, {}
    try:
        for _ in range(repeats):
            for core in cores:
                os.environ[compiled.CORE_ENV] = core
                t = time.perf_counter()
                out[core] = fn()
                sec[core] = min(sec.get(core, np.inf), time.perf_counter() - t)
    finally:
        if before is None:
            os.environ.pop(compiled.CORE_ENV, None)
        else:
            os.environ[compiled.CORE_ENV] = before
    return sec, out


def machine() -> dict:
    from scube_sim.cpus import usable_cpus

    return {"cpus": os.cpu_count(), "usable_cpus": usable_cpus(), "python": platform.python_version(),
            "platform": platform.platform(), "date": time.strftime("%Y-%m-%d %H:%M")}


def write_results(name: str, rows: list[dict], header: list[str], notes: str = "", results: Path = RESULTS) -> Path:
    """<results>/<name>.json (all fields) and <name>.md (the `header` columns); results: bench/results
    by default (experiments/ writes to its own)."""
    results.mkdir(exist_ok=True)
    (results / f"{name}.json").write_text(json.dumps({"machine": machine(), "rows": rows}, indent=1))
    lines = [f"# {name}", "", f"machine: {machine()}", ""]
    if notes:
        lines += [notes, ""]
    lines.append("| " + " | ".join(header) + " |")
    lines.append("|" + "---|" * len(header))
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r.get(h, "")) for h in header) + " |")
    path = results / f"{name}.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _fmt(v) -> str:
    if isinstance(v, float):
        if v != v:
            return "-"
        return f"{v:.3g}" if abs(v) < 1000 else f"{v:,.0f}"
    return str(v)
