"""Sparse convolution (`scube_sim.model.sparse`) against torch's dense conv3d on the bounding grid.

The active sites: a street-like 2.5D surface (a rolling ground height field, 1 voxel thick, with
building walls along two sides), about 1e5 voxels in a 320 x 320 x 32 bounding grid (3.3 M
sites, 3 % active). Each case runs in its own process (peak RSS is per process), forward and
forward + backward of one 3x3x3 convolution with C_in = C_out = C, at C = 32 and 64, torch's
default threads (2 here). The sparse kernel map is built once per grid (a network reuses it for
every layer on that grid): its time is reported apart and not in the per-step times.

Run: `python -m bench.bench_sparse [--quick]`. Results: bench/results/sparse_conv.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import numpy as np

from .common import peak_mb, reset_peak, rss_mb, write_results

SHAPE = (320, 320, 32)


def street_sites(shape=SHAPE) -> np.ndarray:
    """(N, 3) int64 voxel indices of the synthetic street surface inside `shape`."""
    x, y = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    z = np.round(4 + 2 * np.sin(x / 23.0) + 1.5 * np.cos(y / 17.0)).astype(np.int64)
    ground = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    walls = []
    for j in (40, 280):  # two facades, full height, every 8th column left open (windows, gaps)
        xi, zi = np.meshgrid(np.arange(shape[0]), np.arange(8, shape[2]), indexing="ij")
        keep = (xi % 8) != 0
        walls.append(np.stack([xi[keep], np.full(keep.sum(), j), zi[keep]], 1))
    return np.unique(np.concatenate([ground] + walls), axis=0)


def run_case(method: str, channels: int, repeat: int) -> dict:
    import torch
    import torch.nn.functional as F

    from scube_sim.model.nn.sparse import Grid, SparseTensor, SubmanifoldConv3d

    torch.manual_seed(0)
    ijk = torch.from_numpy(street_sites())
    n = ijk.shape[0]
    base = rss_mb()
    reset_peak()
    row = {"method": method, "channels": channels, "active": n, "grid_sites": int(np.prod(SHAPE))}
    if method == "sparse":
        t = time.perf_counter()
        grid = Grid(torch.cat([torch.zeros(n, 1, dtype=torch.int64), ijk], 1), 1)
        kmap = grid.submanifold_map(3)
        row["map_s"] = time.perf_counter() - t
        row["pairs"] = kmap.num_pairs
        conv = SubmanifoldConv3d(channels, channels, 3)
        feats = torch.randn(n, channels, requires_grad=True)
        x = SparseTensor(feats, grid)

        def fwd():
            return conv(x).feats

    else:
        conv = torch.nn.Conv3d(channels, channels, 3, padding=1)
        dense = torch.zeros((1, channels) + SHAPE)
        dense[0, :, ijk[:, 0], ijk[:, 1], ijk[:, 2]] = torch.randn(channels, n)
        dense.requires_grad_(True)
        row["map_s"] = float("nan")

        def fwd():
            return F.conv3d(dense, conv.weight, conv.bias, padding=1)

    def step():
        out = fwd()
        out.square().mean().backward()

    for name, fn in (("forward_s", lambda: fwd()), ("fwd_bwd_s", step)):
        fn()  # warm-up (allocator, oneDNN primitives)
        times = []
        for _ in range(repeat):
            t = time.perf_counter()
            with torch.no_grad() if name == "forward_s" else _null():
                fn()
            times.append(time.perf_counter() - t)
        row[name] = float(np.median(times))
    row["peak_mb"] = peak_mb() - base
    row["per_1e5_fwd_bwd_s"] = row["fwd_bwd_s"] * 1e5 / n
    row["threads"] = torch.get_num_threads()
    return row


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="C = 32 only, one repeat")
    ap.add_argument("--case", nargs=2, metavar=("METHOD", "CHANNELS"), help=argparse.SUPPRESS)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    if args.case:
        print(json.dumps(run_case(args.case[0], int(args.case[1]), args.repeat)))
        return
    from rich.progress import Progress

    channels = (32,) if args.quick else (32, 64)
    repeat = 1 if args.quick else args.repeat
    cases = [(m, c) for c in channels for m in ("sparse", "dense")]
    rows = []
    with Progress() as progress:
        task = progress.add_task("sparse vs dense conv", total=len(cases))
        for m, c in cases:
            out = subprocess.run([sys.executable, "-m", "bench.bench_sparse", "--case", m, str(c),
                                  "--repeat", str(repeat)], capture_output=True, text=True, check=True)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
            progress.advance(task)
    by = {(r["method"], r["channels"]): r for r in rows}
    for r in rows:
        d = by[("dense", r["channels"])]
        r["dense_over_sparse_fwd_bwd"] = d["fwd_bwd_s"] / r["fwd_bwd_s"]
        r["dense_over_sparse_memory"] = d["peak_mb"] / r["peak_mb"]
    header = ["method", "channels", "active", "grid_sites", "map_s", "forward_s", "fwd_bwd_s", "per_1e5_fwd_bwd_s",
              "peak_mb", "dense_over_sparse_fwd_bwd", "dense_over_sparse_memory"]
    path = write_results("sparse_conv", rows, header,
                         notes="One 3x3x3 convolution, C_in = C_out = C, float32; dense: torch conv3d on the "
                               "bounding grid; peak_mb: peak RSS over the process's baseline; times: median wall s.")
    print(path.read_text())


if __name__ == "__main__":
    main()
