"""The converter's first-voxel casts on the compiled core against the torch loop (issue 13).

Both stages cast rays through a voxel grid (`model/voxel_rays.py`): the geometry stage marks the
voxels an input camera saw (`observed`), the appearance stage deposits each pixel's feature in the
first voxel its ray enters. The same traversal runs in the compiled trace core or in torch; this
converts the demo's five camera images with each, in the same process, per shipped profile:
seconds (best of `--repeats`), the ratio, and whether the two scenes are equal array for array.
No dataset needed. Run: `python -m bench.bench_voxel_cast [--repeats 2]`.
Results: bench/results/voxel_cast.{json,md}.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from scube_sim.converter.profile import FineProfile, load_profile
from scube_sim.raytrace import compiled

from .common import best_per_core, write_results

# the shipped paper-route profiles, and cpu-lidar with the fine geometry level (0.2 m grouped into 0.4 m)
PROFILES = ("cpu", "cpu-lidar", "cpu-lidar-fine")


def _profile(name: str):
    if name != "cpu-lidar-fine":
        return name
    return load_profile("cpu-lidar").model_copy(update={
        "name": name, "fine": FineProfile(checkpoint="geometry-fine-cpu", focal_px=342.5, output_voxel_size=0.4)})


def _same_scene(a, b) -> bool:
    """Whether two VoxSplats save to the same arrays (every entry of the .npz)."""
    with tempfile.TemporaryDirectory() as tmp:
        pa, pb = Path(tmp) / "a.npz", Path(tmp) / "b.npz"
        a.save(pa)
        b.save(pb)
        with np.load(pa) as za, np.load(pb) as zb:
            return za.files == zb.files and all(np.array_equal(za[k], zb[k]) for k in za.files)


def run(repeats: int = 2) -> list[dict]:
    from scube_sim.converter.pipeline import Converter
    from scube_sim.runs.demo import DEFAULT_WORLD, FRAMES_SCALE
    from scube_sim.worlds.dataset import render_frames
    from scube_sim.worlds.generator import generate_world

    if not compiled.available():
        raise SystemExit(f"the compiled core is not built: {compiled.load_error()}")
    frames = render_frames(generate_world(DEFAULT_WORLD), "waymo-5", 0.0, FRAMES_SCALE)
    rows = []
    for profile in PROFILES:
        conv = Converter(_profile(profile))
        conv.convert(frames, seed=0).scene  # warm-up: first-call allocations
        sec, scene = best_per_core(lambda: conv.convert(frames, seed=0).scene, repeats)
        rows.append({"profile": profile, "voxels": int(scene["compiled"].num_voxels),
                     "torch_loop_s": round(sec["reference"], 2), "compiled_s": round(sec["compiled"], 2),
                     "speedup": round(sec["reference"] / sec["compiled"], 2),
                     "same_scene": _same_scene(scene["reference"], scene["compiled"])})
        print(rows[-1])
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    rows = run(args.repeats)
    write_results("voxel_cast", rows, list(rows[0]),
                  notes="the demo world's five camera images (waymo-5 at the converter's image scale) converted "
                        "with each core in one process, best of "
                        f"{args.repeats}; same_scene: every array of the saved .npz equal; 2 cores")


if __name__ == "__main__":
    main()
