"""The generic task pool: many independent tasks run as one resumable job, on a local process
pool or on a Ray cluster. It knows no job of ours (the jobs are in `scube_sim.runs.batch_jobs`).

- `runner`: the driver (`run_batch`): which tasks are already complete, dispatch, retries, the
  batch manifest, progress.
- `tasks`: `Task`, the `Job` interface (an object with `tasks`, `manifest` and `run`) and
  `execute`, what a worker does with one task.
- `executors`: where tasks run: `InlineExecutor` (the calling process), `LocalExecutor` (worker
  processes on this machine), `RayExecutor` (a Ray cluster, the optional `ray` extra).
"""
