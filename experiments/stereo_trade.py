"""Trade study of plane-sweep stereo (`stereo.stereo_depth`, issue 43): one factor at a time around
the default `StereoConfig()` (whatever its defaults are when run) and the default context
(`--context`, ±4 instants), depth error and coverage against seconds and peak memory.

Factors (each value one run point; the default point is run once and shared by every factor):
- context: the ±K instants `datasets.base.frames_with_context` adds (0: only the other cameras at
  the reference instant): 0, 1, 2, 4, 8;
- StereoConfig fields, read generically: sources 1, 2, 3, 4, 6; hypotheses 32, 64, 128, 192;
  scale 0.25, 0.5, 0.75, 1.0. A built-in factor that is no field of StereoConfig is skipped; the
  default's own value is always one of a factor's points. `--vary field=v1,v2,...` (repeatable)
  replaces or adds a factor (`none` for None, e.g. `--vary sgm_paths=0,4,8` or
  `--vary max_rel_error=none,0.05`); `--points f1,f2` runs only those factors (and the default).
  The matching cost and the aggregation are no longer StereoConfig choices (census, the best k of
  the sources that see a pixel); experiments/stereo_costs.py compares the costs on the sweep itself.

Data (held out: the test split and the KITTI-360 acceptance frames; nothing is tuned on them):
- worlds: samples `--worlds-samples` (default 0-5) of `--worlds` (default /work/data/ctx_worlds6)
  split `--split` (test), cameras `--cameras` (default all 5: one frame set = 5 reference images).
  Ground truth: the rendered depth; objects: not ground (semantic labels), not sky. The data,
  stored instants -8, -4, -2, -1, 1, 2, 4, 8 around T so that K = 1, 2, 4, 8 each see a larger
  set (5 and 10 are evaluation instants, never context), was made with
      OMP_NUM_THREADS=1 scube-sim worlds generate --split test --count 6 -j 1 --rig waymo-5 \\
          --frame-offsets=-8,-4,-2,-1,0,1,2,4,8 --image-scale 0.25 --fine-voxel 0.1 \\
          --coarse-factor 4 -o /work/data/ctx_worlds6
  (about 21 s per sample on one core).
- KITTI-360: frames `--kitti-frames` (default 4-15) of `--kitti` (default
  ../shared/data/kitti360-2013_05_28-seq next to the repository), camera image_00; ground truth the
  projected LiDAR (`converter.eval.depth.ground_truth`), objects the returns off its ground plane.
Images, ground truth and the band scores come from experiments/stereo_tune.py (`image_sets`,
`band_rows`).

Measured per point and dataset, on object pixels with ground truth in (0, 40) m: confident
(confidence >= `DEFAULT_STEREO_CONFIDENCE`, 0.5) coverage, per band 0-10 / 10-20 / 20-40 m and in
all; median |error| (m) per band, median relative error and δ<1.25 over the confident ones; seconds
per image (mean of the `stereo_depth` calls) and per frame set (the reference images of one sample
together); peak resident memory (`memory.reset_peak` before each call, `peak_mb` after; the max).

Pareto front per dataset, on the trade the issue names (depth error and coverage against time):
among the points with δ<1.25 >= 0.95 that keep the issue's safety case (`mover_safe`: the planted
moving object without a box, the test's scene with the point's factor, at most 0.5 % of it
confidently wrong; the data here have no unboxed movers, so coverage alone would reward letting
them through), those no other point beats on seconds per image (lower;
within 5 % counts as the same time: timing noise), coverage (higher) and median relative error
(lower) at once. Beside it the front of seconds and coverage alone (column `front_time_coverage`,
the dotted steps on the plot): a point can buy coverage and time with error (a lower `scale`).
The run prints whether the default is on each.

Resumable: each (dataset, point) result is appended to experiments/results/<label>_points.jsonl,
keyed by dataset, full config, context and data subset; a key already there is not run again (a
killed run continues where it stopped; a changed default is a new point). `--fresh` starts over.

Run (1 thread; the full study, 18 points x 42 images):
    OMP_NUM_THREADS=1 python -m experiments.stereo_trade
small: `--worlds-samples 0 --cameras 0 --kitti-frames 4 --points sources,scale --label trade_smoke`.
Outputs: experiments/results/<label>.{json,md} (one row per point: factor, value, both datasets'
metrics, on the front or not), docs/<label>.png (coverage against seconds per image, one panel per
dataset); <label> is stereo_trade by default.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from argparse import Namespace
from pathlib import Path

import numpy as np
import torch
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from scube_sim.converter.eval.depth import DEFAULT_STEREO_CONFIDENCE
from scube_sim.memory import peak_mb, reset_peak
from scube_sim.reconstruct.config import StereoConfig
from scube_sim.reconstruct.stereo import stereo_depth

from .common import EXPERIMENTS_DIR, RESULTS, write_results
from .stereo_tune import KITTI_DEFAULT, _ints, _value, band_rows, image_sets

FACTORS = {"context": [0, 1, 2, 4, 8], "sources": [1, 2, 3, 4, 6], "hypotheses": [32, 64, 128, 192],
           "scale": [0.25, 0.5, 0.75, 1.0]}
DEFAULT_CONTEXT = 4
WORLDS_DEFAULT = Path("/work/data/ctx_worlds6")
DOCS = EXPERIMENTS_DIR.parent / "docs"
MIN_DELTA = 0.95  # a point joins the Pareto front only with δ<1.25 >= this ...
MAX_MOVER_WRONG = 0.005  # ... and with at most this share of the planted unboxed mover confidently wrong (`mover_safe`)
TIME_TOL = 0.05  # seconds per image within 5 % of each other: the same time on the front
BAND_NAMES = ("0-10", "10-20", "20-40")
METRICS = ("coverage", "abs_0-10", "abs_10-20", "abs_20-40", "median_rel", "delta_1.25", "s_per_image",
           "s_per_set", "peak_mb")
MARKERS = "osD^vP*XhpH<>"


# --- points -------------------------------------------------------------------------------------


def _parse_value(v: str):
    return None if v.strip().lower() == "none" else _value(v.strip())


def factor_values(args) -> dict[str, list]:
    """factor -> values: the built-in ones (those that are StereoConfig fields, or context), then
    `--vary`, restricted to `--points`."""
    fields = StereoConfig.model_fields
    factors = {f: list(v) for f, v in FACTORS.items() if f == "context" or f in fields}
    for f in FACTORS.keys() - factors.keys():
        print(f"factor {f}: not a StereoConfig field, skipped")
    for spec in args.vary:
        name, _, values = spec.partition("=")
        if name != "context" and name not in fields:
            raise SystemExit(f"--vary {spec}: {name!r} is not a StereoConfig field ({', '.join(fields)})")
        factors[name] = [_parse_value(v) for v in values.split(",") if v.strip()]
    if args.points:
        unknown = set(args.points) - factors.keys()
        if unknown:
            raise SystemExit(f"--points: unknown factors {sorted(unknown)} (known: {', '.join(factors)})")
        factors = {f: factors[f] for f in args.points}
    return factors


def points(factors: dict[str, list], context: int) -> list[dict]:
    """The run points: the default first (factor "default"), then each factor's values other than
    the default's, each {factor, value, config (a full StereoConfig dump), context}. Values are
    validated here, before anything runs."""
    base = StereoConfig().model_dump()
    out = [{"factor": "default", "value": "default", "config": base, "context": context}]
    for f, values in factors.items():
        for v in values:
            if f == "context":
                cfg, ctx = base, int(v)
            else:
                cfg, ctx = StereoConfig(**{f: v}).model_dump(), context
            if (cfg, ctx) != (base, context):
                out.append({"factor": f, "value": v, "config": cfg, "context": ctx})
    return out


def default_value(factor: str, pt: dict):
    return pt["context"] if factor == "context" else pt["config"][factor]


# --- running ------------------------------------------------------------------------------------


def subsets(args) -> dict[str, dict]:
    """dataset -> its data subset (part of each result's key); a dataset without samples is left out."""
    out = {}
    if args.worlds_samples:
        out["worlds"] = {"root": str(args.worlds.resolve()), "split": args.split, "samples": args.worlds_samples,
                         "cameras": args.cameras or "all"}
    if args.kitti_frames:
        out["kitti360"] = {"root": str(args.kitti.resolve()), "frames": args.kitti_frames}
    return out


def run_key(dataset: str, pt: dict, subset: dict) -> str:
    return json.dumps({"dataset": dataset, "config": pt["config"], "context": pt["context"], "subset": subset},
                      sort_keys=True)


def _images(dataset: str, context: int, args):
    """`stereo_tune.image_sets` for one dataset at one context."""
    ns = Namespace(worlds=args.worlds, split=args.split, cameras=args.cameras, kitti=args.kitti, context=context,
                   worlds_samples=args.worlds_samples if dataset == "worlds" else [],
                   kitti_frames=args.kitti_frames if dataset == "kitti360" else [])
    return image_sets(ns)


def run_point(dataset: str, pt: dict, args) -> dict:
    """Stereo on every reference image of `dataset` for one point -> its metrics (module docstring)."""
    cfg = StereoConfig(**pt["config"])
    parts = ([], [], [])  # confidence, depth, ground truth on object pixels
    sets, peaks, last = [], [], None  # sets: seconds per image, grouped by sample
    for _, frames, k, gt, ground in _images(dataset, pt["context"], args):
        reset_peak()
        t0 = time.perf_counter()
        res = stereo_depth(frames, k, cfg)
        dt = time.perf_counter() - t0
        peaks.append(peak_mb())
        if frames is not last:
            sets.append([])
            last = frames
        sets[-1].append(dt)
        obj = np.isfinite(gt) & (gt > 0) & (gt < 40.0) & ~ground
        for lst, m in zip(parts, (res.confidence, res.depth, gt)):
            lst.append(np.asarray(m, np.float32)[obj])
    conf, depth, gt = (np.concatenate(p) for p in parts)
    return metrics(conf, depth, gt, sets, peaks)


def metrics(conf, depth, gt, sets: list[list[float]], peaks: list[float]) -> dict:
    rows = {r["band"]: r for r in band_rows("", conf, depth, gt, [DEFAULT_STEREO_CONFIDENCE])}
    total = rows["0-40 m"]
    out = {"images": sum(len(s) for s in sets), "object_pixels": total["object_pixels"],
           "coverage": total["coverage"], "median_rel": total["median_rel"], "delta_1.25": total["delta_1.25"],
           "s_per_image": float(np.mean([t for s in sets for t in s])),
           "s_per_set": float(np.mean([sum(s) for s in sets])),
           "peak_mb": float(np.nanmax(peaks)) if np.isfinite(peaks).any() else float("nan")}
    for b in BAND_NAMES:
        out[f"abs_{b}"] = rows[f"{b} m"]["median_abs_m"]
        out[f"coverage_{b}"] = rows[f"{b} m"]["coverage"]
    return out


def load_done(path: Path) -> dict[str, dict]:
    """key -> metrics of the results already in the JSON-lines file (a torn last line is ignored)."""
    done = {}
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            done[rec["key"]] = rec["metrics"]
    return done


def run_all(pts: list[dict], subs: dict[str, dict], path: Path, args) -> dict[str, dict]:
    """Every (point, dataset) not in `path` yet, appended to it as it finishes -> key -> metrics."""
    done = load_done(path)
    todo = [(pt, ds) for pt in pts for ds in subs]
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TimeRemainingColumn())
    with Progress(*columns) as bar, path.open("a") as fh:
        task = bar.add_task("stereo trade", total=len(todo))
        for pt, ds in todo:
            key = run_key(ds, pt, subs[ds])
            bar.update(task, description=f"{ds} {pt['factor']}={pt['value']}")
            if key not in done:
                done[key] = run_point(ds, pt, args)
                fh.write(json.dumps({"key": key, "dataset": ds, "factor": pt["factor"], "value": pt["value"],
                                     "metrics": done[key]}) + "\n")
                fh.flush()
                m = done[key]
                bar.console.print(f"{ds} {pt['factor']}={pt['value']}: coverage {100 * m['coverage']:.1f} %, "
                                  f"δ<1.25 {m['delta_1.25']:.3f}, {m['s_per_image']:.1f} s/image, "
                                  f"{m['peak_mb']:.0f} MB")
            bar.advance(task)
    return done


