"""Simulator loop benchmarks.

speed: ticks per second for an HDL-64E and an OS1-128 on the default world (the demo's urban
block), as 0.4 m VoxSplat chunks (the scenarios' default) and as its exact mesh, each before the
compiled core (the NumPy walk, meshes and actors on open3d) and after it, and the overhead of the
loop and of the sinks (PCD files + a USD stage with value clips) over bare tracing of the same
sweeps in the same run.
soak: 3 000 ticks of a multi-LiDAR rig with file and USD sinks: the RSS curve's slope, and threads
and open files before and after.
split: where one sweep's time goes on the urban loop (12 moving actors, compiled core): the ego's
poses at the fire times, the Gaussian and mesh tracers, the scene's own work around them (culling
rays per part, moving them into each part's frame, merging hits), and the rest of `Lidar.scan`
(intensity, echoes, drops, noise, points). The minimum over the ticks of each stage.

Run: `python -m bench.bench_sim [--quick] [--only speed|soak|split]`.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from scube_sim.raytrace.compiled import CORE_ENV

from .common import RESULTS, rss_mb, write_results

REPO = Path(__file__).resolve().parents[1]


def _scenario(name, **changes):
    from scube_sim.runs.scenario import load_scenario

    sc, base = load_scenario(REPO / "scenarios" / f"{name}.yaml")
    for k, v in changes.items():
        obj = sc
        *path, last = k.split(".")
        for p in path:
            obj = getattr(obj, p)
        setattr(obj, last, v)
    return sc, base


def speed(ticks: int = 20) -> list[dict]:
    from scube_sim.runs.scenario import SensorSpec, build_run

    rows = []
    work = Path(tempfile.mkdtemp(prefix="scube-bench-sim-"))
    try:
        for rep, core in (("voxsplat", "reference"), ("voxsplat", "compiled"), ("mesh", "reference"),
                          ("mesh", "compiled")):
            # The core of every tracer the scenario builds: 'reference' is the state before the
            # compiled core (the NumPy walk for Gaussians, open3d for the world's and the actors'
            # meshes), 'compiled' after it (Gaussians and meshes on the compiled core).
            os.environ[CORE_ENV] = core
            for preset in ("hdl64e", "os1-128"):
                sc, base = _scenario("urban-loop", **{"scene.representation": rep})
                sc.sensors = [SensorSpec(preset=preset)]
                sc.duration_s = ticks / sc.tick_hz
                out = work / f"{rep}-{core}-{preset}"
                # 1. bare tracing of the same sweeps
                sc.outputs.files, sc.outputs.usd = [], None
                sim, src, t0, t1 = build_run(sc, base, out)
                sensor = sim.sensors[0]
                ends = t0 + np.arange(1, ticks + 1) / sensor.rate_hz
                sim.scene.update(t0, src.poses_at(np.array([t0]))[0][:3, 3])
                t = time.perf_counter()
                for te in ends:
                    sim.scene.update(te, src.poses_at(np.array([te]))[0][:3, 3])
                    sensor.lidar.scan(sim.scene, None, pose_fn=lambda ts: src.poses_at(ts) @ sensor.mount,
                                      t_start=te - sensor.lidar.pattern.period_s)
                bare = (time.perf_counter() - t) / ticks
                # 2. the loop without sinks, and 3. with PCD files and a USD stage (value clips);
                # timed from the first tick on (tick 0 loads the chunks and sweeps nothing)
                per_tick = []
                for files, usd in (([], None), (["pcd"], "run.usdc")):
                    sc.outputs.files, sc.outputs.usd, sc.outputs.usd_clips = files, usd, True
                    sim, src, t0, t1 = build_run(sc, base, out)
                    frames = sim.run(src, t_start=t0, t_end=t0 + ticks / sc.tick_hz, dt=1 / sc.tick_hz)
                    next(frames)
                    t = time.perf_counter()
                    n = sum(1 for _ in frames)
                    per_tick.append((time.perf_counter() - t) / n)
                loop, sinks = per_tick
                rows.append({"scene": f"urban block, {rep}", "core": core,
                             "mesh_engine": "open3d" if core == "reference" else "compiled", "sensor": preset,
                             "ticks": ticks,
                             "bare_s_per_sweep": bare, "loop_s_per_tick": loop, "loop_sinks_s_per_tick": sinks,
                             "ticks_per_s": 1 / sinks, "loop_overhead": loop / bare, "sinks_overhead": sinks / bare,
                             # how many such sensors at 10 Hz fit in one 2-core machine's time
                             "sensors_at_10Hz": 1 / (10 * sinks)})
                print(rows[-1])
    finally:
        os.environ.pop(CORE_ENV, None)
        shutil.rmtree(work, ignore_errors=True)
    return rows


def split(ticks: int = 10) -> list[dict]:
    """Seconds per stage of one sweep, by wrapping the stages' entry points (min over `ticks`)."""
    from scube_sim.raytrace.tracer import Tracer
    from scube_sim.runs.scenario import SensorSpec, build_run

    rows = []
    work = Path(tempfile.mkdtemp(prefix="scube-bench-split-"))
    try:
        os.environ[CORE_ENV] = "compiled"
        for preset in ("hdl64e", "os1-128"):
            sc, base = _scenario("urban-loop")
            sc.sensors = [SensorSpec(preset=preset)]
            sc.duration_s = (ticks + 2) / sc.tick_hz
            sc.outputs.files, sc.outputs.usd = [], None
            sim, src, t0, _ = build_run(sc, base, work)
            scene, sensor = sim.scene, sim.sensors[0]
            lidar = sensor.lidar
            acc: dict[str, float] = {}

            def timed_call(key, fn):
                def run(*a, **k):
                    t = time.perf_counter()
                    out = fn(*a, **k)
                    acc[key] = acc.get(key, 0.0) + time.perf_counter() - t
                    return out
                return run

            def ego(ts):
                return src.poses_at(ts) @ sensor.mount

            scene_trace = scene.trace_world
            tracer_trace = Tracer.trace_world
            scene.trace_world = timed_call("scene", scene_trace)
            Tracer.trace_world = timed_call("tracers", tracer_trace)
            per = []
            try:
                for k in range(ticks + 1):
                    te = t0 + (k + 1) / sensor.rate_hz
                    scene.update(te, src.poses_at(np.array([te]))[0][:3, 3])
                    acc.clear()
                    t = time.perf_counter()
                    lidar.scan(scene, None, pose_fn=timed_call("ego", ego), t_start=te - lidar.pattern.period_s)
                    acc["sweep"] = time.perf_counter() - t
                    if k:  # the first sweep loads the chunks
                        per.append(dict(acc))
            finally:
                Tracer.trace_world = tracer_trace
                del scene.trace_world
            row = {"sensor": preset, "rays": len(lidar.pattern.time), "ticks": ticks}
            stages = {"sweep_s": lambda a: a["sweep"], "ego_poses_s": lambda a: a["ego"],
                      "tracers_s": lambda a: a["tracers"], "scene_glue_s": lambda a: a["scene"] - a["tracers"],
                      "rest_of_scan_s": lambda a: a["sweep"] - a["ego"] - a["scene"]}
            for name, f in stages.items():
                row[name] = min(f(a) for a in per)
            rows.append(row)
            print(row)
    finally:
        os.environ.pop(CORE_ENV, None)
        shutil.rmtree(work, ignore_errors=True)
    return rows


