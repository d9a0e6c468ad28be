"""Tuning plane-sweep stereo (`stereo.stereo_depth`) on held-in data: confident coverage and error
of "object" pixels per range band, and seconds per image, for one `StereoConfig`.

Data (held in: never the acceptance sets; the worlds folder with every instant within ±4, as the
defaults since semi-global aggregation were chosen on, is made by
`scube-sim worlds generate --split val --count 3 -j 1 --rig waymo-5 --frame-offsets=-4,-3,-2,-1,0,1,2,3,4
--image-scale 0.25 --fine-voxel 0.1 --coarse-factor 4 -o /work/data/ctx_val9`, 34 s per sample):
- worlds: samples `--worlds-samples` of `--worlds DIR` split `--split` (default val), cameras
  `--cameras` (indices into the rig, default all), with ±`--context` instants. Ground truth: the
  rendered depth map; objects: not ground (semantic labels) and not sky (no finite depth).
- KITTI-360: frames `--kitti-frames` (default 16-19; 4-15 are the acceptance frames) of `--kitti`,
  ground truth `converter.eval.depth.ground_truth` (LiDAR projected, occluded returns removed); objects:
  the returns off the LiDAR's ground plane.

Scored: object pixels with ground truth in (0, 40) m, bands 0-10 / 10-20 / 20-40 m. Per band and
confidence threshold (`--thresholds`): coverage (confident pixels with a depth / object pixels),
median |error| (m), median relative error and δ<1.25 over the confident ones. Also error against
confidence deciles (all pixels with a depth, 0-40 m): how well the confidence ranks errors.

`--final DATASET` instead scores the default `StereoConfig` with `scube-sim eval depth`'s code
(`converter.eval.depth.evaluate_depth`, confident pixels: confidence >= 0.5) on `--final-samples` of
`--worlds`/`--split` (worlds) or `--kitti` (kitti360), and writes results/stereo_tune_<label>.json
and its table (.md): the acceptance figures for a subset (e.g. KITTI-360 frames 4-15).

`--set key=value` changes a `StereoConfig` field (repeatable). `--dump FILE.npz` (under /tmp)
keeps the scored pixels' (confidence, peak ratio, agreement, depth, ground truth, dataset) for
offline calibration. Nothing else is cached.

Run (1 thread): `OMP_NUM_THREADS=1 python -m experiments.stereo_tune --label base --worlds-samples 0,1
--cameras 0 --kitti-frames 16,18`; results experiments/results/stereo_tune_<label>.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from scube_sim.converter.eval.depth import depth_method, evaluate_depth, format_table, ground_truth, json_ready
from scube_sim.datasets import open_dataset
from scube_sim.datasets.base import frames_with_context
from scube_sim.memory import peak_mb, reset_peak
from scube_sim.reconstruct.config import StereoConfig
from scube_sim.reconstruct.stereo import stereo_depth

from .common import RESULTS, write_results

BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0))
KITTI_DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti360-2013_05_28-seq"
WORLDS_DEFAULT = Path("/work/data/ctx_val")


def _ints(s: str) -> list[int]:
    return [int(x) for x in s.split(",") if x.strip()] if s else []


def _value(v: str):
    for t in (int, float):
        try:
            return t(v)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(v.lower(), v)


def image_sets(args):
    """(dataset name, frames, image index, ground truth, ground mask) per reference image."""
    if args.worlds_samples:
        ds = open_dataset("worlds", args.worlds, split=args.split, eval_frames=False)
        for i in args.worlds_samples:
            frames = frames_with_context(ds, i, args.context)
            truth = ground_truth(ds[i])
            cams = args.cameras or list(range(len(truth)))
            for k in cams:
                yield "worlds", frames, k, truth[k][0], truth[k][1]
    if args.kitti_frames:
        ds = open_dataset("kitti360", args.kitti)
        for i in args.kitti_frames:
            frames = frames_with_context(ds, i, args.context)
            truth = ground_truth(ds[i])
            for k, (gt, ground, _) in enumerate(truth):
                yield "kitti360", frames, k, gt, ground


def band_rows(group: str, conf, depth, gt, thresholds) -> list[dict]:
    rows = []
    for t in thresholds:
        for lo, hi in BANDS + ((0.0, 40.0),):
            band = (gt >= lo) & (gt < hi)
            sel = band & (conf >= t) & np.isfinite(depth)
            p, g = depth[sel], gt[sel]
            err = np.abs(p - g)
            n = int(band.sum())
            rows.append({"group": group, "threshold": t, "band": f"{lo:g}-{hi:g} m", "object_pixels": n,
                         "coverage": float(sel.sum() / n) if n else float("nan"),
                         "median_abs_m": float(np.median(err)) if len(p) else float("nan"),
                         "median_rel": float(np.median(err / g)) if len(p) else float("nan"),
                         "delta_1.25": float(np.mean(np.maximum(p / g, g / p) < 1.25)) if len(p) else float("nan")})
    return rows


def decile_rows(group: str, conf, depth, gt) -> list[dict]:
    ok = np.isfinite(depth)
    c, p, g = conf[ok], depth[ok], gt[ok]
    if not len(c):
        return []
    edges = np.unique(np.quantile(c, np.linspace(0, 1, 11)))
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (c >= lo) & ((c < hi) | (hi == edges[-1]))
        ratio = p[sel] / g[sel]
        rows.append({"group": group, "conf_lo": float(lo), "conf_hi": float(hi), "pixels": int(sel.sum()),
                     "delta_1.25": float(np.mean(np.maximum(ratio, 1 / ratio) < 1.25)),
                     "median_rel": float(np.median(np.abs(ratio - 1)))})
    return rows


def final(args) -> None:
    """The acceptance figures (`evaluate_depth` with the stereo method) on a chosen subset."""
    if args.final == "worlds":
        ds = open_dataset("worlds", args.worlds, split=args.split, eval_frames=False)
    else:
        ds = open_dataset("kitti360", args.kitti)
    cfg = StereoConfig(**{k: _value(v) for k, v in (s.split("=", 1) for s in args.set)})
    res = evaluate_depth(ds, args.final_samples or range(len(ds)), depth_method("stereo", stereo=cfg),
                         context=args.context)
    res["stereo_config"] = cfg.model_dump()
    res["samples_evaluated"] = list(args.final_samples)
    lines = format_table(res)
    print("\n".join(lines))
    if not args.no_write:
        RESULTS.mkdir(parents=True, exist_ok=True)
        (RESULTS / f"stereo_tune_{args.label}.json").write_text(json.dumps(json_ready(res), indent=2) + "\n")
        (RESULTS / f"stereo_tune_{args.label}.md").write_text(
            f"Samples {args.final_samples or 'all'}; StereoConfig {json.dumps(cfg.model_dump())}\n\n"
            + "\n".join(lines) + "\n")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--label", required=True)
    ap.add_argument("--worlds", type=Path, default=WORLDS_DEFAULT)
    ap.add_argument("--split", default="val")
    ap.add_argument("--worlds-samples", type=_ints, default=[0, 1])
    ap.add_argument("--cameras", type=_ints, default=[])
    ap.add_argument("--kitti", type=Path, default=KITTI_DEFAULT)
    ap.add_argument("--kitti-frames", type=_ints, default=[16, 17, 18, 19])
    ap.add_argument("--context", type=int, default=4)
    ap.add_argument("--set", action="append", default=[], help="StereoConfig field=value")
    ap.add_argument("--thresholds", default="0.3,0.5,0.7")
    ap.add_argument("--dump", type=Path, default=None, help="scored pixels .npz (under /tmp)")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--final", choices=["worlds", "kitti360"], default=None)
    ap.add_argument("--final-samples", type=_ints, default=[])
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.final:
        final(args)
        return
    if args.dump is not None and not str(args.dump.resolve()).startswith("/tmp/"):
        ap.error("--dump: only under /tmp")
    cfg = StereoConfig(**{k: _value(v) for k, v in (s.split("=", 1) for s in args.set)})
    thresholds = [float(t) for t in args.thresholds.split(",")]
    acc = {}  # group -> lists of (conf, peak, agreement, depth, gt)
    seconds, peaks = {}, []
    for group, frames, k, gt, ground in image_sets(args):
        reset_peak()
        t0 = time.perf_counter()
        res = stereo_depth(frames, k, cfg)
        dt = time.perf_counter() - t0
        peaks.append(peak_mb())
        seconds.setdefault(group, []).append(dt)
        obj = np.isfinite(gt) & (gt > 0) & (gt < 40.0) & ~ground
        parts = acc.setdefault(group, [[], [], [], [], []])
        for lst, m in zip(parts, (res.confidence, res.peak_ratio, res.agreement, res.depth, gt)):
            lst.append(np.asarray(m, np.float32)[obj])
        print(f"{group} {frames.images[k].name} {frames.metadata.get('sample', '')}: {dt:.1f} s, "
              f"sources {[(v.offset, v.image.name) for v in res.sources]}, "
              f"conf>=0.5 on {np.mean(res.confidence[obj] >= 0.5):.3f} of {int(obj.sum())} object pixels", flush=True)
    rows, deciles = [], []
    dump = {}
    for group, parts in acc.items():
        conf, peak, agree, depth, gt = (np.concatenate(p) for p in parts)
        rows += band_rows(group, conf, depth, gt, thresholds)
        deciles += decile_rows(group, conf, depth, gt)
        for name, a in zip(("conf", "peak", "agree", "depth", "gt"), (conf, peak, agree, depth, gt)):
            dump[f"{group}_{name}"] = a
    for r in rows:
        r["seconds_per_image"] = float(np.mean(seconds[r["group"]]))
        r["peak_mb"] = float(np.nanmax(peaks))
    print(f"config: {cfg.model_dump()}")
    print("| group | thr | band | objects | coverage | median abs (m) | median rel | δ<1.25 | s/image |")
    for r in rows:
        print(f"| {r['group']} | {r['threshold']:g} | {r['band']} | {r['object_pixels']} | {100 * r['coverage']:.1f} % "
              f"| {r['median_abs_m']:.3f} | {r['median_rel']:.3f} | {r['delta_1.25']:.3f} | "
              f"{r['seconds_per_image']:.1f} |")
    print("| group | confidence decile | pixels | δ<1.25 | median rel |")
    for d in deciles:
        print(f"| {d['group']} | {d['conf_lo']:.2f}-{d['conf_hi']:.2f} | {d['pixels']} | {d['delta_1.25']:.3f} | "
              f"{d['median_rel']:.3f} |")
    print(f"peak {np.nanmax(peaks):.0f} MB")
    if args.dump is not None:
        np.savez_compressed(args.dump, **dump)
    if not args.no_write:
        notes = (f"config {json.dumps(cfg.model_dump())}; data: worlds {args.worlds} {args.split} samples "
                 f"{args.worlds_samples} cameras {args.cameras or 'all'}, kitti360 frames {args.kitti_frames}, "
                 f"context ±{args.context}; peak {np.nanmax(peaks):.0f} MB")
        for r in rows:
            r["label"] = args.label
        write_results(f"stereo_tune_{args.label}", rows + [dict(d, label=args.label, band="deciles") for d in deciles],
                      ["group", "threshold", "band", "object_pixels", "coverage", "median_abs_m", "median_rel",
                       "delta_1.25", "seconds_per_image"], notes)


if __name__ == "__main__":
    main()