# --- analysis -----------------------------------------------------------------------------------


def pareto_front(seconds: list[float], coverage: list[float], eligible: list[bool], tol: float = TIME_TOL,
                 error: list[float] | None = None) -> list[int]:
    """Indices of the eligible points no other eligible point dominates, by increasing seconds. a
    dominates b: no slower, no less coverage and (with `error`) no more error, and better in one of
    them; times within `tol` (relative) of each other count as the same time (timing noise: a point
    whose images are the same as the default's, e.g. a context whose extra instants are never
    chosen, ties with it)."""
    idx = [i for i, ok in enumerate(eligible) if ok and math.isfinite(seconds[i]) and math.isfinite(coverage[i])
           and (error is None or math.isfinite(error[i]))]

    def dominates(a: int, b: int) -> bool:
        faster = seconds[a] < seconds[b] * (1 - tol)
        no_slower = seconds[a] <= seconds[b] * (1 + tol)
        no_worse = error is None or error[a] <= error[b]
        better = faster or coverage[a] > coverage[b] or (error is not None and error[a] < error[b])
        return no_slower and coverage[a] >= coverage[b] and no_worse and better

    front = [b for b in idx if not any(dominates(a, b) for a in idx if a != b)]
    return sorted(front, key=lambda i: (seconds[i], coverage[i]))


