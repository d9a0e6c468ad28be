"""The converter's cost per stage and what each saving buys (issue 13), on worlds samples.

One 5-camera frame set (waymo-5) of the 102.4 m chunk through the shipped profile (or
`--profile`): seconds and peak memory of the geometry and appearance stages, then the savings of a
LiDAR-only run (no sky panorama) and of drawing one geometry sample instead of K, each measured in
the same process as the full conversion it is compared with (ratios, not absolute timings).

Not part of `make bench` (it needs a worlds dataset with the converter's image scale). Run:
`python -m bench.bench_convert --data DIR [--split test] [--samples 3] [--profile cpu]`
Results: bench/results/convert.{json,md}.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from scube_sim.model.converter import Converter, open_frames

from .common import write_results


def _run(conv: Converter, frames, **kw) -> dict:
    t = time.perf_counter()
    scene = conv.convert(frames, **kw)
    wall = time.perf_counter() - t
    return {"seconds": wall, **conv.timings, "voxels": scene.num_voxels}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="a worlds dataset folder")
    ap.add_argument("--split", default="test")
    ap.add_argument("--samples", type=int, default=3)
    ap.add_argument("--profile", default="cpu")
    ap.add_argument("--k", type=int, default=4, help="geometry samples when confidence is asked for")
    args = ap.parse_args(argv)
    conv = Converter(args.profile)
    variants = {"full (sky, one geometry sample)": {},
                "LiDAR only (no sky)": {"sky": False},
                "LiDAR only, within 60 m": {"sky": False, "max_range": 60.0},
                f"confidence over K = {args.k}": {"confidence": True, "k": args.k}}
    per: dict[str, list[dict]] = {name: [] for name in variants}
    folders = sorted(p for p in (Path(args.data) / args.split).iterdir() if p.is_dir())[: args.samples]
    _run(conv, open_frames(folders[0]))  # warm-up: first-call allocations
    for folder in folders:
        frames = open_frames(folder)
        for name, kw in variants.items():
            per[name].append(_run(conv, frames, **kw))
    base = np.mean([r["seconds"] for r in per["full (sky, one geometry sample)"]])
    rows = []
    for name, runs in per.items():
        sec = float(np.mean([r["seconds"] for r in runs]))
        rows.append({"variant": name, "samples": len(runs), "seconds": round(sec, 2),
                     "geometry_s": round(float(np.mean([r["geometry_s"] for r in runs])), 2),
                     "appearance_s": round(float(np.mean([r["appearance_s"] for r in runs])), 2),
                     "peak_mb": round(float(np.max([r["peak_mb"] for r in runs])), 0),
                     "ratio_to_full": round(sec / base, 3),
                     "voxels": int(np.mean([r["voxels"] for r in runs]))})
    write_results("convert", rows, list(rows[0]),
                  notes=f"profile {args.profile}, {len(folders)} {args.split} samples of {args.data}, "
                        f"{len(open_frames(folders[0]))} cameras each; 2 cores")
    for r in rows:
        print(r)


if __name__ == "__main__":
    main()
