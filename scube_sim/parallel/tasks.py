"""A batch's unit of work and what a worker does with it: `Task`, the `Job` interface, and
`execute` (one attempt of one task, in whichever process the executor runs it). See `runner`."""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..atomic import atomic_path
from ..cpus import THREADS_ENV
from ..errors import InputError
from ..memory import peak_mb, reset_peak
from ..run_manifest import RunManifest, finish_run, prepare_output, read_manifest

STATE_DIR = ".batch"
# BLAS and OpenMP pools read these at start-up, our compiled cores SCUBE_SIM_THREADS
# (`cpus.THREADS_ENV`): each worker gets the same, whatever the executor
THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS",
               "VECLIB_MAXIMUM_THREADS", THREADS_ENV)


class BatchError(InputError):
    """A batch that cannot start: bad inputs, two inputs for one output folder, a bad executor."""


@dataclass
class Task:
    """One unit of work. key: its output folder, a relative POSIX path under OUT (unique in the
    batch); input: what the user named (a path, `train:17`); params: job-specific, JSON values."""

    key: str
    input: str
    params: dict = field(default_factory=dict)


class Job:
    """What a batch runs. A job object is built in the driver and sent to the workers (pickled), so
    it holds only its validated settings; `run` loads what it needs there (and may keep a model
    loaded per worker process in a module-level cache)."""

    name = ""
    keep: tuple[str, ...] = ()  # folders in a task's folder that survive a redo (caches with own keys)
    # True: `run` prepares and finishes the task folder's run manifest itself, or keeps no task
    # folder at all (its outputs carry their own key; the record then lists no outputs)
    own_manifest = False

    def tasks(self, inputs: list[str], out: Path) -> list[Task]:
        """The tasks for the user's inputs (`expand_inputs` applied); raise `BatchError` naming a bad one."""
        raise NotImplementedError

    def prepare(self, out: Path) -> None:
        """Driver-side set-up before any task (e.g. a dataset header)."""

    def manifest(self, task: Task, out: Path) -> RunManifest:
        """The run manifest a complete output of `task` carries (its inputs and settings)."""
        raise NotImplementedError

    def complete_without_manifest(self, folder: Path) -> bool:
        """Whether a task folder with no run manifest holds a whole output of an earlier version."""
        return False

    def run(self, task: Task, folder: Path, out: Path) -> dict:
        """Write the task's outputs into `folder` (atomically, file by file); return small stats."""
        raise NotImplementedError

    def describe(self) -> dict:
        """The job's settings, for batch.json."""
        return {}


def pinned_env(threads: int) -> dict[str, str]:
    """Environment variables that pin a worker's BLAS / OpenMP / torch threads and our cores'."""
    return {v: str(threads) for v in THREAD_VARS}


def one_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}" if str(exc) else type(exc).__name__


def marker_path(out: Path, key: str) -> Path:
    return out / STATE_DIR / "running" / (key.replace("/", "__") + ".json")


def execute(job: Job, task: Task, out: str, attempt: int) -> dict:
    """Run one task attempt (in a worker): its folder prepared under its run manifest, the job's
    outputs written, the manifest finished. Returns a JSON-able record: status "complete" or
    "failed" (with a one-line error), outputs (path -> sha256, bytes), seconds, peak_mb, pid, host."""
    out = Path(out)
    folder = out / task.key
    rec = {"key": task.key, "attempt": attempt, "pid": os.getpid(), "host": socket.gethostname()}
    with contextlib.suppress(OSError), atomic_path(marker_path(out, task.key)) as tmp:
        Path(tmp).write_text(json.dumps({**rec, "started": time.time()}))
    reset_peak()
    t0 = time.perf_counter()
    try:
        stats = _run_task(job, task, folder, out)
        manifest = read_manifest(folder)
        rec.update(status="complete", stats=stats, outputs=manifest.outputs if manifest is not None else {})
    except Exception as exc:
        rec.update(status="failed", error=one_line(exc))
    rec.update(seconds=time.perf_counter() - t0, peak_mb=peak_mb())
    return rec


def _run_task(job: Job, task: Task, folder: Path, out: Path) -> dict:
    if job.own_manifest:
        return job.run(task, folder, out) or {}
    manifest = job.manifest(task, out)
    resume = folder.is_dir() and read_manifest(folder) is not None
    state = prepare_output(folder, manifest, resume=resume, keep=job.keep)
    if state == "complete":
        return {"state": state}
    try:
        stats = job.run(task, folder, out) or {}
    except BaseException as exc:
        with contextlib.suppress(OSError):
            finish_run(folder, manifest, "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed",
                       one_line(exc), keep=job.keep)
        raise
    finish_run(folder, manifest, "complete", keep=job.keep)
    return {"state": state, **stats}