def mover_safe(pt: dict) -> tuple[bool, float]:
    """The issue's safety case, for a point's stereo factor: the analytic planted moving object
    without a box (tests/reconstruct/stereo/test_mvs.py's scene and settings, the point's StereoConfig field
    applied to them) -> (at most MAX_MOVER_WRONG of its pixels confidently wrong, that share).
    The default point: the test's settings. Factors that are no StereoConfig field, or that the
    small analytic images cannot take (scale, hypotheses: the tests sweep 128 x 96 images at scale
    1 over 64 planes), pass (NaN)."""
    from tests.reconstruct.stereo.test_mvs import BOX_Z, CFG, _confident_wrong, _moving_scene

    default = pt["factor"] == "default"  # the test's own settings
    if not default and (pt["factor"] not in StereoConfig.model_fields or pt["factor"] in ("scale", "hypotheses")):
        return True, math.nan
    frames, gt, on_box = _moving_scene({-2: (0.3, -0.8, BOX_Z), -1: (-0.2, 0.7, BOX_Z), 1: (0.4, -0.6, BOX_Z)},
                                       with_boxes=False)
    cfg = CFG if default else CFG.model_copy(update={pt["factor"]: pt["config"][pt["factor"]]})
    share = _confident_wrong(stereo_depth(frames, 0, cfg), gt, on_box) / on_box.sum()
    return bool(share <= MAX_MOVER_WRONG), float(share)


