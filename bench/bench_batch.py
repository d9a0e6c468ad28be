"""`scube-sim batch` throughput: tasks per minute for each job with 1 and 2 workers on the local
pool and on Ray, and Ray's scheduling overhead over the local pool on tiny tasks, in one run.

Jobs and inputs (each configuration writes a fresh batch folder, so nothing is skipped):
- worlds: 2 samples of the test split at image scale 0.1;
- build: the nuScenes demo log (../shared/data) under 2 names (2 tasks; skipped if absent);
- replay: a tiny scenario (a 1 m VoxSplat world, a VLP-16, 1 s) x 6 seeds;
- convert: the 2 worlds samples, shipped `cpu` profile (the model loads once per worker);
- tiny: 120 tasks that each write one small file: the per-task cost of the executor itself.
Workers run 1 BLAS / torch thread each. Ray's start-up (a local instance) is reported apart and
not counted in the tasks-per-minute figures; the local pool's worker start-up is counted.

Run: `python -m bench.bench_batch [--quick]`. Results: bench/results/batch.{json,md}.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import yaml

from scube_sim.parallel.runner import run_batch
from scube_sim.parallel.tasks import Job, Task
from scube_sim.run_manifest import RunManifest
from scube_sim.runs.batch_jobs import make_job
from scube_sim.runs.scenario import shared_data_dir

from .common import write_results

REPLAY = {"name": "tiny", "seed": 4, "duration_s": 1.0,
          "scene": {"world": {"style": "suburban", "seed": 3, "layout": "straight", "length_m": 60},
                    "representation": "voxsplat", "voxel_size": 1.0, "gaussians_per_voxel": 1},
          "trajectory": {"source": "world"}, "sensors": [{"preset": "vlp16"}], "outputs": {"files": ["npz"]}}


class TinyJob(Job):
    """A task that writes one 16-byte file: what is left is the executor's own cost per task."""

    name = "tiny"

    def tasks(self, inputs, out):
        return [Task(f"t{int(i):04d}", i) for i in inputs]

    def manifest(self, task, out):
        return RunManifest("tiny", {}, {"i": task.input})

    def run(self, task, folder, out):
        (folder / "x.bin").write_bytes(task.input.encode().ljust(16))
        return {}


def measure(job_fn, inputs, executor, workers, root: Path, name: str) -> dict:
    out = root / f"{name}-{executor}-{workers}"
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    rep = run_batch(job_fn(), inputs, out, executor=executor, workers=workers, threads=1, progress=False)
    wall = time.perf_counter() - t0
    if rep.status != "complete":
        bad = next(r for r in rep.records.values() if r["status"] != "complete")
        raise RuntimeError(f"{name} on {executor}: {bad}")
    per_task = [r["seconds"] for r in rep.records.values()]
    return {"job": name, "executor": executor, "workers": workers, "tasks": rep.completed,
            "seconds": rep.seconds, "start_s": wall - rep.seconds, "tasks_per_min": rep.tasks_per_minute,
            "task_s_mean": sum(per_task) / len(per_task),
            "peak_mb_max": max(r["peak_mb"] for r in rep.records.values())}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer tasks (replay 2, tiny 30), no build")
    ap.add_argument("--executors", default="local,ray")
    args = ap.parse_args()
    try:
        import ray  # noqa: F401
    except ImportError:
        ray = None
    executors = [e for e in args.executors.split(",") if e != "ray" or ray is not None]
    root = Path(tempfile.mkdtemp(prefix="bench_batch-"))
    scen = root / "tiny.yaml"
    scen.write_text(yaml.safe_dump(REPLAY))
    data = root / "worlds-data"
    world_set = {"image_scale": 0.1}
    # the convert job's inputs: made once here, outside the timed runs
    run_batch(make_job("worlds", world_set), ["test:0-1"], data, executor="local", workers=2, progress=False)
    samples = [str(data / "test" / f"{i:06d}") for i in range(2)]
    logs = []
    nus = shared_data_dir() / "nuscenes-mmdet3d-demo"
    if nus.is_dir() and not args.quick:
        for n in ("log_a", "log_b"):
            (root / n).symlink_to(nus.resolve())
            logs.append(str(root / n))
    cases = [("worlds", lambda: make_job("worlds", world_set), ["test:0-1"]),
             ("replay", lambda: make_job("replay", {"seeds": list(range(2 if args.quick else 6))}), [str(scen)]),
             ("convert", lambda: make_job("convert", {"profile": "cpu"}), samples),
             ("tiny", TinyJob, [str(i) for i in range(30 if args.quick else 120)])]
    if logs:
        cases.insert(1, ("build", lambda: make_job("build", {"dataset": "nuscenes"}), logs))
    rows = []
    for name, job_fn, inputs in cases:
        for executor in executors:
            for workers in (1, 2):
                row = measure(job_fn, inputs, executor, workers, root, name)
                rows.append(row)
                print(f"{name:8s} {executor:5s} x{workers}: {row['tasks']} tasks in {row['seconds']:.1f} s "
                      f"({row['tasks_per_min']:.1f}/min, start {row['start_s']:.1f} s, peak {row['peak_mb_max']:.0f} MB)",
                      flush=True)
    by = {(r["job"], r["executor"], r["workers"]): r for r in rows}
    for r in rows:
        one = by[(r["job"], r["executor"], 1)]
        r["speedup_vs_1"] = r["tasks_per_min"] / one["tasks_per_min"]
        loc = by.get((r["job"], "local", r["workers"]))
        r["ray_over_local"] = loc["tasks_per_min"] / r["tasks_per_min"] if r["executor"] == "ray" and loc else float("nan")
    notes = ("tasks_per_min excludes Ray's start-up (start_s: a local Ray instance; for local, the time "
             "before the first task was sent). ray_over_local: the local pool's throughput over Ray's, same "
             "job and workers, same run (> 1: Ray slower). Workers: 1 BLAS/torch thread each; 2 cores.")
    path = write_results("batch", rows, ["job", "executor", "workers", "tasks", "seconds", "tasks_per_min",
                                         "speedup_vs_1", "ray_over_local", "task_s_mean", "start_s", "peak_mb_max"],
                         notes)
    shutil.rmtree(root, ignore_errors=True)
    print(f"-> {path}")


if __name__ == "__main__":
    main()
