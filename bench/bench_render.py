"""The CPU Gaussian renderer (`scube_sim.model.splat_render`): seconds per 480 x 320 view.

Scene: N Gaussians scattered through the view frustum from 2 to 60 m, 3-22 cm std-devs, random
rotations, opacities 0.3-1 (dense enough that most pixels saturate: the early stop matters).
Forward (no grad) and forward + backward (sum of the image), float32, torch's default threads
(2 here), the best of `repeat` runs, each case in its own process (peak RSS per process). For
scale, the float64 per-pixel oracle of the tests on a 64 x 64 crop with 1e4 Gaussians, and the
renderer on the same crop in the same process: the ratio is the point, not the seconds.

Run: `python -m bench.bench_render [--quick]`. Results: bench/results/splat_render.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

from .common import peak_mb, reset_peak, rss_mb, write_results

WIDTH, HEIGHT = 480, 320


def frustum_scene(n: int, seed: int = 0, hfov_deg: float = 70.0, width: int = WIDTH, height: int = HEIGHT):
    import numpy as np
    import torch

    from scube_sim.camera.model import Intrinsics

    rng = np.random.default_rng(seed)
    intr = Intrinsics.from_fov(width, height, hfov_deg)
    z = rng.uniform(2.0, 60.0, n)
    u, v = rng.uniform(0, width, n), rng.uniform(0, height, n)
    x, y = (u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z
    means = torch.tensor(np.stack([x, y, z], 1), dtype=torch.float32)
    quats = torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32)
    scales = torch.tensor(np.exp(rng.uniform(np.log(0.03), np.log(0.22), (n, 3))), dtype=torch.float32)
    opac = torch.tensor(rng.uniform(0.3, 1.0, n), dtype=torch.float32)
    colors = torch.tensor(rng.uniform(0, 1, (n, 3)), dtype=torch.float32)
    return intr, (means, quats, scales, opac, colors)


def _render(intr, scene, grad: bool):
    import torch

    from scube_sim.model.nn.splat_render import rasterization

    leaves = [t.clone().requires_grad_(grad) for t in scene]
    K = torch.tensor(intr.K, dtype=torch.float32)[None]
    vm = torch.eye(4)[None]
    t = time.perf_counter()
    with torch.set_grad_enabled(grad):
        img, alpha, meta = rasterization(*leaves, vm, K, intr.width, intr.height, render_mode="RGB+ED")
        if grad:
            (img.sum() + alpha.sum()).backward()
    return time.perf_counter() - t, float(alpha.detach().mean())


def run_case(n: int, repeat: int) -> dict:
    intr, scene = frustum_scene(n)
    base = rss_mb()
    reset_peak()
    fwd = [_render(intr, scene, False) for _ in range(repeat)]
    bwd = [_render(intr, scene, True) for _ in range(repeat)]
    return {"case": f"{WIDTH}x{HEIGHT}", "gaussians": n, "forward_s": min(f[0] for f in fwd),
            "fwd_bwd_s": min(b[0] for b in bwd), "mean_alpha": fwd[0][1], "peak_mb": peak_mb() - base}


def run_oracle() -> dict:
    import numpy as np
    from tests.model.test_splat_render import oracle

    intr, scene = frustum_scene(10_000, seed=1, width=64, height=64)
    t_ours = min(_render(intr, scene, False)[0] for _ in range(3))
    t = time.perf_counter()
    oracle(intr, np.eye(4), *(x.double().numpy() for x in scene), np.zeros(3))
    t_oracle = time.perf_counter() - t
    return {"case": "64x64 oracle", "gaussians": 10_000, "forward_s": t_ours, "oracle_s": t_oracle,
            "oracle_over_renderer": t_oracle / t_ours}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1e5 only, one repeat, no oracle")
    ap.add_argument("--case", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--oracle", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    if args.case:
        print(json.dumps(run_case(args.case, args.repeat)))
        return
    if args.oracle:
        print(json.dumps(run_oracle()))
        return
    from rich.progress import Progress

    sizes = (100_000,) if args.quick else (100_000, 1_000_000)
    repeat = 1 if args.quick else args.repeat
    jobs = [["--case", str(n), "--repeat", str(repeat)] for n in sizes] + ([] if args.quick else [["--oracle"]])
    rows = []
    with Progress() as progress:
        task = progress.add_task("CPU splat renderer", total=len(jobs))
        for job in jobs:
            out = subprocess.run([sys.executable, "-m", "bench.bench_render", *job], capture_output=True, text=True,
                                 check=True)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
            progress.advance(task)
    header = ["case", "gaussians", "forward_s", "fwd_bwd_s", "mean_alpha", "peak_mb", "oracle_s",
              "oracle_over_renderer"]
    path = write_results("splat_render", rows, header,
                         notes="One view, float32, RGB + expected depth; fwd_bwd: forward and backward of "
                               "sum(image) + sum(alpha); best of the repeats; peak_mb over the process's baseline. "
                               "Oracle: the tests' float64 per-pixel loop, on a 64 x 64 crop.")
    print(path.read_text())


if __name__ == "__main__":
    main()