def table_rows(pts: list[dict], subs: dict[str, dict],
               done: dict[str, dict]) -> tuple[list[dict], dict[str, list[int]]]:
    """One row per point (factor, value, config, `<dataset> <metric>` columns, `<dataset> front`) and
    dataset -> the row indices on its Pareto front."""
    rows = [{"factor": pt["factor"], "value": pt["value"], "context": pt["context"], "config": pt["config"]}
            for pt in pts]
    safe = [mover_safe(pt) for pt in pts]
    for r, (_, share) in zip(rows, safe):
        r["mover_wrong"] = share
    fronts = {}
    for ds, sub in subs.items():
        ms = [done[run_key(ds, pt, sub)] for pt in pts]
        for r, m in zip(rows, ms):
            r.update({f"{ds} {k}": v for k, v in m.items()})
        secs, cov = [m["s_per_image"] for m in ms], [m["coverage"] for m in ms]
        ok = [m["delta_1.25"] >= MIN_DELTA and sf for m, (sf, _) in zip(ms, safe)]
        fronts[ds] = pareto_front(secs, cov, ok, error=[m.get("median_rel", math.nan) for m in ms])
        fronts[f"{ds} time_coverage"] = pareto_front(secs, cov, ok)
        for i, r in enumerate(rows):
            r[f"{ds} front"] = "yes" if i in fronts[ds] else ""
            r[f"{ds} front_time_coverage"] = "yes" if i in fronts[f"{ds} time_coverage"] else ""
    return rows, fronts


