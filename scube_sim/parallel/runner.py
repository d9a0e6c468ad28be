"""The batch driver: tasks in, each task's outputs in its own folder under OUT, resumable.

    OUT/<task key>/...             a task's outputs and its run manifest (`scube_sim.run_manifest`,
                                   the scheme `replay --resume` uses): the proof a task is complete
    OUT/batch.json                 the batch manifest: per task its input, status, attempts,
                                   seconds, peak memory, error and output checksums
    OUT/.batch/attempts.jsonl      one line per finished attempt (appended, flushed)
    OUT/.batch/running/<key>.json  written by a worker when it starts a task (pid, host, attempt),
                                   removed by the driver when the attempt ends

A task whose folder holds a complete run manifest for the same inputs and settings, with every
output's checksum intact, is skipped; any other is (re)run from scratch, so an interrupted batch
run again finishes only what is missing and gives the same bytes. A failed attempt (an exception,
or a worker process that died) is retried up to `retries` times, then recorded as failed; the
other tasks go on. Timings live only in batch.json and the attempts log, so task folders are
byte-identical across executors, worker counts and reruns.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from ..atomic import atomic_path
from ..errors import ScubeSimError
from ..run_manifest import MANIFEST_NAME, is_complete, read_manifest
from .executors import EXECUTORS, make_executor
from .tasks import STATE_DIR, BatchError, Job, Task, marker_path

BATCH_FILE = "batch.json"
FORMAT = "scube-sim-batch"
VERSION = 1
SUMMARY_EVERY_S = 2.0  # batch.json is rewritten at most this often while tasks finish (and at the end)


def expand_inputs(items: list[str]) -> list[str]:
    """The user's `--inputs`: each item a list file (`@FILE` or a .txt/.list file: one input per
    line, `#` comments), a glob pattern (sorted matches; none matching is an error), or a
    comma-separated list; order kept, duplicates dropped."""
    out: list[str] = []
    for item in items:
        if item.startswith("@") or (item.endswith((".txt", ".list")) and Path(item).is_file()):
            path = Path(item.removeprefix("@"))
            if not path.is_file():
                raise BatchError(f"--inputs {item}: no such list file")
            lines = [ln.split("#", 1)[0].strip() for ln in path.read_text(encoding="utf-8").splitlines()]
            out += [ln for ln in lines if ln]
        elif any(c in item for c in "*?["):
            base = Path(item).anchor or "."
            pattern = str(Path(item).relative_to(base)) if Path(item).is_absolute() else item
            hits = sorted(str(p) for p in Path(base).glob(pattern))
            if not hits:
                raise BatchError(f"--inputs {item}: the pattern matches nothing")
            out += hits
        else:
            out += [s.strip() for s in item.split(",") if s.strip()]
    seen: set[str] = set()
    return [s for s in out if not (s in seen or seen.add(s))]


@dataclass
class BatchReport:
    """What `run_batch` did. records: key -> the task's batch.json entry."""

    job: str
    status: str  # complete | failed | interrupted
    total: int
    skipped: int
    completed: int
    failed: int
    attempts: int
    seconds: float
    records: dict[str, dict]

    @property
    def tasks_per_minute(self) -> float:
        return 60.0 * self.completed / self.seconds if self.seconds > 0 else 0.0


