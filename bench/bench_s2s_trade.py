"""The converter's trade, end to end (issue 13): each knob -> LiDAR range error and hit agreement
against seconds, on held-out worlds samples (`model.sensor_to_sensor`), a table and a Pareto plot.

Knobs (each changed alone from the shipped `cpu` profile): the geometry stage's input resolution
(its images resized to half the training focal length), the appearance stage's, the Gaussians'
size cap (`max_scale_voxels`), M (the most opaque Gaussians kept per voxel), the fine geometry level
(its voxels grouped into 0.4 m, or its own 0.2 m), the appearance stage's test-time fit to the
input views (`fit_steps`), the conversion range (`max_range`), soft mode's alpha floor
(`soft_alpha_min`, where each Gaussian's box ends), the trace mode of the converted
scene (soft vs hard `max_response`), and with `--diffusion CKPT` a diffusion geometry stage
instead of the single-step predictor at 1 and 10 DDIM steps. Every variant runs on the same
samples in the same process; the ground truth (world, mesh sweeps, ground-truth VoxSplat rows) is
computed once per sample and shared. Seconds: conversion plus one sweep's trace, per sample.

Not part of `make bench` (it needs a worlds dataset). Run:
`python -m bench.bench_s2s_trade --data DIR [--split test] [--samples 3] [--diffusion CKPT] [--name NAME]`
Results: bench/results/<NAME>.{json,md}, docs/<NAME>.png (NAME: s2s_trade).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from scube_sim.converter.eval.sensor_to_sensor import evaluate_sample, geometric_lidar, summarise_rows
from scube_sim.converter.pipeline import Converter
from scube_sim.converter.profile import FineProfile, load_profile
from scube_sim.raytrace import SoftMode

from .common import BENCH_DIR, write_results

REPO = BENCH_DIR.parent


# The fine geometry level (0.2 m, the shipped geometry-fine-cpu) on the coarse prediction, grouped into
# the 0.4 m voxels the appearance stage was trained on; its images at the coarse level's focal length
FINE_04 = FineProfile(checkpoint="geometry-fine-cpu", focal_px=342.5, output_voxel_size=0.4)


def variants(base, diffusion: str | None) -> list[tuple[str, object, dict, str | SoftMode | None]]:
    """(name, profile, convert options, trace) per variant; trace: None (the scene's own mode), a
    trace mode's name or a `SoftMode`."""
    g, a = base.geometry, base.appearance
    out = [
        ("shipped cpu profile", base, {}, None),
        ("geometry images at half focal", base.model_copy(update={"geometry": g.model_copy(
            update={"focal_px": g.focal_px / 2})}), {}, None),
        ("appearance images at half focal", base.model_copy(update={"appearance": a.model_copy(
            update={"focal_px": a.focal_px / 2})}), {}, None),
        ("Gaussians capped at 0.5 voxel", base.model_copy(update={"appearance": a.model_copy(
            update={"max_scale_voxels": 0.5})}), {}, None),
        ("Gaussians capped at 2 voxels", base.model_copy(update={"appearance": a.model_copy(
            update={"max_scale_voxels": 2.0})}), {}, None),
        ("M = 2 (the two most opaque per voxel)", base.model_copy(update={"appearance": a.model_copy(
            update={"gaussians_per_voxel": 2})}), {}, None),
        ("M = 1", base.model_copy(update={"appearance": a.model_copy(update={"gaussians_per_voxel": 1})}), {}, None),
        ("converted within 60 m", base, {"max_range": 60.0}, None),
        ("coarse + fine level, 0.4 m voxels", base.model_copy(update={"fine": FINE_04}), {}, None),
        ("coarse + fine level, 0.4 m voxels, M = 1", base.model_copy(update={
            "fine": FINE_04, "appearance": a.model_copy(update={"gaussians_per_voxel": 1})}), {}, None),
        # the fine level's own voxels, half the size the appearance stage was trained on
        ("coarse + fine level, 0.2 m voxels, M = 1", base.model_copy(update={
            "fine": FINE_04.model_copy(update={"output_voxel_size": 0.2}),
            "appearance": a.model_copy(update={"gaussians_per_voxel": 1})}), {}, None),
        # the appearance stage's test-time fit to the input views (`appearance.fit_input_views`)
        *[(f"coarse + fine level, 0.4 m voxels, M = 1, fitted to the input views ({n} steps)", base.model_copy(update={
            "fine": FINE_04, "appearance": a.model_copy(update={"gaussians_per_voxel": 1, "fit_steps": n})}), {}, None)
          for n in (25, 50)],
        ("traced at hard opacity (max_response)", base, {}, "max_response"),
        # soft mode's alpha floor: each Gaussian's box ends where its response reaches it
        ("M = 1, traced with soft alpha_min 0.05", base.model_copy(update={"appearance": a.model_copy(
            update={"gaussians_per_voxel": 1})}), {}, SoftMode(alpha_min=0.05)),
        ("M = 1, traced with soft alpha_min 0.1", base.model_copy(update={"appearance": a.model_copy(
            update={"gaussians_per_voxel": 1})}), {}, SoftMode(alpha_min=0.1)),
        ("coarse + fine level, 0.2 m voxels, M = 1, traced with soft alpha_min 0.1", base.model_copy(update={
            "fine": FINE_04.model_copy(update={"output_voxel_size": 0.2}),
            "appearance": a.model_copy(update={"gaussians_per_voxel": 1})}), {}, SoftMode(alpha_min=0.1)),
    ]
    if diffusion:
        for steps in (1, 10):
            prof = base.model_copy(update={"geometry": g.model_copy(update={"checkpoint": diffusion,
                                                                               "sample_steps": steps})})
            out.append((f"diffusion geometry, {steps} DDIM steps", prof, {}, None))
    return out


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(15, 4.8))
    for ax, key, label in ((axes[0], "median_m", "median |range error| [m] (lower is better)"),
                           (axes[1], "hit_agreement", "hit agreement (higher is better)")):
        xs = np.array([r["seconds"] for r in rows])
        ys = np.array([r[key] for r in rows])
        for i, (r, x, y) in enumerate(zip(rows, xs, ys)):
            ax.scatter([x], [y], color=plt.cm.tab20(i % 20), label=f"{i + 1}: {r['variant']}")
            ax.annotate(str(i + 1), (x, y), textcoords="offset points", xytext=(4, 3), fontsize=8)
        # the Pareto front: no other variant both faster and better
        better = (lambda u, v: u <= v) if key == "median_m" else (lambda u, v: u >= v)
        front = sorted((i for i in range(len(rows)) if not any(
            xs[j] <= xs[i] and better(ys[j], ys[i]) and (xs[j], ys[j]) != (xs[i], ys[i]) for j in range(len(rows)))),
            key=lambda i: xs[i])
        ax.plot(xs[front], ys[front], "--", c="0.4", marker="o", mfc="none", ms=12, label="Pareto front")
        ax.set_xlabel("seconds per sample (convert + one sweep), 2 cores")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.suptitle("Sensor to sensor: converter knobs vs LiDAR error on the mesh (HDL-64E, input pose, held-out worlds)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="test")
    ap.add_argument("--samples", type=int, default=3)
    ap.add_argument("--sensor", default="hdl64e")
    ap.add_argument("--diffusion", default=None, help="a diffusion geometry checkpoint to add as variants")
    ap.add_argument("--only", nargs="+", default=None,
                    help="run only these variants and write bench/results/s2s_trade_only.{json,md} (no plot)")
    ap.add_argument("--plot-only", action="store_true", help="redraw the plot from bench/results/<name>.json")
    ap.add_argument("--name", default=None,
                    help="results bench/results/<name>.{json,md} and plot docs/<name>.png (default s2s_trade, "
                         "with --only s2s_trade_only)")
    args = ap.parse_args(argv)
    args.name = args.name or ("s2s_trade_only" if args.only else "s2s_trade")
    if args.plot_only:
        rows = json.loads((BENCH_DIR / "results" / f"{args.name}.json").read_text())["rows"]
        plot([r for r in rows if "seconds" in r], REPO / "docs" / f"{args.name}.png")
        return
    dirs = sorted(d for d in (Path(args.data) / args.split).iterdir() if (d / "meta.json").is_file())[:args.samples]
    lidar = geometric_lidar(args.sensor)
    cache: dict = {}
    rows = []
    for name, prof, opts, trace in variants(load_profile("cpu"), args.diffusion):
        if args.only and name not in args.only:
            continue
        conv = Converter(prof)
        samples = [evaluate_sample(conv, d, lidar, ahead=(0.0,), convert_options=opts, with_psnr=False,
                                   gt_cache=cache, trace_mode=trace) for d in dirs]
        summ = {(r["scene"], r["split"]): r for r in summarise_rows(samples)}
        conv_all = summ[("converted", "all")]
        sec = float(np.mean([s["stages"]["seconds"] + s["stages"]["trace_s_per_sweep"] for s in samples]))
        rows.append({"variant": name, "seconds": round(sec, 2),
                     "convert_s": round(float(np.mean([s["stages"]["seconds"] for s in samples])), 2),
                     "peak_mb": round(max(s["stages"]["peak_mb"] for s in samples)),
                     "median_m": round(conv_all["median_m"], 3), "p90_m": round(conv_all["p90_m"], 3),
                     "hit_agreement": round(conv_all["hit_agreement"], 4),
                     "median_seen_m": round(summ[("converted", "seen")]["median_m"], 3),
                     "median_unseen_m": round(summ[("converted", "unseen")]["median_m"], 3),
                     "geometry_iou": round(float(np.mean([s["stages"].get("geometry_iou", np.nan) for s in samples])), 4)})
        print(rows[-1], flush=True)
    gt = {(r["scene"], r["split"]): r for r in summarise_rows(samples)}[("ground-truth VoxSplat", "all")]
    rows.append({"variant": "ground-truth VoxSplat (0.4 m, entry): the representation's own error",
                 "median_m": round(gt["median_m"], 3), "p90_m": round(gt["p90_m"], 3),
                 "hit_agreement": round(gt["hit_agreement"], 4)})
    write_results(args.name, rows, ["variant", "seconds", "convert_s", "peak_mb", "median_m", "p90_m",
                                      "hit_agreement", "median_seen_m", "median_unseen_m", "geometry_iou"],
                  notes=f"{len(dirs)} {args.split} samples, {lidar.config.name} at the input pose, against the mesh; "
                        f"each knob changed alone from the shipped cpu profile")
    if not args.only:
        plot([r for r in rows if "seconds" in r], REPO / "docs" / f"{args.name}.png")


if __name__ == "__main__":
    main()