def describe_default(pt: dict, factors: dict[str, list]) -> str:
    return ", ".join(f"{f} {default_value(f, pt)}" for f in factors) or "StereoConfig()"


def plot(rows: list[dict], fronts: dict[str, list[int]], factors: dict[str, list], subs: dict, path: Path) -> None:
    """Coverage (%) against seconds per image (log), one panel per dataset (module docstring)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(subs), figsize=(7.5 * len(subs), 6), squeeze=False)
    for ax, ds in zip(axes[0], subs):
        _panel(ax, ds, rows, fronts[ds], factors, fronts.get(f"{ds} time_coverage", []))
        n = rows[0][f"{ds} images"]
        ax.set_title(f"{ds}: {n} reference image(s), one factor at a time")
    fig.suptitle(f"Plane-sweep stereo trade: confident (conf >= {DEFAULT_STEREO_CONFIDENCE:g}) object coverage "
                 f"0-40 m vs time\nhollow markers: δ<1.25 < {MIN_DELTA:g} or the planted unboxed mover let through "
                 f"(not eligible for the front)", fontsize=11)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _panel(ax, ds: str, rows: list[dict], front: list[int], factors: dict[str, list],
           time_coverage: list[int] = ()) -> None:
    from matplotlib.ticker import FuncFormatter

    x = np.array([r[f"{ds} s_per_image"] for r in rows], float)
    y = 100 * np.array([r[f"{ds} coverage"] for r in rows])
    none = [f"{r['factor']}={r['value']}" for r, c in zip(rows, y) if not c > 0]
    x = np.where(y > 0, x, np.nan)  # no depth at all (no source view): named in a note, not drawn
    if none:
        ax.text(0.99, 0.02, "0 % coverage (not drawn): " + ", ".join(none), transform=ax.transAxes, ha="right",
                fontsize=8)
    ok = np.array([r[f"{ds} delta_1.25"] >= MIN_DELTA and not r.get("mover_wrong", 0.0) > MAX_MOVER_WRONG
                   for r in rows])
    for j, f in enumerate(factors):
        idx = [0] + [i for i, r in enumerate(rows) if r["factor"] == f]
        idx.sort(key=lambda i: _order(default_value(f, rows[i])))
        color = f"C{j % 10}"
        if all(_order(default_value(f, rows[i]))[0] == 0 for i in idx):  # numbers: a line in value order
            ax.plot(x[idx], y[idx], "-", color=color, lw=0.8, alpha=0.5)
        for i in (i for i in idx if i != 0):
            ax.scatter(x[i], y[i], marker=MARKERS[j % len(MARKERS)], s=50, zorder=3, edgecolors=color,
                       facecolors=color if ok[i] else "none")
            ax.annotate(str(rows[i]["value"]), (x[i], y[i]), textcoords="offset points", xytext=(4, 4), fontsize=7,
                        color=color)
        ax.scatter([], [], marker=MARKERS[j % len(MARKERS)], color=color, label=f)
    ax.scatter(x[0], y[0], marker="*", s=300, zorder=4, facecolors="gold" if ok[0] else "none", edgecolors="k",
               label="default")
    if front:
        ax.scatter(x[front], y[front], s=260, facecolors="none", edgecolors="k", lw=1.2, zorder=5,
                   label=f"Pareto front: time, coverage, median rel. error (δ<1.25 >= {MIN_DELTA:g}, mover kept out)")
    if time_coverage:
        fx, fy = x[time_coverage], y[time_coverage]
        ax.step(np.r_[fx, np.nanmax(x)], np.r_[fy, fy[-1]], where="post", color="k", lw=1.0, ls=":", alpha=0.7,
                zorder=2, label="front of time and coverage alone")
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    lo, hi = ax.get_xlim()
    shown = range(2, 10) if hi / lo < 20 else (2, 5)  # minor labels: all within about a decade
    ax.xaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if round(v / 10 ** math.floor(math.log10(v)))
                                               in shown else ""))
    ax.tick_params(axis="x", which="minor", labelsize=7)
    ax.set_xlabel("seconds per image (log)")
    ax.set_ylabel("confident object coverage 0-40 m (%)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="best")


def _order(v):
    """Sort key for a factor's values: numbers by value, others (strings, None) after, by name."""
    return (0, float(v), "") if isinstance(v, (int, float)) and not isinstance(v, bool) else (1, 0.0, str(v))


