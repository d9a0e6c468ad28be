"""A trained geometry checkpoint's depth head, its 2D prior, and that prior added to the prediction.

1. **Depth**: each stride-s feature pixel's most likely depth bin (its centre, metres) against
   the depth map at the pixel's centre, on every valid pixel with depth in (0.1, 90) m: AbsRel,
   median relative error, delta < 1.25, and the median absolute error by range; and how sharp the
   softmax over the bins is (what Eq. 1 weighs the features with): its largest probability, its
   entropy (nats; uniform over D bins is ln D) and the probability on the true bin and within one
   bin of it.
2. **Grids** on the split (issue 11's metrics): the checkpoint's prediction, its 2D prior (its own
   depth unprojected into voxels, `GeometryNet.predict_from_depth`) and their union (the
   prediction plus the 2D prior's voxels it lacks, label 0).

Not part of `make bench` (minutes per split on 2 cores). Run:
`python -m experiments.geometry_depth --data DIR [--checkpoint geometry-coarse-cpu] [--split test]`.
Results: experiments/results/geometry_depth.{json,md}.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from .common import write_results

RANGES_M = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 90.0))


def measure(data: Path, checkpoint: str, split: str, limit: int | None = None) -> list[dict]:
    import torch
    from rich.progress import track

    from scube_sim.model.checkpoint import load_model
    from scube_sim.model.geometry.data import GeometryDataConfig
    from scube_sim.model.geometry.net import flat_keys
    from scube_sim.model.geometry.stage import grid_metrics
    from scube_sim.model.nn.lifting import depth_to_bin
    from scube_sim.model.stages import get_stage

    stage = get_stage("geometry")
    model, run = load_model(stage, checkpoint)
    model.eval()
    ds = stage.dataset(data, GeometryDataConfig(**run.data), split, 0)
    n = len(ds) if limit is None else min(limit, len(ds))
    cond = model.conditioner
    stride = cond.encoder.stride
    sharp = {"max_prob": [], "entropy_nats": [], "p_true_bin": [], "p_within_1_bin": []}
    est, truth, grids = [], [], {"prediction": [], "2D prior (own depth, unprojected)": [], "union": []}
    items = []
    with torch.no_grad():
        for i in track(range(n), description=f"{split}: depth and grids"):
            item = ds[i]
            out = cond.head(cond.encoder(item["images"]))
            probs = out[:, cond.cfg.feature_channels:].softmax(1)
            h, w = probs.shape[-2:]
            rows = torch.clamp(torch.arange(h) * stride + stride // 2, max=item["images"].shape[2] - 1)
            cols = torch.clamp(torch.arange(w) * stride + stride // 2, max=item["images"].shape[3] - 1)
            gt = item["depth"][:, rows][:, :, cols].double()
            ok = item["valid"][:, rows][:, :, cols] & torch.isfinite(gt) & (gt > 0.1) & (gt < 90.0)
            est.append(cond.bin_centres.double()[probs.argmax(1)][ok])
            truth.append(gt[ok])
            q = probs.permute(0, 2, 3, 1)[ok].double()  # (P, D) at the pixels with depth
            true_bin = depth_to_bin(gt[ok], cond.bin_edges).clamp(0, q.shape[1] - 1)
            near = (torch.arange(q.shape[1])[None] - true_bin[:, None]).abs() <= 1
            sharp["max_prob"].append(q.max(1).values)
            sharp["entropy_nats"].append(-(q * q.clamp_min(1e-30).log()).sum(1))
            sharp["p_true_bin"].append(q.gather(1, true_bin[:, None]).squeeze(1))
            sharp["p_within_1_bin"].append((q * near).sum(1))
            pred = model.predict(item)
            prior = model.predict_from_depth(item)
            dims = item["gt_grid"].dims
            extra = ~torch.isin(flat_keys(prior[0], dims), flat_keys(pred[0], dims))
            grids["prediction"].append(pred)
            grids["2D prior (own depth, unprojected)"].append(prior)
            grids["union"].append((torch.cat([pred[0], prior[0][extra]]), torch.cat([pred[1], prior[1][extra]])))
            items.append(item)
    p, g = torch.cat(est), torch.cat(truth)
    rel = (p - g).abs() / g
    ratio = torch.maximum(p / g, g / p)
    rows_out = [{"what": "depth, all", "pixels": len(g), "abs_rel": float(rel.mean()),
                 "median_rel": float(rel.median()), "delta_1.25": float((ratio < 1.25).double().mean()),
                 "median_abs_err_m": float((p - g).abs().median())}]
    for lo, hi in RANGES_M:
        m = (g >= lo) & (g < hi)
        if bool(m.any()):
            rows_out.append({"what": f"depth, {lo:g}-{hi:g} m", "pixels": int(m.sum()),
                             "abs_rel": float(rel[m].mean()), "median_rel": float(rel[m].median()),
                             "delta_1.25": float((ratio[m] < 1.25).double().mean()),
                             "median_abs_err_m": float((p[m] - g[m]).abs().median())})
    bins = cond.bin_centres.numel()
    rows_out.append({"what": f"depth softmax sharpness (uniform: max {1 / bins:.3f}, entropy {math.log(bins):.2f})",
                     "pixels": len(g), **{k: float(torch.cat(v).mean()) for k, v in sharp.items()}})
    for name, preds in grids.items():
        met = grid_metrics(preds, items, split=True)
        rows_out.append({"what": f"grid: {name}", **{k: met[k] for k in ("iou", "miou", "iou_visible",
                                                                          "iou_invisible", "chamfer_q50")}})
    return rows_out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path, help="a worlds dataset folder")
    ap.add_argument("--checkpoint", default="geometry-coarse-cpu", help="a geometry checkpoint (path or shipped name)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--limit", type=int, default=None, help="the first N samples only")
    ap.add_argument("--name", default="geometry_depth", help="the results' file name in experiments/results/")
    args = ap.parse_args(argv)
    rows = measure(args.data, args.checkpoint, args.split, args.limit)
    path = write_results(args.name, rows, ["what", "pixels", "abs_rel", "median_rel", "delta_1.25",
                                                  "median_abs_err_m", "max_prob", "entropy_nats", "p_true_bin",
                                                  "p_within_1_bin", "iou", "miou", "iou_visible",
                                                  "iou_invisible", "chamfer_q50"],
                         notes=f"checkpoint {args.checkpoint}, split {args.split}, {args.data}")
    print(path.read_text())


if __name__ == "__main__":
    main()
