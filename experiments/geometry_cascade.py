"""Coarse + fine against coarse only (issue 11), scored on the fine grid.

On one split, per sample: the coarse checkpoint's grid (0.8 m) with each voxel split into its
children at the fine voxel size (what the coarse level alone says at 0.2 m); the fine checkpoint
conditioned on that coarse prediction (the cascade the converter would run); the fine checkpoint
on the ground-truth coarse grid (the fine level alone: the cascade's bound with a perfect coarse
level); the fine VAE's decoding of a zero latent on the ground-truth coarse grid (the fine level
without images: its floor); and the ground-truth coarse grid split into children (what the coarse
truth says at 0.2 m without any fine model). Metrics are issue 11's
(`geometry.grid_metrics`: IoU, mIoU, seen / unseen IoU, voxel Chamfer in fine voxels) and the
seconds and peak resident memory (above the level's start) per sample.

Not part of `make bench`. Slow: a coarse grid split into children holds millions of fine voxels,
and scoring it (the visibility split and the voxel Chamfer distance's nearest-neighbour queries)
takes minutes per sample on 2 cores; start with `--limit`. Run:
`python -m experiments.geometry_cascade --data DIR --fine RUN/best.pt [--coarse geometry-coarse-cpu] [--split test]`.
Results: experiments/results/geometry_cascade.{json,md}.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from .common import write_results


def split_into_children(ijk, labels, factor: int):
    """(V, 3) voxels and (V,) labels -> their factor^3 children each (V * factor^3, 3), labels."""
    import torch

    r = torch.arange(factor)
    offs = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    kids = (ijk[:, None, :] * factor + offs[None]).reshape(-1, 3)
    return kids, labels.repeat_interleave(len(offs))


def zero_latent_grid(model, sites):
    """The fine VAE's decoding of a zero latent (the prior's mean) on the coarse sites (V, 3): the
    fine level without images, its floor given those sites. -> (ijk (N, 3), labels (N,))."""
    import torch

    from scube_sim.model.geometry.sparse_nets import decoded_voxels
    from scube_sim.model.nn.sparse import SparseTensor

    coords = torch.cat([torch.zeros(len(sites), 1, dtype=torch.int64), sites], 1)
    st = SparseTensor.from_coords(coords, torch.zeros(len(sites), model.cfg.vae.latent_channels), batch_size=1,
                                  stride=model.vae.stride)
    ijk, labels = decoded_voxels(model.vae.decode(st))
    return ijk[:, 1:], labels


def measure(data: Path, coarse_ck: str, fine_ck: str, split: str, limit: int | None = None) -> list[dict]:
    import torch
    from rich.progress import track

    from scube_sim.memory import peak_mb, reset_peak, rss_mb
    from scube_sim.model.checkpoint import load_model
    from scube_sim.model.geometry.data import GeometryDataConfig
    from scube_sim.model.geometry.stage import grid_metrics
    from scube_sim.model.stages import get_stage

    stage = get_stage("geometry")
    coarse, crun = load_model(stage, coarse_ck)
    fine, frun = load_model(stage, fine_ck)
    coarse.eval()
    fine.eval()
    fcfg = GeometryDataConfig(**{**frun.data, "crop": None})
    ccfg = GeometryDataConfig(**{**crun.data, "region": fcfg.region})
    factor = round(ccfg.voxel_size / fcfg.voxel_size)
    if abs(ccfg.voxel_size - fcfg.lift_voxel_size) > 1e-9:
        raise SystemExit(f"--coarse predicts {ccfg.voxel_size} m voxels; --fine's sites are {fcfg.lift_voxel_size} m")
    cds = stage.dataset(data, ccfg, split, 0)
    fds = stage.dataset(data, fcfg, split, 0)
    n = len(fds) if limit is None else min(limit, len(fds))
    names = ("coarse only, split into children", "coarse + fine (cascade)",
             "fine on the ground-truth coarse grid", "zero latent on the ground-truth coarse grid (no images)",
             "ground-truth coarse, split into children")
    preds = {k: [] for k in names}
    sec = {"coarse": [], "fine": []}
    peak = {"coarse": [], "fine": []}
    items = []
    with torch.no_grad():
        for i in track(range(n), description=f"{split}: coarse, then fine"):
            citem, fitem = cds[i], fds[i]
            if citem["sample"] != fitem["sample"]:
                raise SystemExit(f"sample {i}: {citem['sample']} against {fitem['sample']}")
            # each level's wall seconds and peak resident memory above its start (geometry.evaluate's)
            base = rss_mb() if reset_peak() else float("nan")
            t = time.perf_counter()
            cijk, clab = coarse.predict(citem)
            sec["coarse"].append(time.perf_counter() - t)
            peak["coarse"].append(peak_mb() - base)
            base = rss_mb() if reset_peak() else float("nan")
            t = time.perf_counter()
            preds["coarse + fine (cascade)"].append(fine.predict(fitem, coarse=(cijk, clab)))
            sec["fine"].append(time.perf_counter() - t)
            peak["fine"].append(peak_mb() - base)
            preds["coarse only, split into children"].append(split_into_children(cijk, clab, factor))
            preds["fine on the ground-truth coarse grid"].append(fine.predict(fitem))
            preds["zero latent on the ground-truth coarse grid (no images)"].append(
                zero_latent_grid(fine, fitem["coarse_gt_ijk"]))
            preds["ground-truth coarse, split into children"].append(
                split_into_children(fitem["coarse_gt_ijk"], fitem["coarse_gt_labels"], factor))
            items.append(fitem)
    rows = []
    for name in names:
        m = grid_metrics(preds[name], items, split=True)
        rows.append({"variant": name, **{k: m[k] for k in ("iou", "miou", "iou_visible", "iou_invisible",
                                                          "chamfer_q50", "chamfer_q90")}})
    rows[0]["s_per_sample"] = sum(sec["coarse"]) / n
    rows[1]["s_per_sample"] = (sum(sec["coarse"]) + sum(sec["fine"])) / n
    rows[0]["peak_mb_per_sample"] = max(peak["coarse"])
    rows[1]["peak_mb_per_sample"] = max(max(a, b) for a, b in zip(peak["coarse"], peak["fine"]))
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path, help="a worlds dataset folder")
    ap.add_argument("--coarse", default="geometry-coarse-cpu", help="a coarse-level geometry checkpoint")
    ap.add_argument("--fine", required=True, help="a fine-level geometry checkpoint")
    ap.add_argument("--split", default="test")
    ap.add_argument("--limit", type=int, default=None, help="the first N samples only")
    args = ap.parse_args(argv)
    rows = measure(args.data, args.coarse, args.fine, args.split, args.limit)
    path = write_results("geometry_cascade", rows, ["variant", "iou", "miou", "iou_visible", "iou_invisible",
                                                    "chamfer_q50", "chamfer_q90", "s_per_sample", "peak_mb_per_sample"],
                         notes=f"coarse {args.coarse}, fine {args.fine}, split {args.split}, {args.data}; "
                               f"scored on the fine grid")
    print(path.read_text())


if __name__ == "__main__":
    main()