def write_outputs(rows, fronts, factors, subs, args) -> None:
    header = ["factor", "value", "mover_wrong"] + [f"{ds} {m}" for ds in subs
                                                   for m in (*METRICS, "front", "front_time_coverage")]
    default = describe_default({"context": rows[0]["context"], "config": rows[0]["config"]}, factors)
    notes = (f"One factor at a time around the default ({default}; StereoConfig "
             f"{json.dumps(rows[0]['config'])}). Data: {json.dumps(subs)}; torch threads {args.threads}. "
             f"Confident: confidence >= {DEFAULT_STEREO_CONFIDENCE:g}; object pixels 0-40 m. coverage: confident "
             f"share of object pixels; abs_*: median |error| (m) per band; median_rel, delta_1.25: confident pixels "
             f"0-40 m; s_per_image, s_per_set (a sample's reference images), peak_mb. front: on the Pareto front "
             f"(min seconds per image, times within {100 * TIME_TOL:g} % tied, max coverage, min median_rel, among "
             f"delta_1.25 >= {MIN_DELTA:g} and mover_wrong <= {MAX_MOVER_WRONG:g}: the share of the planted unboxed "
             f"mover confidently wrong, tests/reconstruct/stereo/test_mvs.py's scene with the point's factor; NaN: not "
             f"applicable); "
             f"front_time_coverage: the same without the error. Plot: docs/{args.label}.png")
    write_results(args.label, rows, header, notes)
    plot(rows, fronts, factors, subs, DOCS / f"{args.label}.png")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--worlds", type=Path, default=WORLDS_DEFAULT)
    ap.add_argument("--split", default="test")
    ap.add_argument("--worlds-samples", type=_ints, default=[0, 1, 2, 3, 4, 5])
    ap.add_argument("--cameras", type=_ints, default=[])
    ap.add_argument("--kitti", type=Path, default=KITTI_DEFAULT)
    ap.add_argument("--kitti-frames", type=_ints, default=list(range(4, 16)))
    ap.add_argument("--context", type=int, default=DEFAULT_CONTEXT, help="the default point's ±K instants")
    ap.add_argument("--vary", action="append", default=[], help="field=v1,v2,... (repeatable)")
    ap.add_argument("--points", type=lambda s: [f for f in s.split(",") if f], default=[],
                    help="run only these factors (and the default)")
    ap.add_argument("--label", default="stereo_trade", help="output names (results/<label>.*, docs/<label>.png)")
    ap.add_argument("--fresh", action="store_true", help="forget the stored points and start over")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    factors = factor_values(args)
    pts = points(factors, args.context)
    subs = subsets(args)
    if not subs:
        ap.error("no data: give --worlds-samples and/or --kitti-frames")
    RESULTS.mkdir(parents=True, exist_ok=True)
    store = RESULTS / f"{args.label}_points.jsonl"
    if args.fresh:
        store.unlink(missing_ok=True)
    print(f"{len(pts)} points x {len(subs)} datasets; default: {describe_default(pts[0], factors)}")
    done = run_all(pts, subs, store, args)
    rows, fronts = table_rows(pts, subs, done)
    write_outputs(rows, fronts, factors, subs, args)
    for ds, front in fronts.items():
        names = [f"{rows[i]['factor']}={rows[i]['value']}" for i in front]
        which = "the front of time and coverage alone" if ds.endswith("time_coverage") else "the Pareto front"
        on = "on" if 0 in front else "NOT on"
        print(f"{ds.split()[0]}: the default is {on} {which} ({', '.join(names) or 'empty'})")


if __name__ == "__main__":
    main()
