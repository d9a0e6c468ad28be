"""A prediction scored against camera views: the training loss (0.9 L1(image) + 1.0 L1(alpha,
non-sky) + 0.1 (1 - SSIM), + 0.6 LPIPS where configured) and the held-out metrics (PSNR, SSIM,
sky PSNR, LPIPS), moving actors masked.
"""

from __future__ import annotations

import torch

from ..nn.image_metrics import psnr, ssim
from .data import frame_at, is_front_camera, static_mask
from .net import AppearanceNet

LOSS_WEIGHTS = {"l1": 0.9, "alpha": 1.0, "ssim": 0.1}


# ---------------------------------------------------------------------------- stage
def view_losses(model: AppearanceNet, out: dict, item: dict, views=None) -> tuple[torch.Tensor, dict]:
    """The loss over views (frame offset, camera index) of an item (default: its cameras at T).
    After T the moving actors' pixels are left out (the grid holds them where they were at T)."""
    total = 0.0
    logs = {"l1": 0.0, "alpha": 0.0, "ssim": 0.0}
    lpips = model.lpips()
    if lpips is not None:
        logs["lpips"] = 0.0
    views = [(0, i) for i in range(item["images"].shape[0])] if views is None else views
    moving = item.get("moving_instances", torch.zeros(0, dtype=torch.int64))
    for k, i in views:
        frame = frame_at(item, k)
        hh, ww = (int(s) for s in frame["image_size"][i])
        img, alpha, _ = model.render(out, frame["intrinsics"][i], frame["cam_to_chunk"][i], hh, ww,
                                     frame["distortion"][i])
        gt = frame["images"][i, :, :hh, :ww]
        nonsky = (~frame["sky"][i, :hh, :ww]).to(img.dtype)
        keep = (static_mask(frame, i, moving) if k != 0 else frame["valid"][i, :hh, :ww]).to(img.dtype)
        n_keep = keep.sum().clamp_min(1.0)
        l1 = ((img - gt).abs() * keep).sum() / (3 * n_keep)
        la = ((alpha - nonsky).abs() * keep).sum() / n_keep
        ls = 1 - ssim(img[None], gt[None], keep[None])
        total = total + LOSS_WEIGHTS["l1"] * l1 + LOSS_WEIGHTS["alpha"] * la + LOSS_WEIGHTS["ssim"] * ls
        if lpips is not None:
            lp = lpips(img[None], gt[None], keep[None])[0]
            total = total + model.cfg.lpips.weight * lp
            logs["lpips"] += float(lp.detach()) / len(views)
        logs["l1"] += float(l1.detach()) / len(views)
        logs["alpha"] += float(la.detach()) / len(views)
        logs["ssim"] += float(1 - ls.detach()) / len(views)
    return total / len(views), logs


def evaluate_item(model: AppearanceNet, item: dict, cameras: str = "front", out: dict | None = None) -> dict:
    """Per-view metrics of one item at T and at each of its ``eval_frames``: ``{name: [values]}``
    with names psnr_t<k>, ssim_t<k> (moving actors and padding masked out), lpips_t<k> (the same
    pixels; where the model config names LPIPS weights) and psnr_sky_t<k> (sky pixels alone, where
    the view has any); k the frame offset. `cameras`: front | all."""
    out = model(item) if out is None else out
    lpips = model.lpips()
    moving = item.get("moving_instances", torch.zeros(0, dtype=torch.int64))
    res: dict[str, list[float]] = {}
    for frame in [item] + list(item.get("eval_frames", [])):
        k = int(frame.get("offset", 0)) if frame is not item else 0
        for i, name in enumerate(frame["camera_names"]):
            if cameras == "front" and not is_front_camera(name):
                continue
            hh, ww = (int(s) for s in frame["image_size"][i])
            img, _, _ = model.render(out, frame["intrinsics"][i], frame["cam_to_chunk"][i], hh, ww,
                                     frame["distortion"][i])
            gt = frame["images"][i, :, :hh, :ww]
            keep = static_mask(frame, i, moving)
            sky = frame["sky"][i, :hh, :ww] & keep
            res.setdefault(f"psnr_t{k}", []).append(psnr(img[None], gt[None], keep[None]))
            res.setdefault(f"ssim_t{k}", []).append(float(ssim(img[None], gt[None], keep[None])))
            if lpips is not None:
                res.setdefault(f"lpips_t{k}", []).append(float(lpips(img[None], gt[None], keep[None])[0]))
            if bool(sky.any()):
                res.setdefault(f"psnr_sky_t{k}", []).append(psnr(img[None], gt[None], sky[None]))
    return res


