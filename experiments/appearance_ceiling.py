"""How far the VoxSplat itself goes on the appearance benchmark at the shipped grid: the
Gaussians of a test world's ground-truth grid and its sky panorama, optimised directly on that
world's input views at T, against the shipped network's feed-forward prediction from the same grid
and images. Both are scored with `eval appearance`'s protocol (front cameras, moving actors masked)
at T, T+5 and T+10.

What is optimised is exactly what the network outputs (`appearance.fit_input_views`): the raw values
(V, M, 14) of every voxel's Gaussians and the panorama's features (the sky decoder stays as
trained), starting from the network's own prediction; Adam with a rate per kind of value, one
input view per step in camera order, the training loss (0.9 L1 + 1.0 alpha L1 + 0.1 SSIM) on all
input cameras at T. So the PSNR at T after the fit shows what the representation at this voxel
size, M and image size reaches with the same renderer (a lower bound on its best: a few hundred
steps of a local optimiser), against what the network reaches; T+5 and T+10 show how such a fit
carries to novel views. The same function is the converter's optional test-time fit (profile `appearance.fit_steps`), so
the early marks measure that knob's trade (PSNR against seconds).

Not part of `make bench` (about 10 min per world on 2 cores at the defaults).
Run: `python -m experiments.appearance_ceiling --data DIR [--checkpoint appearance-cpu-640] [--limit 2] [--steps 300]
[--level fine --coarsen 2 --name appearance_ceiling_0.2m]` (the last: 0.2 m voxels, 4 times the Gaussians)
with DIR a worlds dataset whose test split has the evaluation instants (`worlds generate --split test`).
Results: experiments/results/<name>.{json,md} and a plot docs/<name>.png (`--plot-only` redraws it).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from scube_sim.model.appearance.fit import FIT_RATES, fit_input_views
from scube_sim.model.appearance.losses import evaluate_item
from scube_sim.model.checkpoint import load_model
from scube_sim.model.config import stage_configs
from scube_sim.model.stages import get_stage

from .common import EXPERIMENTS_DIR, RESULTS, write_results

KEYS = ("psnr_t0", "psnr_t5", "psnr_t10", "ssim_t0", "ssim_t5", "ssim_t10", "psnr_sky_t0")


def scores(model, out: dict, item: dict) -> dict[str, float]:
    with torch.no_grad():
        res = evaluate_item(model, item, "front", out=out)
    return {k: float(np.mean(res[k])) for k in KEYS if k in res}


def fit(model, item: dict, steps: int, marks: set[int]) -> list[dict]:
    """Scores of the network's prediction for `item` (step 0) and of its test-time fit
    (`appearance.fit_input_views`) after each step in `marks`, with the fit's seconds so far."""
    with torch.no_grad():
        pred = model(item)
    rows = [{"step": 0, "seconds": 0.0, **scores(model, pred, item)}]
    t0 = time.perf_counter()
    paused = 0.0

    def hook(step: int, out: dict) -> None:
        nonlocal paused
        if step in marks:
            t = time.perf_counter()
            rows.append({"step": step, "seconds": round(t - t0 - paused, 1), **scores(model, out, item)})
            print(rows[-1], flush=True)
            paused += time.perf_counter() - t

    with Progress(TextColumn(f"fit {item['sample']}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()) as bar:
        task = bar.add_task("", total=steps)
        fit_input_views(model, pred, item, steps, on_step=lambda step, out: (hook(step, out), bar.advance(task)))
    return rows


PAPER_PSNR = {"psnr_t0": 25.90, "psnr_t5": 19.90, "psnr_t10": 18.78}  # SCube on Waymo, the paper's Table 1


def plot(rows: list[dict], path: Path) -> None:
    """PSNR at T, T+5, T+10 against the fit's seconds (the mean rows), the paper's figures dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mean = sorted((r for r in rows if r["sample"] == "mean"), key=lambda r: r["step"])
    fig, ax = plt.subplots(figsize=(6.4, 4))
    for (key, label), colour in zip((("psnr_t0", "T (input views)"), ("psnr_t5", "T+5"), ("psnr_t10", "T+10")),
                                    ("C0", "C1", "C2")):
        ax.plot([r["seconds"] for r in mean], [r[key] for r in mean], "o-", c=colour, label=label)
        for r in mean:
            ax.annotate(str(r["step"]), (r["seconds"], r[key]), textcoords="offset points", xytext=(3, -10), fontsize=7)
        ax.axhline(PAPER_PSNR[key], ls="--", c=colour, lw=1)
    ax.set_xlabel("seconds of the test-time fit per frame set (2 cores); labels: steps")
    ax.set_ylabel("PSNR, front cameras, moving actors masked [dB]")
    ax.set_title(f"Network prediction + fit to the input views ({len({r['sample'] for r in rows}) - 1} test worlds)\n"
                 "dashed: the paper's feed-forward SCube on Waymo", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="worlds dataset with a test split (evaluation instants)")
    ap.add_argument("--checkpoint", default="appearance-cpu-640")
    ap.add_argument("--split", default="test")
    ap.add_argument("--limit", type=int, default=2, help="the first N samples of the split")
    ap.add_argument("--samples", help="these sample indices instead, comma-separated (the rigs cycle in blocks of 4)")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--marks", default="100,200,300", help="the steps after which to score, comma-separated")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--level", choices=("coarse", "fine"), help="the ground-truth grid (default: the checkpoint's)")
    ap.add_argument("--coarsen", type=int, help="coarsen that grid by this factor (fine x 2: 0.2 m voxels)")
    ap.add_argument("--name", default="appearance_ceiling")
    ap.add_argument("--plot-only", action="store_true", help="redraw docs/<name>.png from experiments/results/<name>.json")
    args = ap.parse_args(argv)
    png = EXPERIMENTS_DIR.parent / "docs" / f"{args.name}.png"
    if args.plot_only:
        plot(json.loads((RESULTS / f"{args.name}.json").read_text())["rows"], png)
        return
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    stage = get_stage("appearance")
    model, run = load_model(stage, args.checkpoint)
    _, data_cfg = stage_configs(run, stage.model_config, stage.data_config)
    grid = {k: v for k, v in (("level", args.level), ("coarsen", args.coarsen)) if v is not None}
    data_cfg = data_cfg.model_copy(update={"eval_frames": True, **grid})
    ds = stage.dataset(Path(args.data), data_cfg, args.split, run.train.seed)
    rows = []
    indices = [int(i) for i in args.samples.split(",")] if args.samples else list(range(min(args.limit, len(ds))))
    for index in indices:
        item = ds[index]
        for r in fit(model, item, args.steps, {int(m) for m in args.marks.split(",")}):
            rows.append({"sample": item["sample"], "voxel_m": float(item["voxel_size"]), "gaussians": int(item["ijk"].shape[0]) * model.cfg.gaussians_per_voxel,
                         **{k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()}})
    for step in sorted({r["step"] for r in rows}):
        at = [r for r in rows if r["step"] == step]
        rows.append({"sample": "mean", "voxel_m": at[0]["voxel_m"], "gaussians": int(np.mean([r["gaussians"] for r in at])), "step": step,
                     "seconds": round(float(np.mean([r["seconds"] for r in at])), 1),
                     **{k: round(float(np.mean([r[k] for r in at if k in r])), 3) for k in KEYS if any(k in r for r in at)}})
    header = ["sample", "voxel_m", "gaussians", "step", "seconds", *[k for k in KEYS if any(k in r for r in rows)]]
    write_results(args.name, rows, header,
                  notes=f"checkpoint {args.checkpoint}; {args.split} split of {args.data}, samples {indices}; step 0 is the "
                        f"network's prediction, later steps the same Gaussians and panorama optimised on the input views "
                        f"at T (appearance.fit_input_views: one view per step; rates {FIT_RATES}; seconds: the fit alone); scored on the front cameras, moving actors masked")
    plot(rows, png)


if __name__ == "__main__":
    main()
