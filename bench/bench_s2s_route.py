"""Long routes converted chunk by chunk (issue 13): the seams between converted chunks and the
sweep-to-sweep consistency along the route, beside the same for ground-truth VoxSplat chunks.

A straight urban world long enough for three chunks (`worlds.groundtruth.chunk_frames`, 96 m
apart, so consecutive 102.4 m chunks overlap by 6.4 m). Each chunk is converted from the rig held
at its origin at the instant the ego passes it (`sim.scenario.route_stops`, as `scene.frames.route`
does), the moving actors' voxels cut out; the ground-truth VoxSplat is fitted to the static mesh
in the same chunk frames (0.4 m).

Seams: a geometric HDL-64E on the ego where it crosses the middle of each overlap sweeps each of
the two chunks alone; over the rays whose returns from both lie in the overlap (within 3.2 m of
its middle plane, the most both chunks cover), the range difference between the chunks (median,
p90). The same surface seen from two chunks should give the same range: the ground truth's
difference is its voxelisation noise, the converter's shows how differently it filled the same
place from two viewpoints.

Along the route: a sweep every `--step` metres through all chunks at once (nearest hit wins, as
`ChunkSet` traces them), against the static mesh: median |range error| per sweep, and its change
between consecutive sweeps at the seams against elsewhere. Plot: docs/s2s_route.png.

Not part of `make bench` (minutes of CPU). Run: `python -m bench.bench_s2s_route [--step 4]`
Results: bench/results/s2s_route_seams.{json,md}, s2s_route_sweeps.json.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from rich.progress import track

from scube_sim.converter.eval.sensor_to_sensor import geometric_lidar
from scube_sim.converter.pipeline import Converter
from scube_sim.raytrace.tracer import Tracer
from scube_sim.runs.scenario import route_stops
from scube_sim.sim.converted import remove_boxes, scene_part
from scube_sim.sim.scene import Part, SimScene
from scube_sim.transforms import invert_pose, transform_points
from scube_sim.worlds.dataset import render_frames
from scube_sim.worlds.generator import WorldConfig, generate_world
from scube_sim.worlds.groundtruth import CHUNK_CORNER, CHUNK_SIZE, gt_voxsplat

from .common import BENCH_DIR, write_results

REPO = BENCH_DIR.parent
SPACING = 96.0
HALF_OVERLAP = 0.5 * (CHUNK_SIZE - SPACING)  # 3.2 m


def _ego_at_distance(world, s: float) -> np.ndarray:
    """The ego pose where it has driven `s` metres along its path (nearest sample)."""
    pos = np.asarray(world.ego_poses)[:, :3, 3]
    run = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos[:, :2], axis=0), axis=1))])
    return np.asarray(world.ego_poses[int(np.argmin(np.abs(run - s)))], np.float64)


def _range_img(lidar, scene, pose):
    sweep = lidar.scan(scene, pose)
    return sweep.range_image(), sweep


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--step", type=float, default=4.0, help="metres between sweeps along the route")
    ap.add_argument("--profile", default="cpu")
    args = ap.parse_args(argv)
    wcfg = WorldConfig(style="urban", seed=args.seed, layout="straight", length_m=330, ego_speed_mps=10,
                       duration_s=26)
    world = generate_world(wcfg)
    stops = route_stops(world, SPACING)
    conv = Converter(args.profile)
    lidar = geometric_lidar("hdl64e")
    actors = world.actors
    converted, truth = [], []
    for i, (t, pose) in enumerate(track(stops, description="chunks")):
        frames = render_frames(world, "waymo-5", t, ego_pose=pose)
        vs = conv.convert(frames, seed=0, sky=False).scene
        vs, _ = remove_boxes(vs, [a.box_at(t) for a in actors])
        converted.append(scene_part(vs, name=f"converted{i}"))
        truth.append(scene_part(gt_voxsplat(world.static, pose, 0.4), name=f"truth{i}", mode="entry"))
    mesh = Part(Tracer(world.static), name="mesh")

    # --- seams -------------------------------------------------------------------------------
    seams = []
    for i in range(len(stops) - 1):
        c2w = stops[i][1]
        mid = CHUNK_CORNER[0] + CHUNK_SIZE - HALF_OVERLAP
        ego = c2w.copy()
        ego[:3, 3] = c2w[:3, :3] @ np.array([mid, 0.0, 0.0]) + c2w[:3, 3]
        pose = lidar.sensor_pose(ego)
        for kind, parts in (("ground-truth VoxSplat", truth), ("converted", converted)):
            a, sa = _range_img(lidar, SimScene(static=[parts[i]]), pose)
            b, sb = _range_img(lidar, SimScene(static=[parts[i + 1]]), pose)
            m, _ = _range_img(lidar, SimScene(static=[mesh]), pose)
            # returns of both in the overlap slab (chunk i's x within HALF_OVERLAP of `mid`)
            to_chunk = invert_pose(c2w) @ pose
            xa = _x_image(sa, to_chunk, a.shape)
            xb = _x_image(sb, to_chunk, b.shape)
            both = np.isfinite(a) & np.isfinite(b) & (np.abs(xa - mid) <= HALF_OVERLAP) & (np.abs(xb - mid) <= HALF_OVERLAP)
            d = np.abs(a - b)[both]
            ea, eb = np.abs(a - m)[both & np.isfinite(m)], np.abs(b - m)[both & np.isfinite(m)]
            seams.append({"seam": f"{i} to {i + 1}", "scene": kind, "rays": int(both.sum()),
                          "median_between_chunks_m": round(float(np.median(d)), 3) if d.size else None,
                          "p90_between_chunks_m": round(float(np.percentile(d, 90)), 3) if d.size else None,
                          "median_vs_mesh_first_m": round(float(np.median(ea)), 3) if ea.size else None,
                          "median_vs_mesh_second_m": round(float(np.median(eb)), 3) if eb.size else None})
            print(seams[-1], flush=True)
    write_results("s2s_route_seams", seams, list(seams[0]),
                  notes=f"urban straight world seed {args.seed}, {len(stops)} chunks {SPACING:g} m apart (overlap "
                        f"{CHUNK_SIZE - SPACING:.1f} m); HDL-64E at the middle of each overlap")

    # --- along the route ---------------------------------------------------------------------
    # distances along the ego's path, which starts at the first chunk's origin
    s0 = 5.0
    s1 = SPACING * (len(stops) - 1) + CHUNK_SIZE + CHUNK_CORNER[0] - 5.0
    rows = []
    scenes = {"ground-truth VoxSplat": SimScene(static=truth), "converted": SimScene(static=converted)}
    mesh_scene = SimScene(static=[mesh])
    for s in track(np.arange(s0, s1, args.step), description="route"):
        pose = lidar.sensor_pose(_ego_at_distance(world, float(s)))
        m, sm = _range_img(lidar, mesh_scene, pose)
        row = {"s_m": float(s)}
        for kind, sc in scenes.items():
            img, _ = _range_img(lidar, sc, pose)
            ok = np.isfinite(m) & np.isfinite(img)
            row[kind] = float(np.median(np.abs(img - m)[ok])) if ok.any() else float("nan")
            row[kind + " hits"] = float(ok.sum() / max(np.isfinite(m).sum(), 1))
        rows.append(row)
    seam_s = [SPACING * i + CHUNK_SIZE + CHUNK_CORNER[0] - HALF_OVERLAP for i in range(len(stops) - 1)]
    (BENCH_DIR / "results" / "s2s_route_sweeps.json").write_text(json.dumps({"seams_s_m": seam_s, "rows": rows}, indent=1))
    summary = []
    for kind in scenes:
        v = np.array([r[kind] for r in rows])
        jumps = np.abs(np.diff(v))
        mids = np.array([0.5 * (rows[k]["s_m"] + rows[k + 1]["s_m"]) for k in range(len(rows) - 1)])
        at_seam = np.zeros(len(jumps), bool)
        for s in seam_s:
            at_seam |= np.abs(mids - s) <= HALF_OVERLAP + args.step
        summary.append({"scene": kind, "sweeps": len(rows), "median_error_m": round(float(np.nanmedian(v)), 3),
                        "median_jump_m": round(float(np.nanmedian(jumps)), 3),
                        "max_jump_at_seams_m": round(float(np.nanmax(jumps[at_seam])), 3) if at_seam.any() else None,
                        "max_jump_elsewhere_m": round(float(np.nanmax(jumps[~at_seam])), 3)})
        print(summary[-1], flush=True)
    write_results("s2s_route_consistency", summary, list(summary[0]),
                  notes=f"a sweep every {args.step:g} m from {s0:g} to {s1:.0f} m along the route; jump: the change of the "
                        f"per-sweep median |range error| between consecutive sweeps")
    _plot(rows, seam_s, list(scenes))


def _x_image(sweep, to_chunk: np.ndarray, shape) -> np.ndarray:
    """Each return's x in the chunk frame, as a range image (NaN: no return)."""
    out = np.full(shape, np.nan)
    out[sweep.pixels()] = transform_points(to_chunk, sweep.xyz().astype(np.float64))[:, 0]
    return out


def _plot(rows, seam_s, kinds) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 3.8))
    s = [r["s_m"] for r in rows]
    for k in kinds:
        ax.plot(s, [r[k] for r in rows], "o-", ms=3, label=k)
    for i, x in enumerate(seam_s):
        ax.axvline(x, color="0.5", ls="--", label="chunk seam (middle of the overlap)" if i == 0 else None)
    ax.set_yscale("log")
    ax.set_xlabel("distance along the route [m]")
    ax.set_ylabel("median |range error| vs the mesh [m]")
    ax.set_title("HDL-64E along a route of converted chunks (each from its own cameras)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(REPO / "docs" / "s2s_route.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
