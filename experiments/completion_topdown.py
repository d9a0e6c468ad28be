"""Where a completion adds, seen from above: one worlds sample's truth, observed surfaces and the
cells the completion added, with the LiDAR poses `eval sensor-to-sensor` drives ahead (issue 45).

    python -m experiments.completion_topdown --data DIR --sample 000008 [--split test] \\
        [--profile evidence-complete] [-o experiments/results/completion_topdown_000008.png]

Each 0.4 m column of the chunk, chunk frame (x ahead, y left): grey where the truth holds an object
(not ground) voxel, blue where the scene holds an observed voxel that is no ground, red where the
completion added a cell (0.8 m: its Gaussian at the centre) and the truth holds no object voxel in
the column, purple where it added one and the truth holds an object there; triangles: the LiDAR at the input pose, 20 m and
60 m ahead.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from experiments.common import RESULTS
from scube_sim.converter.eval import sensor_to_sensor as s2s
from scube_sim.converter.frames import open_frames
from scube_sim.converter.merge import GROUND_IDS
from scube_sim.converter.pipeline import Converter
from scube_sim.viz import pyplot, save_png
from scube_sim.voxsplat import voxel_keys
from scube_sim.worlds.groundtruth import CHUNK_CORNER, CHUNK_SIZE

CELL_M = 0.4
COLOURS = {"truth": (0.75, 0.75, 0.75), "added_wrong": (0.95, 0.25, 0.25), "added_right": (0.55, 0.2, 0.6),
           "observed": (0.1, 0.1, 0.85)}


def columns(points: np.ndarray, n: int, cell: float = CELL_M) -> np.ndarray:
    """(n, n) bool: the `cell` metre columns of the chunk that hold any of the chunk-frame points (N, 3)."""
    ij = np.floor((points[:, :2] - CHUNK_CORNER[:2]) / cell).astype(np.int64)
    ok = np.all((ij >= 0) & (ij < n), 1)
    out = np.zeros((n, n), bool)
    out[ij[ok, 0], ij[ok, 1]] = True
    return out


def topdown(data: Path, split: str, sample: str, profile: str, out: Path) -> dict:
    """Draws the sample (module docstring) into `out`; returns the counts of added columns."""
    d = Path(data) / split / sample
    meta = json.loads((d / "meta.json").read_text(encoding="utf-8"))
    conv = Converter(profile)
    done = conv.convert(open_frames(d, context=conv.profile.context))
    scene = done.scene
    if done.uncompleted is None:
        raise SystemExit(f"--profile {profile}: has no completion to draw")
    centres = scene.origin + scene.voxel_centers()
    before = set(voxel_keys(done.uncompleted.ijk.astype(np.int64)).tolist())
    added = np.array([k not in before for k in voxel_keys(scene.ijk.astype(np.int64)).tolist()], bool)
    observed = scene.channel("observed").astype(bool) & ~np.isin(scene.labels.astype(np.int64), GROUND_IDS)
    with np.load(d / "voxels.npz") as z:
        ijk, labels = z["coarse_ijk"].astype(np.int64), z["coarse_labels"].astype(np.int64)
        size = float(z["coarse_voxel_size"])
    n = int(round(CHUNK_SIZE / CELL_M))
    objects = ~np.isin(labels, GROUND_IDS)
    truth = columns(CHUNK_CORNER + (ijk[objects] + 0.5) * size, n)
    # an added cell (`completion_voxel_size`) holds one Gaussian at its centre: drawn as the whole cell
    k = max(1, int(round(conv.pipeline.completion_voxel_size / CELL_M)))
    add = np.kron(columns(centres[added], n // k, CELL_M * k), np.ones((k, k), bool))
    img = np.ones((n, n, 3))
    img[truth] = COLOURS["truth"]
    img[add & ~truth] = COLOURS["added_wrong"]
    img[add & truth] = COLOURS["added_right"]
    img[columns(centres[observed], n)] = COLOURS["observed"]  # on top: what the cameras saw
    lidar = s2s.geometric_lidar("hdl64e")
    poses = s2s.ahead_poses(lidar, np.asarray(meta["chunk_to_world"], np.float64))
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 7.5), dpi=80)
    lo, hi = CHUNK_CORNER[:2], CHUNK_CORNER[:2] + CHUNK_SIZE
    ax.imshow(img, origin="lower", extent=(lo[1], hi[1], lo[0], hi[0]), interpolation="nearest")
    for p in poses:
        ax.plot(p.chunk[1, 3], p.chunk[0, 3], "k^", ms=7)
        ax.annotate(f"{p.ahead:.0f} m", (p.chunk[1, 3], p.chunk[0, 3]), xytext=(6, -3), textcoords="offset points")
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in COLOURS.values()]
    ax.legend(handles, ["truth: objects", "added, no object there", "added on an object", "observed, not ground"],
              loc="lower left", fontsize=8)
    ax.set_xlabel("y, chunk frame (m)")
    ax.set_ylabel("x, chunk frame (m, ahead)")
    ax.set_title(f"worlds {split} {sample}, {profile}: where the completion added", fontsize=10)
    fig.tight_layout()
    save_png(fig, out)
    return {"added_columns": int(add.sum()), "added_columns_on_objects": int((add & truth).sum())}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--split", default="test")
    ap.add_argument("--sample", required=True, help="the sample's folder name, e.g. 000008")
    ap.add_argument("--profile", default="evidence-complete")
    ap.add_argument("-o", "--out", type=Path, default=None)
    args = ap.parse_args(argv)
    if not (args.data / args.split / args.sample / "meta.json").is_file():
        ap.error(f"--sample: no worlds sample at {args.data / args.split / args.sample} (meta.json missing)")
    out = args.out or RESULTS / f"completion_topdown_{args.sample}.png"
    print(topdown(args.data, args.split, args.sample, args.profile, out), out)


if __name__ == "__main__":
    main()
