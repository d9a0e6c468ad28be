"""Ship a geometry-stage checkpoint inside the package: weights only (`trainer.export_weights`),
for a structure VAE with its latent_std recalibrated on the final encoder over the train split,
plus the run's config, metrics and loss curve, under scube_sim/model/checkpoints/<name>/.

    python tools/ship_geometry.py RUN_DIR/best.pt NAME --data DIR [--limit 200]
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import yaml

from scube_sim.model.checkpoint import export_weights, load_checkpoint, load_model, save_checkpoint
from scube_sim.model.config import config_from_dict, stage_configs
from scube_sim.model.geometry.stage import calibrate_latent_std
from scube_sim.model.stages import get_stage

CHECKPOINTS = Path(__file__).resolve().parents[1] / "scube_sim" / "model" / "checkpoints"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("name")
    ap.add_argument("--data", required=True, help="the worlds folder the run trained on (its train split)")
    ap.add_argument("--limit", type=int, default=None, help="train items for the latent calibration")
    args = ap.parse_args(argv)
    out = CHECKPOINTS / args.name
    out.mkdir(parents=True, exist_ok=True)
    target = export_weights(args.checkpoint, out / "model.pt")
    ck = load_checkpoint(target)
    if ck["stage"] == "geometry-vae":
        stage = get_stage("geometry-vae")
        model, run = load_model(stage, target)
        _, data_cfg = stage_configs(run, stage.model_config, stage.data_config)
        before = float(model.vae.latent_std)
        after = calibrate_latent_std(model, stage.dataset(Path(args.data), data_cfg, "train", 0), args.limit)
        ck["model"] = {k: v.clone() for k, v in model.state_dict().items()}
        save_checkpoint(target, ck)
        print(f"latent_std: {before:.4f} (running RMS over training) -> {after:.4f} (final encoder, train split)")
    run_dir = Path(args.checkpoint).parent
    (out / "config.yaml").write_text(yaml.safe_dump(ck["config"], sort_keys=False))
    for name in ("metrics.jsonl", "loss.png"):
        if (run_dir / name).is_file():
            shutil.copy(run_dir / name, out / name)
    config_from_dict(ck["config"])  # the shipped config still validates
    print(f"{out}: {', '.join(sorted(p.name for p in out.iterdir()))}; step {ck.get('step')}")


if __name__ == "__main__":
    main()
