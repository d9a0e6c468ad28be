"""The geometry stage's comparisons and trades (issue 11), coarse level.

1. **Variants at one budget**: each trained from scratch for the same `--steps` from the shipped
   config (`scube_sim/model/configs/geometry-coarse.yaml`), seed 0, on the same frozen structure
   VAE (`--vae`), then evaluated on `--eval-split`: the latent diffusion with depth-weighted
   lifting (Eq. 1), the same with the broadcast lifting (the paper's ablation), the
   deterministic single-step predictor, the diffusion lifting with the depth maps' own bins
   (`lifting: oracle`, an upper bound that isolates the 3D prior from the depth estimate), the
   diffusion on the frozen ImageNet EfficientNet-Lite0 instead of the from-scratch CNN, the
   diffusion at a lower image resolution, the 2D-prior
   baseline (the diffusion variant's own depth head unprojected into voxels, no 3D prior) and a
   floor without images (the mean training scene).
2. **DDIM steps** (1, 5, 10, 25, 50) of the diffusion variant (or `--checkpoint`): IoU against
   seconds and peak memory per sample, a table and a Pareto plot (docs/geometry_trade.png).
3. **Image resolution and voxel size** (`--scales 0.33 0.67 1.0`, alone): the shipped predictor's
   config (`geometry-coarse-predictor.yaml`) trained for `--steps` at each image scale, IoU against
   seconds and peak memory per sample (geometry_resolution.{json,md}); plotted with the output
   voxel size's trade, 0.8 m (coarse only) against 0.2 m (coarse + fine), from
   `experiments.geometry_cascade`'s results where they exist (docs/geometry_resolution_trade.png).
4. **Lifting at two feature strides** (`--lifting`, alone): the shipped predictor's config
   trained for `--steps` with depth-weighted (Eq. 1) and broadcast lifting, at the image
   encoder's stride 8 (shipped) and 4 (down to 8 and back up: the same context), each with its own depth head's 2D-prior baseline
   (geometry_lifting.{json,md}). `experiments.geometry_lift_ceiling` bounds what a finer stride can add.
   With `--refine`: the same at stride 8 with the occupancy refiner (`refine: true`, the lifted
   volume read again at the voxels' own resolution after the decoder), depth against broadcast
   lifting and the oracle depth's upper bound (geometry_lifting_refined.{json,md}). `--name`
   writes the results under another name (a longer budget beside the 400-step tables) and
   `--baseline CHECKPOINT` evaluates a trained model in the same command (the shipped predictor
   beside the variants retrained at its own budget).

Not part of `make bench` (it trains for hours on 2 cores). Run:
`python -m experiments.ablate_geometry --data DIR --vae VAE.pt [--steps 600] [--work experiments/.cache/ablate_geometry]`
Each training is resumable and each row is kept in --work once measured: a rerun continues where
the last one stopped. Results:
experiments/results/geometry_ablation.{json,md} and geometry_ddim.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import yaml

from .common import EXPERIMENTS_DIR, RESULTS, write_results

REPO = Path(__file__).resolve().parents[1]
VARIANTS = {
    "diffusion": {},
    "broadcast lifting": {"model": {"lifting": "broadcast"}},
    "single-step predictor": {"model": {"mode": "predictor"}},
    "diffusion, oracle depth (upper bound)": {"model": {"lifting": "oracle"}},
    "diffusion, EfficientNet-Lite0 (ImageNet, frozen)": {
        "model": {"encoder": {"kind": "efficientnet-lite0", "channels": 64, "stride": 8, "freeze_backbone": True}}},
    "diffusion, half resolution": {"data": {"image_scale": 0.33}},
    "diffusion, mean lifting": {"model": {"lift_norm": "mean"}},
    "diffusion, oracle depth, mean lifting": {"model": {"lifting": "oracle", "lift_norm": "mean"}},
    "predictor, decoded loss, mean lifting": {"model": {"mode": "predictor", "predictor_loss": "decoded",
                                                        "lift_norm": "mean"}},
    "predictor, decoded loss, oracle depth, mean lifting": {
        "model": {"mode": "predictor", "predictor_loss": "decoded", "lift_norm": "mean", "lifting": "oracle"}},
}
DDIM_STEPS = (1, 5, 10, 25, 50)
# Image scales of the resolution trade, of the stored images (the worlds store 0.25 of each rig's
# size: 480 x 320 for the Waymo rig); the shipped config uses 0.67.
IMAGE_SCALES = (0.33, 0.67, 1.0)
# (feature stride, lifting) of the lifting comparison, the most informative first
LIFTING_VARIANTS = ((4, "depth"), (8, "broadcast"), (8, "depth"), (4, "broadcast"))
# with the refiner: the lifting pair, then the depth maps' own bins (an upper bound: is it the
# depth estimate or the 3D side that holds the visible surfaces back?)
REFINE_VARIANTS = ((8, "depth"), (8, "broadcast"), (8, "oracle"))


_EVAL_KEYS = ("iou", "miou", "iou_visible", "iou_invisible", "chamfer_q50", "chamfer_q90", "seconds_per_sample",
              "peak_mb_per_sample")


def _config(base: dict, variant: dict, steps: int, vae: str) -> dict:
    cfg = yaml.safe_load(yaml.safe_dump(base))
    for section, values in variant.items():
        cfg[section].update(values)
    cfg["model"]["vae_checkpoint"] = vae
    cfg["train"].update(steps=steps, checkpoint_every=25)
    return cfg


def _cached_row(args, tag: str, measure) -> dict:
    """The row `measure()` gives, kept in --work as TAG.row.json so a rerun does not measure twice."""
    path = Path(args.work) / f"{tag}.row.json"
    if path.is_file():
        return json.loads(path.read_text())
    row = measure()
    path.write_text(json.dumps(row))
    return row


def _train_and_evaluate(stage, name: str, cfg: dict, args, rows: list) -> Path:
    from scube_sim.model.checkpoint import load_checkpoint
    from scube_sim.model.config import load_config
    from scube_sim.model.evaluate import evaluate
    from scube_sim.model.trainer import LAST, train

    tag = "".join(c for c in name if c.isalnum() or c in " -").replace(" ", "-")
    work = Path(args.work)
    cfg_path = work / f"{tag}.yaml"
    cfg_path.write_text(yaml.safe_dump(cfg))
    run_dir = work / tag
    timing = run_dir / "timing.json"
    resume = (run_dir / LAST).is_file()
    start = load_checkpoint(run_dir / LAST)["step"] if resume else 0
    t0 = time.perf_counter()
    res = train(stage, load_config(str(cfg_path)), args.data, run_dir, resume=resume, progress=True)
    # seconds per step over the sessions that were timed (a killed session's steps are not)
    took = json.loads(timing.read_text()) if timing.is_file() else {"train_s": 0.0, "steps_timed": 0}
    if res.step > start:
        took = {"train_s": took["train_s"] + time.perf_counter() - t0, "steps_timed": took["steps_timed"] + res.step - start}
        timing.write_text(json.dumps(took))

    def measure():
        m = evaluate(stage, res.last, args.data, split=args.eval_split, progress=True)
        per_step = took["train_s"] / took["steps_timed"] if took["steps_timed"] else float("nan")
        return {"variant": name, "steps": res.step, "s_per_step": round(per_step, 2),
                **{k: round(v, 4) for k, v in m.items() if k in _EVAL_KEYS}}

    rows.append(_cached_row(args, tag, measure))
    return res.last


def vae_of(checkpoint: str, template: str, work: Path) -> Path:
    """The frozen structure VAE inside a trained conditional geometry model, written as a
    `geometry-vae` checkpoint in `work` with the run record of `template` (a geometry-vae
    checkpoint of the same VAE config), so that a variant retrained beside that model starts from
    the very VAE it was trained with (the shipped predictor keeps its first-run VAE)."""
    from scube_sim.model.checkpoint import load_checkpoint, resolve_checkpoint, save_checkpoint

    src, tpl = (load_checkpoint(resolve_checkpoint(c)) for c in (checkpoint, template))
    if src.get("stage") != "geometry" or tpl.get("stage") != "geometry-vae":
        raise SystemExit(f"--vae-of {checkpoint} with --vae {template}: a 'geometry' and a 'geometry-vae' "
                         f"checkpoint expected, got {src.get('stage')!r} and {tpl.get('stage')!r}")
    weights = {k: v for k, v in src["model"].items() if k.startswith("vae.")}
    if set(weights) != set(tpl["model"]):
        raise SystemExit(f"--vae-of {checkpoint}: its VAE's weights are not those of --vae {template}'s network")
    out = work / f"vae-of-{Path(str(checkpoint)).name}.pt"
    save_checkpoint(out, {**tpl, "model": weights, "exported_from": f"{checkpoint} (its frozen VAE)"})
    return out


def checkpoint_row(checkpoint: Path, args) -> dict:
    """A trained model (a path or a shipped checkpoint's name) evaluated on the eval split."""
    from scube_sim.model.evaluate import evaluate
    from scube_sim.model.stages import get_stage

    m = evaluate(get_stage("geometry"), checkpoint, args.data, split=args.eval_split, progress=True)
    return {"variant": f"trained model {checkpoint}", "steps": "", "s_per_step": "",
            **{k: round(v, 4) for k, v in m.items() if k in _EVAL_KEYS}}


def depth_prior_row(checkpoint: Path, args) -> dict:
    """The 2D-prior baseline of a trained model's depth head on the eval split."""
    import torch

    from scube_sim.model.checkpoint import load_model
    from scube_sim.model.geometry.data import GeometryDataConfig
    from scube_sim.model.geometry.stage import grid_metrics
    from scube_sim.model.stages import get_stage

    stage = get_stage("geometry")
    model, run = load_model(stage, checkpoint)
    data_cfg = GeometryDataConfig(**run.data)
    ds = stage.dataset(Path(args.data), data_cfg, args.eval_split, 0)
    preds, items = [], []
    with torch.no_grad():
        for i in range(len(ds)):
            item = ds[i]
            preds.append(model.predict_from_depth(item))
            items.append(item)
    m = grid_metrics(preds, items, split=True)
    return {"variant": "2D prior (own depth, unprojected)", "steps": "", "s_per_step": "",
            **{k: round(v, 4) for k, v in m.items() if k in ("iou", "iou_visible", "iou_invisible", "chamfer_q50",
                                                          "chamfer_q90")}}


def mean_scene(data, samples: int):
    """The first `samples` training chunks' coarse grids stacked: (share (X, Y, Z) float the fraction
    of chunks occupying each voxel, mode (X, Y, Z) long its most frequent label, grid config)."""
    import numpy as np

    from scube_sim.labels import NUM_LABELS
    from scube_sim.model.geometry.data import GeometryDataConfig
    from scube_sim.model.stages import get_stage

    cfg = GeometryDataConfig(level="coarse", voxel_size=0.8)
    train = get_stage("geometry").dataset(Path(data), cfg, "train", 0)
    n = min(len(train), samples)
    counts = None
    for i in range(n):
        item = train[i]
        if counts is None:
            counts = np.zeros((*(int(d) for d in item["gt_grid"].dims), NUM_LABELS), np.int32)
        ijk, lab = item["gt_ijk"].numpy(), item["gt_labels"].numpy()
        np.add.at(counts, (ijk[:, 0], ijk[:, 1], ijk[:, 2], lab), 1)
    return counts.sum(-1) / n, counts.argmax(-1), cfg


def mean_scene_grid(share, mode, q: float):
    """The floor without images: voxels occupied in at least a share q of the chunks, with their
    most frequent label -> (ijk (V, 3) long, labels (V,) long)."""
    import numpy as np
    import torch

    ijk = np.argwhere(share >= q)
    return torch.from_numpy(ijk).long(), torch.from_numpy(mode[tuple(ijk.T)]).long()


def mean_scene_row(args) -> dict:
    """A floor without images: every voxel occupied in at least a share q of the first
    `--mean-scene-samples` training chunks (q picked for the best IoU on the val split) with its
    most frequent training label."""
    from scube_sim.model.geometry.stage import grid_metrics
    from scube_sim.model.stages import get_stage

    stage = get_stage("geometry")
    share, mode, cfg = mean_scene(args.data, args.mean_scene_samples)

    def items(split):
        ds = stage.dataset(Path(args.data), cfg, split, 0)
        return [ds[i] for i in range(len(ds))]

    val = items("val")
    qs = [0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7]
    best_q = max(qs, key=lambda q: grid_metrics([mean_scene_grid(share, mode, q)] * len(val), val,
                                                 split=False)["iou"])
    ev = items(args.eval_split)
    m = grid_metrics([mean_scene_grid(share, mode, best_q)] * len(ev), ev, split=True)
    return {"variant": f"mean training scene (no images, share >= {best_q})", "steps": "", "s_per_step": "",
            **{k: round(v, 4) for k, v in m.items() if k in ("iou", "miou", "iou_visible", "iou_invisible",
                                                          "chamfer_q50", "chamfer_q90")}}


def ddim_trade(checkpoint: Path, args) -> list[dict]:
    """IoU, seconds and peak memory per sample against the number of DDIM steps."""
    from scube_sim.model.checkpoint import load_model
    from scube_sim.model.evaluate import evaluate_model
    from scube_sim.model.geometry.data import GeometryDataConfig
    from scube_sim.model.stages import get_stage

    stage = get_stage("geometry")
    model, run = load_model(stage, checkpoint)
    ds = stage.dataset(Path(args.data), GeometryDataConfig(**run.data), args.eval_split, 0)
    rows = []
    for steps in DDIM_STEPS:
        def measure():
            model.cfg = model.cfg.model_copy(update={"sample_steps": steps})
            m = evaluate_model(stage, model, ds, batch_size=1, progress=True)
            return {"ddim_steps": steps, "iou": round(m["iou"], 4), "miou": round(m["miou"], 4),
                    "seconds_per_sample": round(m["seconds_per_sample"], 3),
                    "peak_mb_per_sample": round(m["peak_mb_per_sample"], 1)}

        rows.append(_cached_row(args, f"ddim-{steps}-{checkpoint.parent.name}", measure))
    return rows


def resolution_trade(stage, args) -> list[dict]:
    """The shipped predictor's config trained for --steps at each of --scales, evaluated as a variant."""
    base = yaml.safe_load((REPO / "scube_sim/model/configs/geometry-coarse-predictor.yaml").read_text())
    rows: list[dict] = []
    for scale in args.scales:
        name = f"predictor, image scale {scale:g}"
        _train_and_evaluate(stage, name, _config(base, {"data": {"image_scale": scale}}, args.steps, args.vae),
                            args, rows)
        rows[-1]["image_scale"] = scale
    return rows


def lifting_trade(stage, args) -> list[dict]:
    """The shipped predictor's config trained for --steps per (stride, lifting) of
    LIFTING_VARIANTS; each depth-lifting variant followed by its own depth head's 2D prior."""
    base = yaml.safe_load((REPO / "scube_sim/model/configs/geometry-coarse-predictor.yaml").read_text())
    rows: list[dict] = []
    variants = REFINE_VARIANTS if args.refine else LIFTING_VARIANTS
    if args.baseline:
        rows.append(_cached_row(args, "baseline", lambda: checkpoint_row(Path(args.baseline), args)))
    for stride, lifting in variants:
        name = f"predictor, stride {stride}, {lifting} lifting" + (", refined" if args.refine else "")
        if args.only and name not in args.only:
            continue
        # a finer map keeps the shipped encoder's context: down to stride 8 and back up
        encoder = {**base["model"]["encoder"], "stride": stride, **({"context_stride": 8} if stride < 8 else {})}
        model = {"encoder": encoder, "lifting": lifting, **({"refine": True} if args.refine else {})}
        ck = _train_and_evaluate(stage, name, _config(base, {"model": model}, args.steps, args.vae), args, rows)
        rows[-1].update(stride=stride, lifting=lifting)
        if lifting == "depth":
            tag = f"2d-prior-stride-{stride}" + ("-refined" if args.refine else "")
            rows.append({**_cached_row(args, tag, lambda: depth_prior_row(ck, args)), "stride": stride,
                         "lifting": "own depth, unprojected"})
    return rows


def _pareto(xs: list[float], ys: list[float]) -> list[bool]:
    """Which points no other point beats: one with x <= and y >= (cost down, IoU up), one strictly."""
    pts = list(zip(xs, ys))
    return [not any(x2 <= x and y2 >= y and (x2, y2) != (x, y) for x2, y2 in pts) for x, y in pts]


def plot_resolution_trade(rows: list[dict], cascade: list[dict], path: Path) -> Path:
    """IoU against seconds and peak memory per sample: image scale (coarse IoU, top) and output voxel
    size (scored on the 0.2 m grid, bottom, where `cascade` rows exist); Pareto-optimal points filled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    voxel = [dict(r, label={"coarse only, split into children": "0.8 m (coarse only)",
                            "coarse + fine (cascade)": "0.2 m (coarse + fine)"}[r["variant"]])
             for r in cascade if r["variant"] in ("coarse only, split into children", "coarse + fine (cascade)")]
    panels = [(rows, "coarse IoU (0.8 m)", lambda r: f"scale {r['image_scale']:g}", "image resolution")]
    if voxel:
        panels.append((voxel, "IoU on the 0.2 m grid", lambda r: r["label"], "output voxel size"))
    fig, axes = plt.subplots(len(panels), 2, figsize=(9, 3.4 * len(panels)), squeeze=False)
    for (data, ylabel, name, title), ax_row in zip(panels, axes):
        for a, key, xlabel in ((ax_row[0], ("seconds_per_sample", "s_per_sample"), "seconds per sample (2 cores)"),
                               (ax_row[1], ("peak_mb_per_sample",), "peak resident memory rise per sample (MB)")):
            pts = [(next(r[k] for k in key if k in r), r["iou"], name(r)) for r in data]
            front = _pareto([p[0] for p in pts], [p[1] for p in pts])
            for (x, y, label), best in zip(pts, front):
                a.plot(x, y, "o", color="C0", markerfacecolor="C0" if best else "none")
                a.annotate(label, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
            a.set_xlabel(xlabel)
            a.set_ylabel(ylabel)
            a.margins(x=0.3, y=0.15)  # room for the labels
            a.set_title(f"{title} (filled: Pareto-optimal)", fontsize=9)
            a.grid(alpha=0.3)
    return save_png(fig, "geometry stage: image resolution and voxel size against IoU, time and memory", path)


def plot_trade(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    for a, key, label in ((ax[0], "seconds_per_sample", "seconds per sample (2 cores)"),
                          (ax[1], "peak_mb_per_sample", "peak resident memory rise per sample (MB)")):
        xs, ys = [r[key] for r in rows], [r["iou"] for r in rows]
        # time grows with the steps, so a line reads along it; peak memory does not: points only
        a.plot(xs, ys, "o-" if key == "seconds_per_sample" else "o")
        for r, x, y in zip(rows, xs, ys):
            a.annotate(str(r.get("ddim_steps", r.get("variant"))), (x, y), textcoords="offset points", xytext=(4, 4))
        a.set_xlabel(label)
        a.set_ylabel("coarse IoU")
        a.grid(alpha=0.3)
    return save_png(fig, "geometry stage: DDIM steps against IoU, time and memory", path)


def save_png(fig, title: str, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> None:
    from scube_sim.model.stages import get_stage

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--vae", required=True, help="the coarse structure VAE's checkpoint (geometry-vae run)")
    ap.add_argument("--steps", type=int, default=600, help="training steps of every variant (the budget)")
    ap.add_argument("--work", default=str(EXPERIMENTS_DIR / ".cache" / "ablate_geometry"))
    ap.add_argument("--eval-split", default="test")
    ap.add_argument("--only", nargs="*", default=None,
                    help="variants to run (default: all; with --lifting, e.g. 'predictor, stride 8, depth lifting')")
    ap.add_argument("--mean-scene-samples", type=int, default=100, help="training chunks the no-image floor averages")
    ap.add_argument("--checkpoint", default=None, help="the DDIM trade on this checkpoint instead of the diffusion variant's")
    ap.add_argument("--scales", nargs="+", type=float, default=None,
                    help=f"run only the image-resolution trade at these image scales (e.g. {' '.join(map(str, IMAGE_SCALES))})")
    ap.add_argument("--lifting", action="store_true",
                    help="run only the lifting comparison (depth vs broadcast at feature strides 4 and 8)")
    ap.add_argument("--refine", action="store_true",
                    help="with --lifting: depth vs broadcast vs oracle depth at stride 8, each with the occupancy refiner")
    ap.add_argument("--vae-of", default=None,
                    help="the frozen VAE's weights from inside this trained geometry model (a path or a shipped name); --vae then "
                         "only gives the VAE's run record")
    ap.add_argument("--name", default=None, help="with --lifting: the results' file name in experiments/results/")
    ap.add_argument("--baseline", default=None,
                    help="with --lifting: also evaluate this trained checkpoint (a path or a shipped name)")
    args = ap.parse_args(argv)
    stage = get_stage("geometry")
    Path(args.work).mkdir(parents=True, exist_ok=True)
    if args.vae_of:
        args.vae = str(vae_of(args.vae_of, args.vae, Path(args.work)))
    if args.refine and not args.lifting:
        ap.error("--refine goes with --lifting")
    if args.lifting:
        rows = lifting_trade(stage, args)
        name = args.name or "geometry_lifting" + ("_refined" if args.refine else "")
        write_results(name, rows, list(dict.fromkeys(k for r in rows for k in r)),
                      notes=f"the shipped predictor's config{', refine: true' if args.refine else ''}, "
                            f"{args.steps} steps each, frozen VAE {args.vae}, "
                            f"{args.eval_split} split, {args.data}")
        return
    if args.scales:
        rows = resolution_trade(stage, args)
        write_results("geometry_resolution", rows, list(rows[0]),
                      notes=f"the shipped predictor's config, {args.steps} steps at each image scale, frozen VAE "
                            f"{args.vae}, {args.eval_split} split, {args.data}")
        cascade = RESULTS / "geometry_cascade.json"
        plot_resolution_trade(rows, json.loads(cascade.read_text())["rows"] if cascade.is_file() else [],
                              REPO / "docs" / "geometry_resolution_trade.png")
        return
    base = yaml.safe_load((REPO / "scube_sim/model/configs/geometry-coarse.yaml").read_text())
    rows, diffusion_ck = [], None
    if not args.only or "mean training scene" in args.only:
        rows.append(_cached_row(args, "mean-training-scene", lambda: mean_scene_row(args)))
    for name, variant in VARIANTS.items():
        if args.only and name not in args.only:
            continue
        ck = _train_and_evaluate(stage, name, _config(base, variant, args.steps, args.vae), args, rows)
        if name == "diffusion":
            diffusion_ck = ck
            rows.append(_cached_row(args, "2d-prior", lambda: depth_prior_row(ck, args)))
    if rows:
        columns = list(dict.fromkeys(k for r in rows for k in r))  # every row's keys, first seen first
        write_results("geometry_ablation", rows, columns,
                      notes=f"coarse level, {args.steps} steps each on the same frozen VAE, {args.eval_split} split")
    trade_ck = Path(args.checkpoint) if args.checkpoint else diffusion_ck
    if trade_ck is not None:
        trade = ddim_trade(trade_ck, args)
        write_results("geometry_ddim", trade, list(trade[0]), notes=f"checkpoint {trade_ck}, {args.eval_split} split")
        plot_trade(trade, REPO / "docs" / "geometry_trade.png")


if __name__ == "__main__":
    main()