def run_batch(job: Job, inputs: list[str], out: str | Path, *, executor: str = "local", workers: int = 1,
              retries: int = 1, threads: int = 1, address: str | None = None, progress: bool = True) -> BatchReport:
    """Run `job` over `inputs` (`expand_inputs`) into the folder `out` (module doc).

    executor: "inline" (this process, one task at a time), "local" (`workers` processes) or "ray"
    (`workers` tasks at a time on the Ray cluster at `address`, or a local Ray instance started
    here with `workers` CPUs). threads: BLAS / OpenMP / torch threads per worker. retries: further
    attempts after a failed one. A Ctrl-C stops the workers, records the batch as interrupted and
    re-raises `KeyboardInterrupt`."""
    out = Path(out)
    if workers < 1 or retries < 0 or threads < 1:
        raise BatchError(f"--workers and --threads must be >= 1 and --retries >= 0; got {workers}, {threads}, "
                         f"{retries}")
    if executor not in ("inline", *EXECUTORS):
        raise BatchError(f"--executor: expected one of {', '.join(EXECUTORS)}, got {executor!r}")
    if address and executor != "ray":
        raise BatchError("--address: only for --executor ray")
    if out.exists() and not out.is_dir():
        raise BatchError(f"{out}: the output folder is a file")
    out.mkdir(parents=True, exist_ok=True)
    job.prepare(out)
    tasks = job.tasks(expand_inputs(inputs), out)
    by_key: dict[str, Task] = {}
    for t in tasks:
        if t.key in by_key:
            raise BatchError(f"inputs {by_key[t.key].input!r} and {t.input!r} both write {out / t.key}; "
                             f"rename one or run them as two batches")
        by_key[t.key] = t
    running = out / STATE_DIR / "running"
    running.mkdir(parents=True, exist_ok=True)
    for stale in running.glob("*.json"):  # an earlier driver's, killed before it cleaned up
        stale.unlink()

    records: dict[str, dict] = {}
    todo: list[Task] = []
    for t in tasks:
        folder = out / t.key
        if folder.is_dir() and _complete(job, t, folder, out):
            records[t.key] = {"input": t.input, "status": "complete", "skipped": True, "attempts": 0,
                              "outputs": read_manifest(folder).outputs}
        elif folder.is_dir() and not (folder / MANIFEST_NAME).exists() and job.complete_without_manifest(folder):
            records[t.key] = {"input": t.input, "status": "complete", "skipped": True, "attempts": 0,
                              "outputs": {}}
        else:
            todo.append(t)
    skipped = len(tasks) - len(todo)

    summary = _Summary(out, job, executor, workers, threads, records)
    ex = make_executor(executor, workers=workers, threads=threads, address=address) if todo else None
    bar = _Bar(job.name, len(todo), progress)
    counter = itertools.count()
    pending = deque((t, 1) for t in todo)
    inflight: dict[int, tuple[Task, int]] = {}
    attempts = completed = failed = 0
    t_start = time.perf_counter()
    log = open(out / STATE_DIR / "attempts.jsonl", "a", encoding="utf-8")
    try:
        while pending or inflight:
            while pending and len(inflight) < ex.slots:
                task, attempt = pending.popleft()
                ticket = next(counter)
                inflight[ticket] = (task, attempt)
                ex.submit(ticket, job, task, str(out), attempt)
            for ticket, rec in ex.wait():
                task, attempt = inflight[ticket]  # dropped once recorded: a Ctrl-C in between marks it interrupted
                attempts += 1
                with contextlib.suppress(FileNotFoundError):
                    marker_path(out, task.key).unlink()
                rec = {"key": task.key, "input": task.input, "attempt": attempt, **rec}
                entry = {"input": task.input, "status": rec["status"], "attempts": attempt,
                         "seconds": rec.get("seconds"), "peak_mb": rec.get("peak_mb"), "error": rec.get("error"),
                         "outputs": rec.get("outputs", {}), "stats": rec.get("stats", {})}
                if rec["status"] == "complete":
                    completed += 1
                    bar.advance()
                elif attempt <= retries:
                    pending.append((task, attempt + 1))
                    entry["status"] = "retrying"
                    bar.note(f"{task.key}: attempt {attempt} failed ({rec.get('error')}); retrying")
                else:
                    failed += 1
                    bar.advance()
                    bar.note(f"{task.key}: failed after {attempt} attempt(s): {rec.get('error')}")
                records[task.key] = entry  # before the log line: a Ctrl-C between them loses no result
                del inflight[ticket]
                log.write(json.dumps(rec, sort_keys=True) + "\n")
                log.flush()
                summary.save("running")
    except KeyboardInterrupt:
        if ex is not None:
            ex.close(kill=True)
            ex = None
        for task, attempt in [*inflight.values(), *pending]:
            records[task.key] = {"input": task.input, "status": "interrupted", "attempts": attempt - 1}
        summary.save("interrupted", force=True)
        raise
    finally:
        if ex is not None:
            ex.close()
        bar.stop()
        log.close()
    status = "failed" if failed else "complete"
    summary.save(status, force=True)
    return BatchReport(job.name, status, len(tasks), skipped, completed, failed, attempts,
                       time.perf_counter() - t_start, records)


def _complete(job: Job, task: Task, folder: Path, out: Path) -> bool:
    try:
        expected = job.manifest(task, out)
    except (ScubeSimError, OSError):
        return False  # e.g. a broken scenario file: its task runs, fails with the message and is recorded
    return is_complete(folder, expected, keep=job.keep)


class _Summary:
    """batch.json, rewritten atomically (at most every SUMMARY_EVERY_S while the batch runs)."""

    def __init__(self, out: Path, job: Job, executor: str, workers: int, threads: int, records: dict):
        self.path = out / BATCH_FILE
        self.head = {"format": FORMAT, "version": VERSION, "job": job.name, "settings": job.describe(),
                     "executor": executor, "workers": workers, "threads_per_worker": threads}
        self.records = records
        self.last = 0.0

    def save(self, status: str, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self.last < SUMMARY_EVERY_S:
            return
        self.last = now
        counts: dict[str, int] = {}
        for r in self.records.values():
            counts[r["status"]] = counts.get(r["status"], 0) + 1
        data = {**self.head, "status": status, "counts": counts,
                "tasks": {k: self.records[k] for k in sorted(self.records)}}
        with atomic_path(self.path) as tmp:
            Path(tmp).write_text(json.dumps(data, indent=1, sort_keys=True) + "\n", encoding="utf-8")


class _Bar:
    """A rich progress bar with throughput (tasks per minute) and ETA; silent when off."""

    def __init__(self, name: str, total: int, on: bool):
        self.bar = None
        if not (on and total):
            return
        self.t0 = time.perf_counter()
        self.bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                            TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), TextColumn("ETA"),
                            TimeRemainingColumn())
        self.bar.start()
        self.task = self.bar.add_task(f"batch {name}", total=total, rate="")

    def advance(self) -> None:
        if self.bar is not None:
            done = self.bar.tasks[0].completed + 1
            rate = 60.0 * done / max(time.perf_counter() - self.t0, 1e-9)
            self.bar.update(self.task, advance=1, rate=f"{rate:.1f} tasks/min")

    def note(self, text: str) -> None:
        if self.bar is not None:
            self.bar.console.print(text)

    def stop(self) -> None:
        if self.bar is not None:
            self.bar.stop()
