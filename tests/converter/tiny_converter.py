"""The tiny converter the converter, sensor-to-sensor and converted-scene tests share (built once per
session by the `tiny_converter` fixture in tests/conftest.py): a one-world-per-split worlds dataset,
both stages trained a few steps, and a profile naming them."""

from __future__ import annotations

from pathlib import Path

import yaml

from scube_sim.datasets import open_dataset
from scube_sim.model.config import config_from_dict
from scube_sim.model.trainer import train
from scube_sim.worlds.dataset import DatasetConfig, generate_dataset

TINY = DatasetConfig(image_scale=0.04, visibility_scale=0.04, fine_voxel_m=0.4, coarse_factor=2, frame_offsets=[0],
                     lidar="vlp16", styles=["suburban"])
GEO_DATA = {"voxel_size": 3.2, "image_scale": 1.0}
VAE = {"widths": [16], "blocks": 1, "latent_channels": 4, "groups": 4}
GEO = {"vae": VAE, "encoder": {"kind": "cnn", "channels": 8, "stride": 4}, "feature_channels": 4, "depth_bins": 8,
       "cond_channels": 8, "widths": [8, 16], "blocks": 1, "groups": 4, "sample_steps": 2, "lift_norm": "mean"}
APP = {"gaussians_per_voxel": 2, "image_channels": 8, "widths": [8, 16], "pe_frequencies": 2, "panorama": [8, 16]}
APP_DATA = {"level": "coarse", "image_scale": 1.0}


def _train(stage, model, data_cfg, data, out, steps=2, lr=1e-3):
    cfg = {"stage": stage, "train": {"seed": 0, "steps": steps, "batch_size": 1, "lr": lr, "threads": 1},
           "model": model, "data": data_cfg}
    train(stage, config_from_dict(cfg), data, out, progress=False)
    return out / "last.pt"


def build(tmp: Path) -> dict:
    """A tiny worlds dataset under `tmp`, both stages trained two steps, and a profile naming them:
    {"data", "profile", "geo", "app", "sample"}."""
    data = tmp / "worlds"
    for split in ("train", "val", "test"):
        generate_dataset(data, split, 1, TINY, progress=False)
    # the VAE overfits the one training world, so that even an untrained denoiser's latents decode
    # to a grid of that world's kind (not an empty one)
    vae = _train("geometry-vae", {"vae": VAE}, GEO_DATA, data, tmp / "vae", steps=40, lr=1e-2)
    geo = _train("geometry", {**GEO, "vae_checkpoint": str(vae)}, GEO_DATA, data, tmp / "geo")
    app_ck = _train("appearance", APP, APP_DATA, data, tmp / "app")
    fx = float(open_dataset("worlds", data, split="test")[0].frames.images[0].intrinsics.K[0, 0])
    profile = tmp / "tiny.yaml"
    profile.write_text(yaml.safe_dump({"geometry": {"checkpoint": str(geo), "focal_px": fx},
                                       "appearance": {"checkpoint": str(app_ck), "focal_px": fx, "sky_size": [8, 16]},
                                       "confidence_samples": 3}))
    return {"data": data, "profile": profile, "geo": geo, "app": app_ck, "sample": data / "test" / "000000"}


FINE_DATA = {"level": "fine", "voxel_size": 1.6, "coarse_voxel_size": 3.2, "image_scale": 1.0}
FINE_GEO = {**GEO, "level": "fine", "mode": "predictor", "predictor_loss": "decoded"}


def build_fine(tiny: dict, tmp: Path) -> Path:
    """A fine level (1.6 m under the tiny converter's 3.2 m) for `build`'s dataset: its sparse
    structure VAE overfit on the training world, the single-step predictor trained two steps."""
    vae = _train("geometry-vae", {"level": "fine", "vae": VAE}, FINE_DATA, tiny["data"], tmp / "fine-vae",
                 steps=30, lr=1e-2)
    return _train("geometry", {**FINE_GEO, "vae_checkpoint": str(vae)}, FINE_DATA, tiny["data"], tmp / "fine")
