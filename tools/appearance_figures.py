"""Pictures of a trained appearance checkpoint on one worlds sample, for docs/:

- ``<prefix>_inputs.png``: the input cameras at T (what the network sees);
- ``<prefix>_novel.png``: the three front cameras at T+5 and T+10, ground truth above the render
  (moving actors hatched out: the grid holds them where they were at T);
- ``<prefix>_bev.png``: a bird's-eye view from 80 m above the chunk, the predicted Gaussians
  beside the world's mesh rendered from the same camera (the ground truth).

Run: ``python tools/appearance_figures.py --checkpoint CK --data DIR [--split test] [--index 0]
-o docs [--prefix appearance] [--voxsplat pred.npz]`` (the prediction, for ``scube-sim render``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from scube_sim.camera.model import Intrinsics  # noqa: E402
from scube_sim.camera.render import render_camera  # noqa: E402
from scube_sim.model.appearance.data import frame_at, is_front_camera, static_mask  # noqa: E402
from scube_sim.model.checkpoint import load_model  # noqa: E402
from scube_sim.model.config import stage_configs  # noqa: E402
from scube_sim.model.nn.image_metrics import psnr  # noqa: E402
from scube_sim.model.stages import get_stage  # noqa: E402
from scube_sim.raytrace.tracer import Tracer  # noqa: E402
from scube_sim.worlds.generator import WorldConfig, generate_world  # noqa: E402
from scube_sim.worlds.textures import albedo  # noqa: E402

BEV_HEIGHT_M, BEV_SIZE = 80.0, (320, 320)


def _img(t: torch.Tensor) -> np.ndarray:
    return t.permute(1, 2, 0).clamp(0, 1).numpy()


def bev_camera(centre_xy, half_width_m: float) -> tuple[Intrinsics, np.ndarray]:
    """A pinhole camera BEV_HEIGHT_M above `centre_xy` (chunk frame) looking straight down, image
    up = chunk +x (forward), covering +-half_width_m at the ground."""
    h, w = BEV_SIZE
    f = w / 2 * BEV_HEIGHT_M / half_width_m
    intr = Intrinsics(w, h, f, f, w / 2, h / 2)
    pose = np.eye(4)
    # camera x (image right) = chunk -y, camera y (image down) = chunk -x, camera z = chunk -z
    pose[:3, :3] = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]).T
    pose[:3, 3] = [centre_xy[0], centre_xy[1], BEV_HEIGHT_M]
    return intr, pose


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="test")
    ap.add_argument("--index", type=int, default=0)
    ap.add_argument("-o", "--output", default="docs")
    ap.add_argument("--prefix", default="appearance")
    ap.add_argument("--voxsplat", help="also save the prediction here (a chunk-frame VoxSplat .npz with its sky)")
    args = ap.parse_args(argv)
    out_dir = Path(args.output)
    out_dir.mkdir(parents=True, exist_ok=True)
    stage = get_stage("appearance")
    model, run = load_model(stage, args.checkpoint)
    _, data_cfg = stage_configs(run, stage.model_config, stage.data_config)
    data_cfg = data_cfg.model_copy(update={"eval_frames": True})
    ds = stage.dataset(Path(args.data), data_cfg, args.split, run.train.seed)
    item = ds[args.index]
    name = item["sample"]
    with torch.no_grad():
        pred = model(item)
        if args.voxsplat:
            model.to_voxsplat(pred, item).save(args.voxsplat)

        # inputs
        n = item["images"].shape[0]
        fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 2.6))
        for i, ax in enumerate(np.atleast_1d(axes)):
            hh, ww = (int(s) for s in item["image_size"][i])
            ax.imshow(_img(item["images"][i, :, :hh, :ww]))
            ax.set_title(f"{item['camera_names'][i]} at T", fontsize=9)
            ax.axis("off")
        fig.suptitle(f"{name}: the input images", fontsize=10)
        fig.tight_layout()
        fig.savefig(out_dir / f"{args.prefix}_inputs.png", dpi=110)
        plt.close(fig)

        # novel views at T+5 and T+10, front cameras
        moving = item["moving_instances"]
        cols = []
        for k in (5, 10):
            frame = frame_at(item, k)
            for i, cam in enumerate(frame["camera_names"]):
                if is_front_camera(cam):
                    hh, ww = (int(s) for s in frame["image_size"][i])
                    img, _, _ = model.render(pred, frame["intrinsics"][i], frame["cam_to_chunk"][i], hh, ww,
                                             frame["distortion"][i])
                    gt = frame["images"][i, :, :hh, :ww]
                    keep = static_mask(frame, i, moving)
                    cols.append((f"{cam} T+{k}", gt, img, keep, psnr(img[None], gt[None], keep[None])))
        ncol = max(1, len(cols) // 2)  # the front cameras; rows: T+5 truth, render, T+10 truth, render
        fig, axes = plt.subplots(4, ncol, figsize=(3.4 * ncol, 9.6), squeeze=False)
        for c, (title, gt, img, keep, p) in enumerate(cols):
            r0, col = 2 * (c // ncol), c % ncol
            hatch = np.where(keep.numpy()[..., None], _img(gt), 0.5 * _img(gt) + 0.5 * np.array([1.0, 0.0, 1.0]))
            axes[r0, col].imshow(hatch)
            axes[r0, col].set_title(f"{title}: ground truth", fontsize=8)
            axes[r0 + 1, col].imshow(_img(img))
            axes[r0 + 1, col].set_title(f"{title}: render, PSNR {p:.1f} dB", fontsize=8)
        for ax in axes.ravel():
            ax.axis("off")
        fig.suptitle(f"{name}: novel views (moving actors magenta, masked out of the PSNR)", fontsize=10)
        fig.tight_layout()
        fig.savefig(out_dir / f"{args.prefix}_novel.png", dpi=110)
        plt.close(fig)

        # bird's-eye view of the region the network covers
        region = data_cfg.region or (-10.24, -51.2, -3.23, 92.16, 51.2, 99.17)
        centre = ((region[0] + region[3]) / 2, (region[1] + region[4]) / 2)
        half = max(region[3] - region[0], region[4] - region[1]) / 2
        intr, cam_to_chunk = bev_camera(centre, half)
        img, alpha, sky = model.render(pred, torch.from_numpy(intr.K), torch.from_numpy(cam_to_chunk), intr.height,
                                       intr.width)
        gaussians = img - (1 - alpha)[None] * sky  # the Gaussians alone, over black
        meta = json.loads((Path(args.data) / name / "meta.json").read_text())
        world = generate_world(WorldConfig(**meta["world"]))
        chunk_to_world = np.asarray(meta["chunk_to_world"], np.float64)
        gt = render_camera([Tracer(world.mesh_at(0.0))], intr, chunk_to_world @ cam_to_chunk,
                           sun_dir=world.sun_dir, albedo_fn=albedo)["rgb"]
        fig, axes = plt.subplots(1, 2, figsize=(8, 4.3))
        axes[0].imshow(gt)
        axes[0].set_title("ground truth: the world's mesh at T", fontsize=9)
        axes[1].imshow(_img(gaussians))
        axes[1].set_title(f"predicted Gaussians ({pred['means'].shape[0]:,})", fontsize=9)
        for ax in axes:
            ax.axis("off")
        fig.suptitle(f"{name}: bird's-eye view from {BEV_HEIGHT_M:.0f} m, ego at T facing up", fontsize=10)
        fig.tight_layout()
        fig.savefig(out_dir / f"{args.prefix}_bev.png", dpi=110)
        plt.close(fig)
    print(f"{name}: wrote {args.prefix}_inputs.png, {args.prefix}_novel.png, {args.prefix}_bev.png -> {out_dir}")


if __name__ == "__main__":
    main()
