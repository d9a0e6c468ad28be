"""Tracer benchmark: the compiled core against raw Embree first hit on the source mesh and
against the NumPy reference walk, all in one process on the same rays.

- Scenes: the street scene fitted at 0.4, 0.2 and 0.1 m voxels (M = 4: 0.26, 1.03 and 4.3 M
  Gaussians) and the demo world at 0.2 m (0.90 M), each beside its source mesh.
- Sensors: a full HDL-64E sweep (133 k rays) and an OS1-128 at 2048 columns (262 k rays).
- Compiled core: build time and peak memory; both hard depth modes at 1 and 2 threads; the whole
  `Lidar.scan` (HDL-64E, with every effect of the preset); x_mesh = sweep time / raw Embree first
  hit on the scene's source mesh (the street's, or the demo world's cropped to the fitted region;
  the same rays; open3d multi-threaded for 2 threads, embreex for 1). The compiled core's own
  mesh engine (worlds and actors) is timed beside them ("raw compiled").
- Exactness: rays whose hit differs (> 1 um) from an exhaustive listing of every proxy crossing
  (open3d list_intersections over the reference's octahedra, each crossing tested exactly), for
  both cores.
- Reference walk (open3d, octahedra) on the 0.3 M and 1 M scenes: its build and sweeps, for the
  before / after ratio.
- Soft mode on the shipped third-party splats (VLP-16 and HDL-64E rays), both cores, the
  compiled core's k-buffer at 16 and 64 against its default 256, and its soft boxes (each
  Gaussian bounded where its response reaches soft_alpha_min) against k-sigma boxes, and its
  Morton storage order against the file's order.

Run: `make bench` (all benchmarks) or `python -m bench.bench_tracer [--quick]` (no 3.7 M scene).
"""

from __future__ import annotations

import argparse
import functools
import time
from unittest import mock

import numpy as np
from rich.progress import Progress

from scube_sim.lidar.config import load_lidar_config
from scube_sim.lidar.model import Lidar
from scube_sim.raytrace import CompiledCore, HardMode, MeshEngine, ReferenceCore, Tracer, compiled, reference
from scube_sim.raytrace import gaussian_math as gm
from scube_sim.raytrace.backends import BACKENDS
from scube_sim.worlds.street import street_scene

from .common import CACHE, RESULTS, peak_mb, reset_peak, rss_mb, street_voxsplat, timed, write_results

SENSORS = {"HDL-64E": ("hdl64e", None), "OS1-128x2048": ("os1-128", 2048)}
MODES = ("entry", "max_response")
THREADS = (1, 2)


def sensor_rays(name: str, pose: np.ndarray):
    preset, columns = SENSORS[name]
    cfg = load_lidar_config(preset)
    if columns:
        cfg.pattern.columns = columns
    pat = Lidar(cfg).pattern
    o = pose[:3, :3] @ pat.offsets.T
    return (o.T + pose[:3, 3]), pat.directions @ pose[:3, :3].T, cfg.range.max_m


def compare(h, ref):
    both = h.hit & ref.hit
    err = np.abs(h.t[both] - ref.t[both])
    return {
        "median_err_cm": float(np.median(err) * 100) if err.size else float("nan"),
        "p90_err_cm": float(np.percentile(err, 90) * 100) if err.size else float("nan"),
        "hit_agreement": float(np.mean(h.hit == ref.hit)),
    }


