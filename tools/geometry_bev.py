"""Bird's-eye views of the geometry stage's predictions beside the ground truth.

For each chosen sample of a worlds split: the ground-truth grid and each checkpoint's prediction
(its own sampler settings, the sample's fixed seed), drawn as the height of the top-most voxel
per column (box voxels; the cameras sit at the left edge's middle, looking right).

    python tools/geometry_bev.py --data DIR CK [CK ...] --split val --samples 0 5 -o docs/x.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def height_map(ijk: np.ndarray, dims: tuple[int, int, int]) -> np.ndarray:
    """(V, 3) voxel indices -> (X, Y) index of the top-most voxel per column, NaN where empty."""
    out = np.full(dims[:2], np.nan)
    order = np.argsort(ijk[:, 2], kind="stable")  # the last write per column is the highest
    out[ijk[order, 0], ijk[order, 1]] = ijk[order, 2]
    return out


def main(argv=None) -> None:
    import torch
    from matplotlib.figure import Figure

    from scube_sim.atomic import atomic_path
    from scube_sim.model.checkpoint import load_model
    from scube_sim.model.geometry.data import GeometryDataConfig
    from scube_sim.model.geometry.stage import sample_seed
    from scube_sim.model.stages import get_stage

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="+", help="geometry checkpoints (run files or shipped names)")
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--samples", type=int, nargs="+", default=[0])
    ap.add_argument("--labels", nargs="*", default=None, help="a column title per checkpoint")
    ap.add_argument("-o", "--output", required=True)
    args = ap.parse_args(argv)
    stage = get_stage("geometry")
    models = [load_model(stage, ck) for ck in args.checkpoints]
    titles = args.labels or [Path(ck).parent.name or str(ck) for ck in args.checkpoints]
    ds = stage.dataset(Path(args.data), GeometryDataConfig(**models[0][1].data), args.split, 0)
    cols = 1 + len(models)
    fig = Figure(figsize=(3.6 * cols, 3.6 * len(args.samples)))
    axes = np.atleast_2d(fig.subplots(len(args.samples), cols))
    for row, index in zip(axes, args.samples):
        item = ds[index]
        dims = tuple(int(d) for d in item["gt_grid"].dims)
        grids = [("ground truth", item["gt_ijk"].numpy())]
        for (model, _), title in zip(models, titles):
            with torch.no_grad():
                ijk, _ = model.predict(item, seed=sample_seed(item))
            grids.append((title, ijk.numpy()))
        for ax, (title, ijk) in zip(row, grids):
            ax.imshow(height_map(ijk, dims).T, origin="lower", cmap="viridis", vmin=0, vmax=dims[2] * 0.6)
            ax.set_title(f"{args.split} {index}: {title}\n{len(ijk)} voxels", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    with atomic_path(Path(args.output)) as tmp:
        fig.savefig(tmp, format="png", dpi=80)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
