"""The LiDAR-build knobs against real sweeps: what each one buys and costs.

Three studies, each a VoxSplat built from real LiDAR and traced on the rays of a real sweep:
- nuScenes, same pose (build from the keyframe sweep, replay it): the representation's floor;
- KITTI raw 0 -> 2 (build from frame 0, moving objects carved with frame 1; replay frame 2 at its
  ICP pose; static rays only): the novel-pose replay users run;
- Argoverse 2 0 -> 1 (build from sweep 0, both VLP-32C; replay sweep 1 of the upper one as
  measured, per-point timing with the 200 Hz poses).
Per row: median / p90 |range error|, hit agreement, Gaussians, build time. The default row is the
`scube-sim build` default; each other row changes one knob. Needs ../shared/data (skips if absent).

Run: `python -m bench.bench_fidelity [--quick]`.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

from scube_sim.datasets import open_dataset
from scube_sim.raytrace.tracer import Tracer
from scube_sim.realdata.build import BuildOptions, build_from_dataset
from scube_sim.realdata.fidelity import compare, moving_rays, real_rays, simulate_rays

from .common import RESULTS, write_results

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

STUDIES = {
    "nuScenes same pose": dict(name="nuscenes", path="nuscenes-mmdet3d-demo", build=[0], carve=[], test=0,
                               sensor=None, raw=False, static=None),
    "KITTI raw 0->2 static": dict(name="kitti_raw", path="kitti-raw-2011_09_26-udacity", build=[0], carve=[1],
                                  test=2, sensor=None, raw=False, static=[0, 1]),
    "AV2 0->1 up_lidar raw": dict(name="argoverse2", path="argoverse2-sensor-log-7fab2350", build=[0], carve=[],
                                  test=1, sensor="up_lidar", raw=True, static=None),
}

# knob label -> (BuildOptions changes, tracer mode)
KNOBS = {
    "default": ({}, "max_response"),
    "tracer depth: entry": ({}, "entry"),
    "no range-image mesh (points + patches)": ({"mesh": False}, "max_response"),
    "mesh edge <= 0.1 r": ({"mesh_max_edge_rel": 0.1}, "max_response"),
    "mesh edge <= 0.3 r": ({"mesh_max_edge_rel": 0.3}, "max_response"),
    "every return adds its patch": ({"all_points": True}, "max_response"),
    "patch sigma cap 0.1 m": ({"max_patch_sigma": 0.1}, "max_response"),
    "voxel 0.2 m": ({"voxel_size": 0.2}, "max_response"),
    "M = 1": ({"gaussians_per_voxel": 1}, "max_response"),
}
QUICK = ("default", "no range-image mesh (points + patches)", "mesh edge <= 0.1 r")


def run(quick: bool = False) -> list[dict]:
    from rich.progress import Progress

    rows = []
    knobs = {k: v for k, v in KNOBS.items() if not quick or k in QUICK}
    with Progress() as bar:
        task = bar.add_task("fidelity knobs", total=len(STUDIES) * len(knobs))
        for study, st in STUDIES.items():
            root = DATA / st["path"]
            if not root.is_dir():
                print(f"skipping {study}: {root} is absent")
                bar.advance(task, len(knobs))
                continue
            ds = open_dataset(st["name"], root)
            smp = ds[st["test"]]
            sweep = smp.sweep(st["sensor"])
            sweep = sweep.raw() if st["raw"] else sweep
            rays = real_rays(sweep)
            mask = ~moving_rays(ds, sweep, rays, st["static"], [sweep.sensor]) if st["static"] else None
            config = smp.lidars[sweep.sensor].config
            base = BuildOptions(samples=st["build"], carve_with=st["carve"], color=False)
            for label, (change, mode) in knobs.items():
                opts = replace(base, **change)
                t0 = time.perf_counter()
                vs, rep, _ = build_from_dataset(ds, opts)
                t_build = time.perf_counter() - t0
                tracer = Tracer(vs, mode=mode)
                t1 = time.perf_counter()
                sim = simulate_rays(tracer, config, rays, sweep)
                t_trace = time.perf_counter() - t1
                m = compare(rays, sim, mask=mask)
                rows.append({"study": study, "knob": label, "median_cm": 100 * m["median_abs_m"],
                             "p90_cm": 100 * m["p90_abs_m"], "hit_agreement_pct": 100 * m["hit_agreement"],
                             "fscore_5cm": m["fscore_5cm"], "gaussians": rep.gaussians, "build_s": t_build,
                             "trace_s": t_trace, "rays": m["rays"]})
                bar.advance(task)
                del vs, tracer
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="three knobs only")
    args = ap.parse_args()
    rows = run(args.quick)
    header = ["study", "knob", "median_cm", "p90_cm", "hit_agreement_pct", "fscore_5cm", "gaussians", "build_s",
              "trace_s"]
    path = write_results("fidelity", rows, header, notes=__doc__.split("\n\n")[1].strip())
    print(path.read_text())
    if rows:
        plot(rows, RESULTS / "fidelity.png")


def plot(rows: list[dict], path: Path) -> None:
    """p90 against hit agreement per study: the trade the knobs move along."""
    from scube_sim.viz import pyplot, save_png

    plt = pyplot()
    studies = list(dict.fromkeys(r["study"] for r in rows))
    fig, axes = plt.subplots(1, len(studies), figsize=(5.5 * len(studies), 4.6), dpi=110, squeeze=False)
    for ax, study in zip(axes[0], studies):
        sub = [r for r in rows if r["study"] == study]
        for r in sub:
            ax.scatter(r["hit_agreement_pct"], r["p90_cm"], s=30 + 60 * (r["knob"] == "default"),
                       c="C3" if r["knob"] == "default" else "C0")
            ax.annotate(r["knob"], (r["hit_agreement_pct"], r["p90_cm"]), fontsize=6, xytext=(3, 2),
                        textcoords="offset points")
        ax.set_xlabel("hit agreement [%]")
        ax.set_ylabel("p90 |range error| [cm]")
        ax.set_title(study, fontsize=9)
        ax.grid(alpha=0.3)
    fig.suptitle("LiDAR-built VoxSplats: build knobs (red: default); lower right is better", fontsize=10)
    fig.tight_layout()
    save_png(fig, path)


if __name__ == "__main__":
    main()