def listed_nearest(tr: Tracer, o, d, rmax) -> np.ndarray:
    """The nearest entry hit per ray (world-frame rays) from an exhaustive listing of every proxy
    crossing of a reference tracer built on open3d (list_intersections), each tested exactly."""
    ol = o - tr.origin
    n = len(o)
    t_lo, t_hi = gm.clip_to_box(ol, d, np.zeros(n), np.full(n, rmax), tr.prepared.lo, tr.prepared.hi)
    act = np.nonzero(t_hi >= t_lo)[0]
    t0 = np.where(np.isfinite(t_lo), t_lo, 0.0)
    start = ol + t0[:, None] * d
    best = np.full(n, np.inf)
    pg = tr.prepared
    for r, _, prim in pg.backend.all_hits(start[act].astype(np.float32), d[act].astype(np.float32), (t_hi - t0)[act]):
        ri, g = reference.expand(pg, act[r], prim // pg.faces_per_proxy)
        ts, d2, half = reference.exact(pg, ri, g, ol, d, tr.stats)
        ok = d2 <= tr.scene_gaussians.k**2
        np.minimum.at(best, ri[ok], np.maximum(ts - half, 0.0)[ok])
    return np.where(best <= rmax, best, np.inf)


def rays_off(h, want) -> int:
    with np.errstate(invalid="ignore"):  # inf - inf where one side misses: counted by the first test
        return int(((h.hit != np.isfinite(want)) | (h.hit & (np.abs(h.t - want) > 1e-6))).sum())


def demo_scene():
    """The demo's VoxSplat (the default world at 0.2 m; cached like the street scenes) and its
    source mesh in the same (chunk) frame, cropped to the fitted region."""
    from scube_sim.mesh import TriangleMesh
    from scube_sim.runs.demo import DEFAULT_WORLD, REGION
    from scube_sim.transforms import invert_pose, transform_points
    from scube_sim.voxsplat import VoxSplat
    from scube_sim.worlds.generator import generate_world
    from scube_sim.worlds.groundtruth import gt_voxsplat

    CACHE.mkdir(exist_ok=True)
    path = CACHE / "demo_0.2.npz"
    w = generate_world(DEFAULT_WORLD)
    mesh, chunk_to_world = w.mesh_at(0.0), w.ego_pose_at(0.0)
    if path.exists():
        vs = VoxSplat.load(path)
    else:
        vs = gt_voxsplat(mesh, chunk_to_world, 0.2, region=REGION)
        vs.save(path)
    v = transform_points(invert_pose(chunk_to_world), mesh.vertices + mesh.origin)
    c = v[mesh.faces].mean(axis=1)
    keep = np.all((c >= REGION[0]) & (c <= REGION[1]), axis=1)
    cropped = TriangleMesh(v, mesh.faces[keep], mesh.labels[keep], mesh.instances[keep])
    return vs, cropped


def build(vs, **kw):
    base = rss_mb()
    can_peak = reset_peak()
    t = time.perf_counter()
    tr = Tracer(vs, **kw)
    sec = time.perf_counter() - t
    return tr, sec, (peak_mb() - base) if can_peak else float("nan")


def run(quick: bool = False) -> list[dict]:
    voxel_sizes = (0.4, 0.2) if quick else (0.4, 0.2, 0.1)
    mesh = street_scene()
    pose = np.eye(4)
    pose[:3, 3] = [0.0, -2.0, 1.8]
    rays = {s: sensor_rays(s, pose) for s in SENSORS}
    rows = []
    # The practical limit: raw Embree first hit on the mesh itself, same rays, same process.
    mesh_ref, mesh_time = {}, {}
    demo_vs, demo_mesh = demo_scene()
    demo_pose = Lidar(load_lidar_config("hdl64e")).sensor_pose(np.eye(4))  # the HDL-64E's mount at T
    demo_rays = {"HDL-64E": sensor_rays("HDL-64E", demo_pose)}
    for label, m, m_rays in (("street", mesh, rays), ("demo world", demo_mesh, demo_rays)):
        for backend in BACKENDS:
            mtr = Tracer(m, core=MeshEngine(backend))
            for s, (o, d, rmax) in m_rays.items():
                o32, d32, far = o.astype(np.float32), d.astype(np.float32), np.full(len(o), rmax, np.float32)
                sec, _ = timed(lambda: mtr._backend.first_hit(o32, d32, far))
                mesh_time[label, backend, s] = sec
                mesh_ref[label, s] = mtr.trace_world(o, d, 0.0, rmax)
                rows.append({"scene": f"{label} mesh ({m.num_faces} tris)", "gaussians": 0, "core": f"raw {backend}",
                             "mode": "mesh first hit", "threads": 1 if backend == "embreex" else 2, "sensor": s,
                             "rays": len(o), "sweep_s": sec, "Mrays_s": len(o) / sec / 1e6, "x_mesh": 1.0})
    scenes = [(f"street {v:g} m", v) for v in voxel_sizes] + [("demo world 0.2 m", None)]
    with Progress() as progress:
        task = progress.add_task("tracer benchmark", total=len(scenes))
        for name, vsz in scenes:
            vs = street_voxsplat(vsz) if vsz is not None else demo_vs
            n = vs.num_gaussians
            progress.update(task, description=f"{name}: {n / 1e6:.2f} M Gaussians")
            street = vsz is not None
            label = "street" if street else "demo world"
            scan_pose = pose if street else demo_pose
            scene_rays = rays if street else demo_rays
            tr, build_s, peak = build(vs, core=CompiledCore())
            base = {"scene": name, "gaussians": n, "core": "compiled", "build_s": build_s,
                    "build_s_per_M": build_s / (n / 1e6), "peak_MB_per_M": peak / (n / 1e6)}
            sweeps = {}
            for threads in THREADS:
                tr.core.threads = threads
                for mode in MODES:
                    tr.mode = mode
                    for s, (o, d, rmax) in scene_rays.items():
                        sec, h = timed(lambda: tr.trace_world(o, d, 0.0, rmax))
                        sweeps[threads, mode, s] = h
                        raw = mesh_time[label, "open3d" if threads > 1 else "embreex", s]
                        row = {**base, "mode": mode, "threads": threads, "sensor": s, "rays": len(o), "sweep_s": sec,
                               "Mrays_s": len(o) / sec / 1e6, "x_mesh": sec / raw}
                        row.update(compare(h, mesh_ref[label, s]))
                        if threads == 2 and mode == "entry" and s == "HDL-64E":
                            lidar = Lidar(load_lidar_config("hdl64e"))
                            row["scan_s"], _ = timed(lambda: lidar.scan(tr, scan_pose, seed=0))
                        rows.append(row)
            same = all(sweeps[1, m, s].t.tobytes() == sweeps[2, m, s].t.tobytes() for m in MODES for s in scene_rays)
            rows[-1]["threads_bitwise_equal"] = same
            tr = None  # free the BVH before the next build
            if vsz in (0.4, 0.2) or not street:
                # The reference walk (open3d, octahedra): the old path, and the exhaustive listing.
                ref, rbuild, rpeak = build(vs, core=ReferenceCore("open3d"))
                o, d, rmax = scene_rays["HDL-64E"]
                want = listed_nearest(ref, o, d, rmax)
                for mode in MODES:
                    ref.mode = mode
                    sec, h = timed(lambda: ref.trace_world(o, d, 0.0, rmax), repeat=1)
                    comp = sweeps[2, mode, "HDL-64E"]
                    row = {"scene": name, "gaussians": n, "core": "reference (open3d)", "mode": mode, "threads": 2,
                           "sensor": "HDL-64E", "rays": len(o), "build_s": rbuild, "build_s_per_M": rbuild / (n / 1e6),
                           "peak_MB_per_M": rpeak / (n / 1e6), "sweep_s": sec, "Mrays_s": len(o) / sec / 1e6,
                           "x_mesh": sec / mesh_time[label, "open3d", "HDL-64E"]}
                    if mode == "entry":
                        row["rays_off_exhaustive"] = rays_off(h, want)
                        for r in rows:
                            if (r["scene"], r["core"], r["mode"], r["threads"], r.get("sensor")) == (
                                    name, "compiled", "entry", 2, "HDL-64E"):
                                r["rays_off_exhaustive"] = rays_off(comp, want)
                    rows.append(row)
                ref = None
            progress.advance(task)
    return rows


def soft_rows() -> list[dict]:
    """Soft mode on the two third-party splat files (a VLP-16 and an HDL-64E beside the scene),
    the compiled core (k-buffer 16) and the reference (open3d lists every crossing at once)."""
    import os
    from pathlib import Path

    from scube_sim.io.ply3dgs import read_3dgs_ply

    data = Path(os.environ.get("SCUBE_SIM_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    rows = []
    for fname in ("donut_mip-splatting_fused.ply", "inria3dgs_iteration_7000_point_cloud.ply"):
        path = data / "gaussian-splat-ply" / fname
        if not path.exists():
            continue
        g = read_3dgs_ply(path)
        centre = np.median(g.means, axis=0)
        extent = float(np.percentile(np.linalg.norm(g.means - centre, axis=1), 90))
        for sensor in ("vlp16", "hdl64e"):
            pat = Lidar(load_lidar_config(sensor)).pattern
            o = np.broadcast_to(centre - np.array([2.0 * extent, 0, 0]), pat.directions.shape) + g.origin
            d = pat.directions
            hits = {}
            for kb in (16, 64):  # the k-buffer's trade (the default, 256, is the "compiled" row)
                tr = Tracer(g, "soft", core=CompiledCore(k_buffer=kb))
                sec, _ = timed(lambda: tr.trace_world(o, d, 0.0, 10 * extent))
                rows.append({"scene": fname, "gaussians": len(g), "core": f"compiled, k-buffer {kb}", "mode": "soft",
                             "threads": 2, "sensor": sensor, "rays": len(d), "sweep_s": sec,
                             "Mrays_s": len(d) / sec / 1e6})
            # Without the soft boxes (each Gaussian bounded where its response reaches
            # soft_alpha_min): a tracer built for a hard mode answers soft on k-sigma boxes.
            tr = Tracer(g, HardMode("entry", opacity_floor=1.0 / 255.0), core="compiled")
            tr.mode = "soft"
            sec, _ = timed(lambda: tr.trace_world(o, d, 0.0, 10 * extent))
            rows.append({"scene": fname, "gaussians": len(g), "core": "compiled, k-sigma boxes", "mode": "soft",
                         "threads": 2, "sensor": sensor, "rays": len(d), "sweep_s": sec, "Mrays_s": len(d) / sec / 1e6})
            # The storage order: as the file lists them, against the core's Morton order (the
            # "compiled" row); the same answer, measured in tests/raytrace/test_core.py.
            with mock.patch.object(compiled, "_build", functools.partial(compiled._build, morton=False)):
                tr = Tracer(g, mode="soft", core="compiled")
            sec, _ = timed(lambda: tr.trace_world(o, d, 0.0, 10 * extent))
            rows.append({"scene": fname, "gaussians": len(g), "core": "compiled, file order", "mode": "soft",
                         "threads": 2, "sensor": sensor, "rays": len(d), "sweep_s": sec, "Mrays_s": len(d) / sec / 1e6})
            for core in ("compiled", "reference"):
                t = time.perf_counter()
                tr = Tracer(g, "soft", core=CompiledCore() if core == "compiled" else ReferenceCore("open3d"))
                build_s = time.perf_counter() - t
                sec, h = timed(lambda: tr.trace_world(o, d, 0.0, 10 * extent), repeat=1 if core == "reference" else 3)
                hits[core] = h
                rows.append({"scene": fname, "gaussians": len(g), "core": core, "mode": "soft", "threads": 2,
                             "sensor": sensor, "rays": len(d), "build_s": build_s, "sweep_s": sec,
                             "Mrays_s": len(d) / sec / 1e6, "hits": int(h.hit.sum())})
            a, b = hits["compiled"], hits["reference"]
            both = a.hit & b.hit
            rows[-2]["soft_max_depth_diff_vs_reference_m"] = float(np.abs(a.t[both] - b.t[both]).max()) if both.any() else 0.0
            rows[-2]["hit_agreement"] = float(np.mean(a.hit == b.hit))
    return rows


def plot(rows, path):
    from scube_sim.viz import pyplot

    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), dpi=110)
    for ax, mode in zip(axes, MODES):
        for core, threads, ls in (("compiled", 2, "-"), ("compiled", 1, ":"), ("reference (open3d)", 2, "--")):
            pts = sorted((r["gaussians"], r["sweep_s"]) for r in rows
                         if r["mode"] == mode and r["core"] == core and r.get("threads") == threads
                         and r.get("sensor") == "HDL-64E" and r["scene"].startswith("street"))
            if pts:
                x, y = zip(*pts)
                ax.plot(x, y, ls, marker="o", label=f"{core}, {threads} thread{'s' if threads > 1 else ''}")
        for backend, ls in (("open3d", "-"), ("embreex", ":")):
            mesh = [r["sweep_s"] for r in rows if r["core"] == f"raw {backend}" and r["sensor"] == "HDL-64E"
                    and r["scene"].startswith("street")]
            ax.axhline(mesh[0], color="k", ls=ls, lw=0.8, label=f"raw {backend} first hit on the street mesh")
        ax.axhline(0.05, color="r", lw=1, label="0.05 s (trace budget at 10 Hz)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("Gaussians (street scene)")
        ax.set_ylabel("HDL-64E sweep [s] (133 k rays)")
        ax.set_title(f"depth: {mode}")
        ax.grid(alpha=0.3, which="both")
    axes[1].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="no 3.7 M Gaussian scene")
    args = ap.parse_args()
    if not compiled.available():
        raise SystemExit(f"bench_tracer: the compiled core is not built ({compiled.load_error()})")
    rows = run(args.quick) + soft_rows()
    header = ["scene", "gaussians", "core", "mode", "threads", "sensor", "rays", "build_s_per_M", "peak_MB_per_M",
              "sweep_s", "Mrays_s", "x_mesh", "scan_s", "rays_off_exhaustive", "threads_bitwise_equal",
              "median_err_cm", "p90_err_cm", "hit_agreement", "soft_max_depth_diff_vs_reference_m"]
    notes = ("sweep_s: median of 3 `Tracer.trace_world` calls on all rays of one sweep (1 for the reference). "
             "scan_s: the whole `Lidar.scan` of the HDL-64E preset (tracing, intensity, drop, noise, points). "
             "x_mesh: sweep time / raw Embree first hit on the scene's source mesh, same rays, this run (open3d, "
             "multi-threaded, for 2 threads; embreex, 1 thread, for 1). peak_MB_per_M: peak RSS growth during "
             "the build per million Gaussians. rays_off_exhaustive: rays whose hit differs (> 1 um) from an "
             "exhaustive listing of every proxy crossing, each tested exactly. threads_bitwise_equal: 1- and "
             "2-thread ranges of every sweep byte-identical. Errors: |range| against the mesh where both hit "
             f"(the representation's own error). Embree {compiled.embree_version()}.")
    md = write_results("tracer", rows, header, notes)
    plot(rows, RESULTS / "tracer.png")
    print(md.read_text())


if __name__ == "__main__":
    main()
