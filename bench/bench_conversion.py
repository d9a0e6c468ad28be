"""Conversion time and peak memory per profile, as a user runs it (`scube-sim convert` in a child
process, its wall time and peak resident memory), and the thread policy on a busy machine:
default threads pinned to one core (`taskset -c 0`) against `--threads 1` on the same core.

Inputs: the shared KITTI-360 frames (one camera, ±4 context instants) and, where present, the
shared TRI DGP sample (six 1936x1216 cameras). Each input's poses are estimated before the timed
runs (their cache, `datasets.odometry`), so the rows time the conversion, not the odometry.

Run: `python -m bench.bench_conversion [--quick] [--profiles evidence-complete,evidence]`
(a few minutes on 2 cores; `--quick`: KITTI-360 only). Results: bench/results/conversion.{json,md}.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .common import write_results

SHARED = Path(os.environ.get("SCUBE_SIM_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
INPUTS = {
    "KITTI-360 frame 10 (1 camera)": (SHARED / "kitti360-2013_05_28-seq", "kitti360", 10),
    "TRI DGP sample 0 (6 cameras, 1936x1216)": (SHARED / "tri-dgp-test-scene_02", "tri_dgp", 0),
}


def run_convert(path: Path, dataset: str, sample: int, profile: str, out: Path, *, threads: int = 0,
                pin: str | None = None) -> dict:
    """One `scube-sim convert` in a child process: wall seconds and the child's peak RSS (MB)."""
    cmd = [sys.executable, "-m", "scube_sim.cli", "convert", str(path), "--dataset", dataset, "--sample", str(sample),
           "--profile", profile, "-o", str(out), "--no-progress", "--threads", str(threads)]
    if pin is not None:
        if shutil.which("taskset") is None:
            return {"error": "taskset not installed"}
        cmd = ["taskset", "-c", pin, *cmd]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stdout, stderr = proc.communicate()
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        return {"error": (stderr.strip().splitlines() or ["?"])[-1], "wall_s": wall}
    return {"wall_s": wall, "summary": stdout.strip().splitlines()[-1]}


def _peak_mb(summary: str) -> float:
    """The 'peak N MB' the command prints (the conversion's own peak, its process's high-water mark)."""
    words = summary.split()
    for i, w in enumerate(words):
        if w == "peak" and i + 1 < len(words):
            try:
                return float(words[i + 1])
            except ValueError:
                pass
    return float("nan")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="KITTI-360 only")
    ap.add_argument("--profiles", default="evidence-complete,evidence")
    args = ap.parse_args(argv)
    profiles = [p for p in args.profiles.split(",") if p]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "s.npz"
        for name, (path, dataset, sample) in INPUTS.items():
            if not path.exists() or (args.quick and "KITTI" not in name):
                continue
            run_convert(path, dataset, sample, profiles[0], out)  # warm: the poses' cache, the file cache
            for profile in profiles:
                r = run_convert(path, dataset, sample, profile, out)
                rows.append({"input": name, "profile": profile, "threads": "default", "cores": "all",
                             "wall_s": r.get("wall_s"), "peak_mb": _peak_mb(r.get("summary", "")),
                             "error": r.get("error", "")})
                print(rows[-1], flush=True)
            if "KITTI" in name:
                # one core taken by taskset: default threads against one thread, same core, same input
                for threads, label in ((0, "default"), (1, "1")):
                    r = run_convert(path, dataset, sample, profiles[0], out, threads=threads, pin="0")
                    rows.append({"input": name, "profile": profiles[0], "threads": label, "cores": "taskset -c 0",
                                 "wall_s": r.get("wall_s"), "peak_mb": _peak_mb(r.get("summary", "")),
                                 "error": r.get("error", "")})
                    print(rows[-1], flush=True)
    pinned = {r["threads"]: r["wall_s"] for r in rows if r["cores"] == "taskset -c 0" and r["wall_s"]}
    ratio = pinned["default"] / pinned["1"] if len(pinned) == 2 else float("nan")
    write_results("conversion", rows, ["input", "profile", "threads", "cores", "wall_s", "peak_mb", "error"],
                  notes=f"`scube-sim convert` wall time (the whole command, poses cached) and the conversion's "
                        f"peak memory. Under `taskset -c 0`, default threads / one thread = {ratio:.2f}.")


if __name__ == "__main__":
    main()
