"""3DGS initialisation from a converted scene (the SCube paper's Table 2, issue 13): a short 3D
Gaussian optimisation on the worlds' camera views, started from our export (`scube-sim export
scene.npz --to ply --max-gaussians N`: the N Gaussians with the largest opacity x area) or from N
random Gaussians in the paper's box ((-20 m, 20 m)^3 around each input camera); PSNR on held-out
views after the same steps.

A straight urban world without moving actors (a static scene: 3DGS fits one). Input: the waymo-5
rig's five images at T, converted with the shipped profile, exported to a 3DGS PLY and read back
(the file any 3DGS trainer starts from). Training views: the five cameras at T, T+2 and T+7 (10 Hz
instants; the ego moves on); held-out: T+5 and T+10. Both runs optimise the same parameters (means,
log-scales, rotations, opacity logits, colours) with Adam at 3DGS's learning rates, one view per
step in the same order, L1 on the non-sky pixels; no densification or pruning (identical for
both), black background. Random init: uniform means in the paper's box, 3DGS's opacity 0.1,
scales of half the mean spacing, random colours. The export keeps its own scales and opacities
(what a 3DGS trainer reading the PLY starts from). Images at `--scale` of the rig (CPU time).

Not part of `make bench`. Run: `python -m bench.bench_gs_init [--steps 200] [--scale 0.125]`
Results: bench/results/gs_init.{json,md}, docs/gs_init.png.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from rich.progress import track

from scube_sim.converter.pipeline import Converter
from scube_sim.io.ply3dgs import read_3dgs_ply, write_3dgs_ply
from scube_sim.model.nn.image_metrics import psnr
from scube_sim.model.nn.splat_render import rasterization
from scube_sim.transforms import invert_pose
from scube_sim.worlds.dataset import render_frames
from scube_sim.worlds.generator import WorldConfig, generate_world
from scube_sim.worlds.groundtruth import CHUNK_SIZE

from .common import BENCH_DIR, write_results

REPO = BENCH_DIR.parent
TRAIN_T = (0.0, 0.2, 0.7)
PAPER_BOX_M = 20.0  # SCube section 4.4: random points uniform in (-20 m, 20 m)^3 around each camera
HELD_OUT_T = (0.5, 1.0)
LR = {"means": 1.6e-4 * CHUNK_SIZE, "log_scales": 5e-3, "quats": 1e-3, "opacity_logits": 5e-2, "colors": 2.5e-3}


def views(world, ts, scale: float, to_chunk: np.ndarray) -> list[dict]:
    """Camera views (image, non-sky mask, viewmat, K, lens) at the instants `ts`, chunk frame."""
    out = []
    for t in ts:
        for im in render_frames(world, "waymo-5", t, image_scale=scale).images:
            intr = im.intrinsics
            cam = to_chunk @ im.cam_to_world
            out.append({"name": f"{im.name}@{t:g}", "rgb": torch.from_numpy(im.image.astype(np.float32) / 255.0),
                        "mask": torch.from_numpy(~im.sky), "viewmat": torch.from_numpy(np.linalg.inv(cam).astype(np.float32)),
                        "K": torch.from_numpy(intr.K.astype(np.float32)), "w": intr.width, "h": intr.height,
                        "dist": None if not intr.dist else torch.tensor([intr.dist], dtype=torch.float64),
                        "model": intr.model if intr.dist else "pinhole"})
    return out


def render(p: dict, v: dict) -> torch.Tensor:
    img, _, _ = rasterization(p["means"], torch.nn.functional.normalize(p["quats"], dim=1), p["log_scales"].exp(),
                              torch.sigmoid(p["opacity_logits"]), p["colors"].clamp(0, 1), v["viewmat"][None],
                              v["K"][None], v["w"], v["h"], camera_model=v["model"], dist_coeffs=v["dist"],
                              use_checkpoint=False)
    return img[0]


def held_out_psnr(p: dict, vs: list[dict]) -> float:
    with torch.no_grad():
        return float(np.mean([psnr(render(p, v).permute(2, 0, 1)[None], v["rgb"].permute(2, 0, 1)[None], v["mask"][None])
                              for v in vs]))


def optimise(p: dict, train: list[dict], held: list[dict], steps: int, label: str) -> list[tuple[int, float]]:
    p = {k: v.clone().requires_grad_(True) for k, v in p.items()}
    opt = torch.optim.Adam([{"params": [p[k]], "lr": LR[k]} for k in LR], eps=1e-15)
    curve = [(0, held_out_psnr(p, held))]
    for step in track(range(1, steps + 1), description=label):
        v = train[(step - 1) % len(train)]
        img = render(p, v)
        loss = (img - v["rgb"]).abs()[v["mask"]].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % max(steps // 4, 1) == 0:
            curve.append((step, held_out_psnr(p, held)))
    return curve


def params_from(g) -> dict:
    return {"means": torch.tensor(g.means + g.origin, dtype=torch.float32),
            "log_scales": torch.tensor(np.log(np.maximum(g.scales, 1e-4)), dtype=torch.float32),
            "quats": torch.tensor(g.quats, dtype=torch.float32),
            "opacity_logits": torch.logit(torch.tensor(g.opacities, dtype=torch.float32).clamp(1e-4, 1 - 1e-4)),
            "colors": torch.tensor(np.clip(g.colors, 0, 1), dtype=torch.float32)}


def random_params(n: int, cameras: np.ndarray, seed: int) -> dict:
    """n Gaussians uniform in the paper's box: (-20 m, 20 m)^3 around each input camera (positions
    (C, 3), chunk frame), n / C per camera."""
    rng = np.random.default_rng(seed)
    per = np.array_split(np.arange(n), len(cameras))
    means = np.concatenate([c + rng.uniform(-PAPER_BOX_M, PAPER_BOX_M, (len(i), 3)) for c, i in zip(cameras, per)])
    # 3DGS's initial scale: about the mean distance between neighbours in the union of the boxes
    lo, hi = means.min(0), means.max(0)
    spacing = float(np.prod(hi - lo) / n) ** (1 / 3)
    q = np.zeros((n, 4))
    q[:, 0] = 1
    return {"means": torch.tensor(means, dtype=torch.float32),
            "log_scales": torch.full((n, 3), float(np.log(0.5 * spacing))),
            "quats": torch.tensor(q, dtype=torch.float32),
            "opacity_logits": torch.full((n,), float(np.log(0.1 / 0.9))),
            "colors": torch.tensor(rng.random((n, 3)), dtype=torch.float32)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--scale", type=float, default=0.125)
    ap.add_argument("--max-gaussians", type=int, default=200_000)
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args(argv)
    torch.manual_seed(0)
    world = generate_world(WorldConfig(style="urban", seed=args.seed, layout="straight", moving_vehicles=0,
                                       pedestrians=0, ego_speed_mps=8, duration_s=2))
    frames = render_frames(world, "waymo-5", 0.0)
    scene = Converter("cpu").convert(frames, seed=0, sky=False).scene
    to_chunk = invert_pose(np.asarray(scene.metadata["chunk_to_world"], np.float64))
    with tempfile.TemporaryDirectory() as tmp:
        ply = Path(tmp) / "init.ply"
        write_3dgs_ply(ply, scene.gaussians().strongest(args.max_gaussians))  # what `export --max-gaussians` writes
        g = read_3dgs_ply(ply)
    train = views(world, TRAIN_T, args.scale, to_chunk)
    held = views(world, HELD_OUT_T, args.scale, to_chunk)
    rows, curves = [], {}
    cameras = np.stack([(to_chunk @ im.cam_to_world)[:3, 3] for im in frames.images])
    for name, p in (("converted scene export", params_from(g)),
                    ("random, (-20 m, 20 m)^3 around each camera", random_params(len(g), cameras, 0))):
        t = time.perf_counter()
        curve = optimise(p, train, held, args.steps, name)
        curves[name] = curve
        rows.append({"init": name, "gaussians": len(g), "steps": args.steps, "psnr_at_start_db": round(curve[0][1], 2),
                     "psnr_held_out_db": round(curve[-1][1], 2), "seconds": round(time.perf_counter() - t, 1)})
        print(rows[-1], flush=True)
    write_results("gs_init", rows, list(rows[0]),
                  notes=f"urban straight world seed {args.seed}, no moving actors; train T, T+2, T+7; held out T+5, T+10 "
                        f"(5 cameras each) at {args.scale:g} of the rig; PSNR on non-sky pixels")
    _plot(curves, REPO / "docs" / "gs_init.png")


def _plot(curves: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    for name, c in curves.items():
        ax.plot([s for s, _ in c], [v for _, v in c], "o-", label=name)
    ax.set_xlabel("optimisation steps (one view each)")
    ax.set_ylabel("PSNR on held-out views T+5, T+10 [dB]")
    ax.set_title("3DGS from the converted scene vs random initialisation")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
