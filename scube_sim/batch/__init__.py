"""Batches: many independent tasks (generate worlds, build scenes from logs, convert camera frames,
replay scenarios) run as one resumable job, on a local process pool or on a Ray cluster.

- `runner`: the driver (`run_batch`): which tasks are already complete, dispatch, retries, the
  batch manifest, progress.
- `tasks`: `Task`, the `Job` interface (an object with `tasks`, `manifest` and `run`) and
  `execute`, what a worker does with one task.
- `executors`: where tasks run: `InlineExecutor` (the calling process), `LocalExecutor` (worker
  processes on this machine), `RayExecutor` (a Ray cluster, the optional `ray` extra).
- `jobs`: the four jobs of `scube-sim batch` (worlds, build, replay, convert).

This package file imports nothing, so the lower layers (the worlds generator) may use the runner
without pulling the jobs, which import the whole program.
"""
