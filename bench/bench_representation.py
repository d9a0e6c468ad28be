"""The representation's own error: a LiDAR sweep on the ground-truth VoxSplat of a world against
the same sweep on the world's exact mesh, same poses, same rays (the first row of the
speed/accuracy study). Voxel sizes 0.4, 0.2, 0.1 m; M = 1 and 4 Gaussians per voxel; both hard
depth definitions; two world styles.

The VoxSplats cover a 51.2 m x 51.2 m region of the chunk around the ego (the fine levels of the
whole chunk would hold ~13 M Gaussians, beyond this machine's memory for the proxies); only rays
whose mesh return lies inside that region (shrunk by 0.5 m), or that return nothing, are compared.

Run: `python -m bench.bench_representation [--quick]`.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from scube_sim.lidar import Lidar, load_lidar_config
from scube_sim.raytrace.tracer import Tracer
from scube_sim.transforms import invert_pose, transform_points
from scube_sim.worlds.generator import WorldConfig, generate_world
from scube_sim.worlds.groundtruth import gt_voxsplat

from .common import RESULTS, write_results

REGION = (np.array([-10.24, -25.6, -3.23]), np.array([40.96, 25.6, 40.0]))
SCENARIOS = ("urban-block", "suburban")


def run(quick: bool = False) -> list[dict]:
    from pathlib import Path

    from rich.progress import Progress

    repo = Path(__file__).resolve().parents[1]
    sizes = (0.4, 0.2) if quick else (0.4, 0.2, 0.1)
    ms = (1, 4)
    cfg = load_lidar_config("waymo-top")
    # Geometry only: no noise, no quantisation, no drops (the same on both sides anyway).
    cfg.noise.range_sigma_m = 0.0
    cfg.noise.quantization_m = 0.0
    cfg.drop.max_incidence_deg = 90.0
    lidar = Lidar(cfg)
    rows = []
    with Progress() as progress:
        task = progress.add_task("representation error", total=len(SCENARIOS) * len(sizes) * len(ms))
        for name in SCENARIOS:
            world = generate_world(WorldConfig.from_yaml(repo / "scenarios" / f"{name}.yaml"))
            mesh = world.mesh_at(0.0)
            c2w = world.ego_pose_at(0.0)
            pose_w = lidar.sensor_pose(c2w)
            pose_c = invert_pose(c2w) @ pose_w
            ref = lidar.scan(Tracer(mesh), pose_w)
            img_ref = ref.range_image()
            # Rays whose mesh return lies in the region (in the chunk frame), or that return nothing.
            pts_c = transform_points(pose_c, ref.xyz().astype(np.float64))
            inside = np.all((pts_c >= REGION[0] + 0.5) & (pts_c < REGION[1] - 0.5), axis=1)
            keep_img = np.isnan(img_ref)
            rows_of = _row_of_ring(ref)
            keep_img[rows_of[ref.points["ring"][inside]], ref.points["column"][inside]] = True
            for vsz in sizes:
                for m in ms:
                    progress.update(task, description=f"{name}: {vsz:g} m, M={m}")
                    t = time.perf_counter()
                    vs = gt_voxsplat(mesh, c2w, vsz, gaussians_per_voxel=m, region=REGION)
                    fit_s = time.perf_counter() - t
                    for mode in ("entry", "max_response"):
                        t = time.perf_counter()
                        tracer = Tracer(vs, mode)
                        build_s = time.perf_counter() - t
                        img = lidar.scan(tracer, pose_c).range_image()
                        a, b = img_ref[keep_img], img[keep_img]
                        both = np.isfinite(a) & np.isfinite(b)
                        err = np.abs(a - b)[both]
                        rows.append({
                            "scene": name, "voxel_m": vsz, "M": m, "mode": mode, "gaussians": vs.num_gaussians,
                            "core": tracer.core_name, "fit_s": fit_s, "build_s": build_s, "rays": int(keep_img.sum()),
                            "median_err_cm": float(np.median(err) * 100), "p90_err_cm": float(np.percentile(err, 90) * 100),
                            "hit_agreement": float(np.mean(np.isfinite(a) == np.isfinite(b))),
                            "missed": int(np.sum(np.isfinite(a) & ~np.isfinite(b))),
                            "extra": int(np.sum(~np.isfinite(a) & np.isfinite(b))),
                        })
                        del tracer
                    del vs
                    progress.advance(task)
    return rows


def _row_of_ring(sweep):
    row = np.empty(sweep.channels, np.int64)
    row[np.argsort(-sweep.ring_elevation_deg, kind="stable")] = np.arange(sweep.channels)
    return row


def plot(rows, path):
    from scube_sim.viz import pyplot

    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), dpi=110)
    for ax, key, label in ((axes[0], "median_err_cm", "median |range error| [cm]"),
                           (axes[1], "p90_err_cm", "p90 |range error| [cm]")):
        for scene, ls in zip(SCENARIOS, ("-", "--")):
            for mode, marker in (("entry", "o"), ("max_response", "s")):
                for m, color in ((1, "tab:orange"), (4, "tab:blue")):
                    pts = sorted((r["voxel_m"], r[key]) for r in rows
                                 if r["scene"] == scene and r["mode"] == mode and r["M"] == m)
                    if pts:
                        x, y = zip(*pts)
                        ax.plot(x, y, ls, marker=marker, color=color, label=f"{scene}, {mode}, M={m}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("voxel size [m]")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, which="both")
    axes[1].legend(fontsize=7)
    fig.suptitle("Ground-truth VoxSplat vs exact mesh, Waymo-TOP-like sweep, same rays")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="0.4 and 0.2 m only")
    args = ap.parse_args()
    rows = run(args.quick)
    header = ["scene", "voxel_m", "M", "mode", "gaussians", "core", "fit_s", "build_s", "rays", "median_err_cm",
              "p90_err_cm", "hit_agreement", "missed", "extra"]
    md = write_results("representation", rows, header,
                       "Waymo-TOP-like preset without noise, quantisation or drops; the mesh sweep is the reference. "
                       "missed: mesh returns the VoxSplat misses; extra: VoxSplat returns where the mesh has none.")
    plot(rows, RESULTS / "representation.png")
    print(md.read_text())


if __name__ == "__main__":
    main()
