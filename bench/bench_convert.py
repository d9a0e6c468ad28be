"""The converter's cost per stage and what each saving buys (issue 13), on worlds samples.

One 5-camera frame set (waymo-5) of the 102.4 m chunk through the shipped profile (or
`--profile`): seconds and peak memory of the geometry and appearance stages, then the savings of a
LiDAR-only run (no sky panorama) and of drawing one geometry sample instead of K, each measured in
the same process as the full conversion it is compared with (ratios, not absolute timings).

Reliability: on `--reliability-samples` held-out worlds, the geometry stage's voxels against the
ground-truth grid (same 0.8 m voxels from the chunk corner): precision (the share of predicted
voxels the ground truth holds) per confidence decile, and for voxels an input camera saw
(``observed``) against the rest; a reliability plot (docs/convert_reliability.png).

Not part of `make bench` (it needs a worlds dataset with the converter's image scale). Run:
`python -m bench.bench_convert --data DIR [--split test] [--samples 3] [--profile cpu]`
Results: bench/results/convert.{json,md}, convert_reliability.{json,md}.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from scube_sim.converter.frames import open_frames
from scube_sim.converter.pipeline import Converter
from scube_sim.datasets import open_dataset

from .common import BENCH_DIR, write_results

REPO = BENCH_DIR.parent


def _run(conv: Converter, frames, **kw) -> dict:
    t = time.perf_counter()
    done = conv.convert(frames, **kw)
    wall = time.perf_counter() - t
    return {"seconds": wall, **done.timings, "voxels": done.scene.num_voxels}


def reliability(conv: Converter, data: Path, split: str, n: int, k: int | None) -> tuple[list[dict], dict]:
    """Rows per confidence decile and the observed / unobserved split (module docstring)."""
    ds = open_dataset("worlds", data, split=split, eval_frames=False)
    conf, hit, seen = [], [], []
    for i in range(min(n, len(ds))):
        sample = ds[i]
        ijk, _, c, observed, vs = conv.pipeline.predict_voxels(sample.frames, samples=k or 1)
        gt = sample.ground_truth.coarse
        if abs(float(gt.voxel_size) - vs) > 1e-9:
            raise SystemExit(f"{sample.name}: ground truth at {gt.voxel_size} m, the converter's grid at {vs} m")
        truth = set(map(tuple, np.asarray(gt.ijk, np.int64).tolist()))
        conf.append(c.numpy())
        hit.append(np.array([tuple(v) in truth for v in ijk.tolist()], bool))
        seen.append(observed.numpy())
    conf, hit, seen = np.concatenate(conf), np.concatenate(hit), np.concatenate(seen)
    edges = np.unique(np.quantile(conf, np.linspace(0, 1, 11)))
    which = np.clip(np.searchsorted(edges, conf, side="right") - 1, 0, len(edges) - 2)
    rows = []
    for b in range(len(edges) - 1):
        m = which == b
        if m.any():
            rows.append({"bin": f"confidence {edges[b]:.3f}-{edges[b + 1]:.3f}", "voxels": int(m.sum()),
                         "mean_confidence": round(float(conf[m].mean()), 4),
                         "precision": round(float(hit[m].mean()), 4)})
    for name, m in (("observed by an input camera", seen), ("not observed", ~seen), ("all", np.ones_like(seen))):
        rows.append({"bin": name, "voxels": int(m.sum()),
                     "mean_confidence": round(float(conf[m].mean()), 4) if m.any() else float("nan"),
                     "precision": round(float(hit[m].mean()), 4) if m.any() else float("nan")})
    return rows, {"confidence": conf, "hit": hit}


def plot_reliability(rows: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dec = [r for r in rows if r["bin"].startswith("confidence")]
    fig, ax = plt.subplots(figsize=(5.5, 4.5), dpi=110)
    ax.plot([r["mean_confidence"] for r in dec], [r["precision"] for r in dec], "o-", label="confidence deciles")
    for r, mk in zip([r for r in rows if not r["bin"].startswith("confidence") and r["bin"] != "all"], ("s", "x")):
        ax.plot([r["mean_confidence"]], [r["precision"]], mk, ms=9, label=r["bin"])
    ax.plot([0, 1], [0, 1], "k:", lw=0.8, label="calibrated")
    ax.set_xlabel("mean confidence of the bin")
    ax.set_ylabel("precision (share of voxels the ground truth holds)")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="a worlds dataset folder")
    ap.add_argument("--split", default="test")
    ap.add_argument("--samples", type=int, default=3)
    ap.add_argument("--profile", default="cpu")
    ap.add_argument("--k", type=int, default=4, help="geometry samples when confidence is asked for")
    ap.add_argument("--reliability-samples", type=int, default=40)
    args = ap.parse_args(argv)
    conv = Converter(args.profile)
    folders = sorted(p for p in (Path(args.data) / args.split).iterdir() if p.is_dir())
    rel, _ = reliability(conv, Path(args.data), args.split, args.reliability_samples,
                         args.k if conv.pipeline.geometry.cfg.mode == "diffusion" else None)
    write_results("convert_reliability", rel, list(rel[0]),
                  notes=f"profile {args.profile} ({conv.pipeline.geometry.cfg.mode}), {min(len(folders), args.reliability_samples)} "
                        f"{args.split} worlds, coarse voxels against the ground truth's")
    plot_reliability(rel, REPO / "docs" / "convert_reliability.png",
                     f"converter geometry ({args.profile}): precision by confidence, {args.split} split")
    for r in rel:
        print(r)
    variants = {"full (sky, one geometry sample)": {},
                "LiDAR only (no sky)": {"sky": False},
                "LiDAR only, within 60 m": {"sky": False, "max_range": 60.0}}
    if conv.pipeline.geometry.cfg.mode == "diffusion":  # a single-step predictor draws no samples to count
        variants[f"confidence over K = {args.k}"] = {"confidence": True, "confidence_samples": args.k}
    per: dict[str, list[dict]] = {name: [] for name in variants}
    folders = folders[: args.samples]
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
                     "ratio_to_full": round(float(sec / base), 3),
                     "voxels": int(np.mean([r["voxels"] for r in runs]))})
    write_results("convert", rows, list(rows[0]),
                  notes=f"profile {args.profile}, {len(folders)} {args.split} samples of {args.data}, "
                        f"{len(open_frames(folders[0]))} cameras each; 2 cores")
    for r in rows:
        print(r)


if __name__ == "__main__":
    main()
