"""The appearance stage's trades at one fixed training budget (issue 12; the paper's appearance
ablation compares 1024^3 with 256^3 voxels and M = 4 with M = 1):

1. **Variants**, each trained from scratch for the same `--steps` from the shipped config
   (`scube_sim/model/configs/appearance.yaml`), seed 0, then evaluated on the val split at T and
   at its later stored instants (novel views; front cameras, moving actors masked): M = 4 at
   0.4 m (the shipped setting), M = 1 at 0.4 m, M = 4 at 0.2 m (the fine 0.1 m grid coarsened
   by 2). Seconds per step are wall-clock on this machine.
2. **Render resolution**: the first variant's weights evaluated with the images at
   `image_scale` 0.25, 0.5 and 1.0 of the stored ones: seconds per rendered view and PSNR.

Not part of `make bench` (it trains for tens of minutes). Run:
`python -m experiments.ablate_appearance --data DIR [--steps 40] [--work experiments/.cache/ablate_appearance]`
(DIR holds train and val splits with the shipped config's training instants, e.g. made with
`scube-sim worlds generate ... --frame-offsets 0,2,7`). Each training is resumable: a rerun
continues the runs in --work. Results: experiments/results/appearance_ablation.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import yaml

from .common import EXPERIMENTS_DIR, write_results

VARIANTS = {
    "M=4, 0.4 m": {"model": {"gaussians_per_voxel": 4}, "data": {"level": "coarse", "coarsen": 1}},
    "M=1, 0.4 m": {"model": {"gaussians_per_voxel": 1}, "data": {"level": "coarse", "coarsen": 1}},
    "M=4, 0.2 m": {"model": {"gaussians_per_voxel": 4}, "data": {"level": "fine", "coarsen": 2}},
}
SCALES = (0.25, 0.5, 1.0)


def _config(base: dict, variant: dict, steps: int, threads: int | None) -> dict:
    cfg = yaml.safe_load(yaml.safe_dump(base))
    for section, values in variant.items():
        cfg[section].update(values)
    cfg["train"].update(steps=steps, checkpoint_every=10, threads=threads, num_workers=0 if threads == 1 else 1)
    return cfg


def main(argv=None) -> None:
    from scube_sim.model.config import load_config
    from scube_sim.model.evaluate import evaluate
    from scube_sim.model.stages import get_stage
    from scube_sim.model.trainer import LAST, train

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--work", default=str(EXPERIMENTS_DIR / ".cache" / "ablate_appearance"))
    ap.add_argument("--eval-split", default="val")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    args = ap.parse_args(argv)
    stage = get_stage("appearance")
    base = yaml.safe_load((Path(__file__).resolve().parents[1] / "scube_sim/model/configs/appearance.yaml").read_text())
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    first_ck = None
    for name, variant in VARIANTS.items():
        tag = name.replace("=", "").replace(", ", "_").replace(" ", "")
        cfg_path = work / f"{tag}.yaml"
        cfg_path.write_text(yaml.safe_dump(_config(base, variant, args.steps, args.threads)))
        run_dir = work / tag
        timing = run_dir / "timing.json"  # the wall-clock of the training that made the run
        resume = (run_dir / LAST).is_file()
        t0 = time.perf_counter()
        res = train(stage, load_config(str(cfg_path)), args.data, run_dir, resume=resume, progress=True)
        if not resume:
            timing.write_text(json.dumps({"train_s": time.perf_counter() - t0, "steps": res.step}))
        took = json.loads(timing.read_text()) if timing.is_file() else {}
        train_s = float(took["train_s"]) if took.get("steps") == res.step else float("nan")
        t0 = time.perf_counter()
        m = evaluate(stage, res.last, args.data, split=args.eval_split, data_overrides={"eval_frames": True},
                     progress=True)
        eval_s = time.perf_counter() - t0
        row = {"variant": name, "steps": res.step, "train_s": train_s, "s_per_step": train_s / max(1, res.step),
               "eval_s": eval_s, "params": sum(p.numel() for p in res.model.parameters()), **m}
        rows.append(row)
        print(row, flush=True)
        if first_ck is None:
            first_ck = res.last
    offsets = sorted({k.split("_t")[-1] for r in rows for k in r if k.startswith("psnr_t")}, key=int)
    header = ["variant", "steps", "s_per_step", "params"] + [f"psnr_t{k}" for k in offsets] + \
             [f"ssim_t{k}" for k in offsets] + ["psnr_sky_t0"]
    # render resolution / seconds, the first variant's weights
    res_rows = []
    for scale in SCALES:
        t0 = time.perf_counter()
        m = evaluate(stage, first_ck, args.data, split=args.eval_split,
                     data_overrides={"eval_frames": True, "image_scale": scale}, progress=True)
        seconds = time.perf_counter() - t0
        views = m["views_t0"] * sum(1 for k in m if k.startswith("psnr_t"))  # every instant: the same cameras
        res_rows.append({"variant": f"M=4, 0.4 m at image_scale {scale}", "image_scale": scale,
                         "eval_s": seconds, "s_per_view": seconds / max(1.0, views), **m})
        print(res_rows[-1], flush=True)
    notes = (f"Each variant trained for {args.steps} steps from scratch (seed 0) on {args.data}, evaluated on "
             f"its {args.eval_split} split: front cameras, moving actors masked; psnr_t<k> at frame offset k. "
             "The second table: the first variant's weights evaluated with the images at other scales "
             "(s_per_view: the whole evaluation's seconds, the network's forward included, per rendered view).")
    write_results("appearance_ablation", rows + res_rows, header + ["image_scale", "s_per_view"], notes)


if __name__ == "__main__":
    main()
