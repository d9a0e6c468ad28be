"""Where batch tasks run. Every executor has `slots` (tasks it runs at once), `submit(ticket, job,
task, out, attempt)`, `wait()` (blocks until at least one attempt ends; returns [(ticket, record)],
the record `tasks.execute`'s, or status "crashed" when the worker died under the task) and
`close(kill=False)`.

- `InlineExecutor`: the calling process, one task at a time (`worlds generate -j 1`).
- `LocalExecutor`: `workers` spawned processes on this machine, each kept for many tasks (a model
  loads once per worker). The driver watches each worker's process: one that dies (killed, out of
  memory) fails its task's attempt and is replaced.
- `RayExecutor`: Ray tasks on a cluster (`address`) or on a Ray instance started here; Ray reuses
  its worker processes, so a model also loads once per worker. Optional: `pip install scube-sim[ray]`.

Workers get the same BLAS / OpenMP / torch thread count (`tasks.pinned_env`) on every executor
and ignore Ctrl-C (the driver stops them), so a task's outputs do not depend on where it ran.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import signal
from multiprocessing.connection import wait as wait_any

from .tasks import BatchError, execute, pinned_env

EXECUTORS = ("local", "ray")


def make_executor(name: str, *, workers: int, threads: int, address: str | None = None):
    if name == "inline":
        return InlineExecutor()
    if name == "local":
        return LocalExecutor(workers, threads)
    if name == "ray":
        return RayExecutor(workers, threads, address)
    raise BatchError(f"--executor: expected one of {', '.join(EXECUTORS)}, got {name!r}")  # run_batch checked


class InlineExecutor:
    slots = 1

    def __init__(self):
        self._queue: list = []

    def submit(self, ticket, job, task, out, attempt):
        self._queue.append((ticket, (job, task, out, attempt)))

    def wait(self):
        ticket, args = self._queue.pop(0)
        return [(ticket, execute(*args))]

    def close(self, kill: bool = False):
        self._queue.clear()


def _worker_main(conn) -> None:
    """A local worker: run (ticket, job, task, out, attempt) messages until the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        ticket, job, task, out, attempt = msg
        conn.send((ticket, execute(job, task, out, attempt)))


class _Worker:
    def __init__(self, ctx, env: dict[str, str]):
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_worker_main, args=(child,), daemon=True)
        saved = {k: os.environ.get(k) for k in env}
        os.environ.update(env)  # a spawned child takes the parent's environment at start
        try:
            self.proc.start()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        child.close()
        self.ticket: int | None = None


class LocalExecutor:
    def __init__(self, workers: int, threads: int):
        self.slots = workers
        self._ctx = mp.get_context("spawn")
        self._env = pinned_env(threads)
        self._workers = [_Worker(self._ctx, self._env) for _ in range(workers)]

    def submit(self, ticket, job, task, out, attempt):
        w = next(w for w in self._workers if w.ticket is None)
        w.ticket = ticket
        try:
            w.conn.send((ticket, job, task, out, attempt))
        except (BrokenPipeError, OSError):
            pass  # the worker is gone: `wait` sees its process end and reports the attempt crashed

    def wait(self):
        busy = [w for w in self._workers if w.ticket is not None]
        ready = set(wait_any([w.conn for w in busy] + [w.proc.sentinel for w in busy]))
        done = []
        for i, w in enumerate(self._workers):
            if w.ticket is None or not (w.conn in ready or w.proc.sentinel in ready):
                continue
            rec = None
            with contextlib.suppress(EOFError, OSError):
                if w.conn.poll():
                    ticket, rec = w.conn.recv()
            if rec is None:  # the process ended without answering
                w.proc.join(timeout=5)
                code = w.proc.exitcode
                why = f"signal {-code}" if code is not None and code < 0 else f"exit code {code}"
                rec = {"status": "crashed", "error": f"worker process {w.proc.pid} died ({why})",
                       "pid": w.proc.pid}
                w.conn.close()
                self._workers[i] = _Worker(self._ctx, self._env)
            done.append((w.ticket, rec))
            w.ticket = None
        return done

    def close(self, kill: bool = False):
        for w in self._workers:
            with contextlib.suppress(OSError):
                w.conn.close()
        for w in self._workers:
            if kill:
                w.proc.kill()
            w.proc.join(timeout=None if not kill else 5)
        self._workers = []


class RayExecutor:
    def __init__(self, workers: int, threads: int, address: str | None):
        try:
            import ray
        except ImportError:
            raise BatchError("--executor ray: Ray is not installed; pip install 'scube-sim[ray]'") from None
        self._ray = ray
        self.slots = workers
        self._started = not ray.is_initialized()
        if self._started:
            kw = {"address": address} if address else {"num_cpus": workers, "include_dashboard": False}
            ray.init(**kw, runtime_env={"env_vars": pinned_env(threads)}, logging_level="WARNING",
                     log_to_driver=False, configure_logging=False)
        self._remote = ray.remote(num_cpus=1, max_retries=0)(execute)  # our retries, the same on every executor
        self._refs: dict = {}

    def submit(self, ticket, job, task, out, attempt):
        self._refs[self._remote.remote(job, task, out, attempt)] = ticket

    def wait(self):
        ray = self._ray
        ready, _ = ray.wait(list(self._refs), num_returns=1)
        done = []
        for ref in ready:
            ticket = self._refs.pop(ref)
            try:
                rec = ray.get(ref)
            except ray.exceptions.RayError as exc:  # the worker died (killed, out of memory), or Ray lost it
                rec = {"status": "crashed", "error": f"Ray: {type(exc).__name__}: {' '.join(str(exc).split())[:300]}"}
            done.append((ticket, rec))
        return done

    def close(self, kill: bool = False):
        ray = self._ray
        if kill:
            for ref in self._refs:
                with contextlib.suppress(Exception):
                    ray.cancel(ref, force=True)
        self._refs = {}
        if self._started:
            ray.shutdown()