def _fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def soak(ticks: int = 3000) -> list[dict]:
    from rich.progress import Progress

    from scube_sim.runs.scenario import SensorSpec, build_run

    work = Path(tempfile.mkdtemp(prefix="scube-soak-"))
    try:
        sc, base = _scenario("multi-lidar", **{"scene.representation": "mesh"})
        # Three LiDARs at two rates, half resolution: the rig's structure at a soak-friendly cost.
        half = {"pattern": {"columns": 900}}
        sc.sensors = [SensorSpec(preset="vlp16", name="left", overrides=half, phase_s=0.0),
                      SensorSpec(preset="vlp16", name="right", overrides=half, phase_s=0.05),
                      SensorSpec(preset="hdl32e", name="front", overrides={"pattern": {"columns": 542}})]
        sc.duration_s = None
        sc.outputs.files, sc.outputs.usd, sc.outputs.usd_clips = ["bin"], "soak.usdc", True
        threads0, fds0 = threading.active_count(), _fds()
        sim, base_src, t0, t1 = build_run(sc, base, work)
        src = _Looped(base_src)  # drive the world's path again and again: the sensors keep seeing the world
        rss, ticks_done = [], 0
        t = time.perf_counter()
        with Progress() as progress:
            task = progress.add_task("soak", total=ticks)
            for frame in sim.run(src, t_start=t0, t_end=t0 + (ticks - 1) / sc.tick_hz, dt=1 / sc.tick_hz):
                ticks_done += 1
                if ticks_done % 50 == 0:
                    rss.append((ticks_done, rss_mb()))
                progress.advance(task)
        wall = time.perf_counter() - t
        threads1, fds1 = threading.active_count(), _fds()
        x, y = np.array(rss).T
        slope = float(np.polyfit(x, y, 1)[0] * 1000)  # MB per 1000 ticks
        late = y[len(y) // 2:]
        late_slope = float(np.polyfit(x[len(x) // 2:], late, 1)[0] * 1000)
        _plot_rss(x, y, RESULTS / "soak_rss.png")
        disk = sum(p.stat().st_size for p in work.rglob("*") if p.is_file()) / 1e6
        return [{"ticks": ticks_done, "wall_s": wall, "ticks_per_s": ticks_done / wall, "rss_start_MB": float(y[0]),
                 "rss_end_MB": float(y[-1]), "rss_slope_MB_per_1000_ticks": slope,
                 "rss_slope_second_half": late_slope, "threads_before": threads0, "threads_after": threads1,
                 "fds_before": fds0, "fds_after": fds1, "output_MB": disk}]
    finally:
        shutil.rmtree(work, ignore_errors=True)


class _Looped:
    """A `PoseSource` replayed over and over (time modulo its span): an endless drive."""

    def __init__(self, source):
        self.source = source
        self.span = source.t_end - source.t_start
        self.t_start, self.t_end = source.t_start, np.inf

    def poses_at(self, times):
        t = np.atleast_1d(np.asarray(times, np.float64)) - self.source.t_start
        return self.source.poses_at(self.source.t_start + np.mod(t, self.span))


def _plot_rss(x, y, path):
    from scube_sim.viz import pyplot, save_png

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.5), dpi=110)
    ax.plot(x, y, ".-")
    ax.set_xlabel("tick")
    ax.set_ylabel("RSS [MB]")
    ax.set_title("soak: 3 LiDARs, files + USD value clips")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    save_png(fig, path)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer ticks")
    ap.add_argument("--only", choices=("speed", "soak", "split"), default=None)
    args = ap.parse_args()
    if args.only in (None, "speed"):
        rows = speed(10 if args.quick else 20)
        md = write_results("sim_speed", rows, ["scene", "core", "mesh_engine", "sensor", "ticks", "bare_s_per_sweep",
                                               "loop_s_per_tick",
                                               "loop_sinks_s_per_tick", "ticks_per_s", "loop_overhead", "sinks_overhead",
                                               "sensors_at_10Hz"],
                           "bare: LiDAR.scan on the same scene and poses; loop: Simulator.run without sinks; "
                           "loop_sinks: with PCD files and a USD stage with value clips (writer thread). core: the "
                           "tracer core (reference: the NumPy walk for Gaussians and open3d for meshes, the "
                           "'before'; compiled: Gaussians and meshes on the compiled core, the 'after'). "
                           "sensors_at_10Hz: 0.1 s / loop_sinks_s_per_tick.")
        print(md.read_text())
    if args.only in (None, "split"):
        rows = split(5 if args.quick else 10)
        md = write_results("sim_split", rows, ["sensor", "rays", "ticks", "sweep_s", "ego_poses_s", "tracers_s",
                                               "scene_glue_s", "rest_of_scan_s"],
                           "One sweep on the urban loop (12 moving actors, 0.4 m VoxSplat chunks, compiled core), "
                           "minimum over the ticks per stage. ego_poses: the pose source at every distinct fire "
                           "time; tracers: the parts' tracers; scene_glue: the scene's culling, moves into the "
                           "parts' frames and merging; rest_of_scan: intensity, echoes, drops, noise, points.")
        print(md.read_text())
    if args.only in (None, "soak"):
        rows = soak(300 if args.quick else 3000)
        md = write_results("sim_soak", rows, list(rows[0]), "RSS sampled every 50 ticks; slope by least squares.")
        print(md.read_text())


if __name__ == "__main__":
    main()
