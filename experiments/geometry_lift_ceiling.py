"""What perfect depth can put into the coarse lifted volume: the ceiling of the images' direct evidence.

On one split, per feature stride s (8 is the cpu configs' encoder; 1 is every image pixel) and per
placement of a pixel's point along its ray, the coarse voxels (0.8 m) that the depth maps' own
depth puts a point in, each valid pixel at its centre:

- **bin centre**: the centre of the depth bin the depth falls in (64 bins, 0.1-90 m, linearly
  growing widths: Eq. 1's points with the oracle's one-hot weights, `lifting: oracle`);
- **exact depth**: the depth itself.

Reported: voxels per sample, precision (the share in a ground-truth voxel), recall of the
ground-truth voxels the cameras see (`visible_voxels`), and the IoU of the no-image floor (the mean
training scene, `ablate_geometry.mean_scene_grid`) before and after adding those voxels: how far
the images alone could lift a model above the floor if it read them perfectly and predicted
nothing else new.

Not part of `make bench` (a few minutes per split on 2 cores). Run:
`python -m experiments.geometry_lift_ceiling --data DIR [--split test] [--limit N]`.
Results: experiments/results/geometry_lift_ceiling.{json,md}.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .common import write_results

STRIDES = (8, 4, 1)
PLACEMENTS = ("bin centre", "exact depth")


def surface_voxels(item: dict, stride: int, placement: str):
    """(V,) long flat keys (LiftGrid order) of the coarse voxels the item's depth maps put a point
    in, one point per valid stride-`stride` pixel centre with depth in the bins' range."""
    import torch

    from scube_sim.model.nn.lifting import (
        depth_bin_centres,
        depth_bin_edges,
        depth_to_bin,
        feature_intrinsics,
        frustum_points,
    )

    centres, edges = depth_bin_centres(64), depth_bin_edges(64)
    grid, keys = item["gt_grid"], []
    for c in range(len(item["images"])):
        height, width = item["depth"][c].shape
        h, w = height // stride, width // stride
        rows, cols = torch.arange(h) * stride + stride // 2, torch.arange(w) * stride + stride // 2
        depth = item["depth"][c][rows][:, cols].double()
        bins = depth_to_bin(depth, edges)
        ok = (bins >= 0) & item["valid"][c][rows][:, cols]
        k = feature_intrinsics(item["intrinsics"][c], stride)
        pose = item["cam_to_chunk"][c].double()
        if placement == "bin centre":
            pts = frustum_points(k, item["distortion"][c], pose, h, w, centres)
            p = pts.gather(0, bins.clamp(min=0)[None, :, :, None].expand(1, h, w, 3))[0]
        else:  # the camera centre plus the depth times the ray at camera z = 1
            ends = frustum_points(k, item["distortion"][c], pose, h, w, torch.tensor([0.0, 1.0]))
            p = ends[0] + (ends[1] - ends[0]) * torch.where(ok, depth, torch.zeros_like(depth))[..., None]
        index, inside = grid.voxel_index(p)
        keys.append(index[inside & ok])
    return torch.unique(torch.cat(keys))


def measure(data: Path, split: str, limit: int | None, floor_share: float, floor_samples: int) -> list[dict]:
    import numpy as np
    import torch
    from rich.progress import track

    from scube_sim.model.geometry.metrics import visible_voxels, voxel_iou
    from scube_sim.model.geometry.net import flat_keys
    from scube_sim.model.stages import get_stage

    from .ablate_geometry import mean_scene, mean_scene_grid

    share, mode, cfg = mean_scene(data, floor_samples)
    floor, _ = mean_scene_grid(share, mode, floor_share)
    ds = get_stage("geometry").dataset(data, cfg.model_copy(update={"image_scale": 0.67}), split, 0)
    n = len(ds) if limit is None else min(limit, len(ds))
    acc = {(s, p): [] for s in STRIDES for p in PLACEMENTS}
    floor_iou = []
    for i in track(range(n), description=f"{split}: depth-map voxels"):
        item = ds[i]
        grid, gt = item["gt_grid"], item["gt_ijk"]
        dims = grid.dims
        gt_keys = flat_keys(gt, dims)
        seen = visible_voxels(gt, grid.voxel_size, grid.origin, item["intrinsics"], item["distortion"],
                              item["cam_to_chunk"], item["depth"], item["image_size"])
        floor_iou.append(voxel_iou(floor, gt))
        floor_keys = flat_keys(floor, dims)
        for (stride, placement), rows in acc.items():
            keys = surface_voxels(item, stride, placement)
            both = torch.unique(torch.cat([floor_keys, keys]))
            ijk = torch.stack([both // (dims[1] * dims[2]), (both // dims[2]) % dims[1], both % dims[2]], 1)
            rows.append((len(keys), float(torch.isin(keys, gt_keys).double().mean()) if len(keys) else np.nan,
                         float(torch.isin(gt_keys[torch.from_numpy(seen)], keys).double().mean()),
                         voxel_iou(ijk, gt)))
    out = []
    for (stride, placement), rows in acc.items():
        r = np.array(rows, np.float64)
        out.append({"stride": stride, "placement": placement, "voxels_per_sample": float(r[:, 0].mean()),
                    "precision": float(np.nanmean(r[:, 1])), "recall_seen_gt": float(r[:, 2].mean()),
                    "floor_iou": float(np.mean(floor_iou)), "floor_plus_voxels_iou": float(r[:, 3].mean())})
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path, help="a worlds dataset folder")
    ap.add_argument("--split", default="test")
    ap.add_argument("--limit", type=int, default=None, help="the first N samples only")
    ap.add_argument("--floor-share", type=float, default=0.4,
                    help="the floor's share (ablate_geometry picks 0.4 on the val split)")
    ap.add_argument("--floor-samples", type=int, default=60, help="training chunks the floor averages")
    args = ap.parse_args(argv)
    rows = measure(args.data, args.split, args.limit, args.floor_share, args.floor_samples)
    path = write_results("geometry_lift_ceiling", rows, list(rows[0]),
                         notes=f"{args.split} split of {args.data}, coarse 0.8 m voxels, images at 0.67 of the "
                               f"stored size, the floor: share >= {args.floor_share} of {args.floor_samples} "
                               f"training chunks")
    print(path.read_text())


if __name__ == "__main__":
    main()
