"""The CPUs this process may really use, and the one thread count every pool is sized from.

A process may be pinned to a few cores (`taskset`, a batch scheduler) or limited by its
container's CPU quota (a pod given 2 CPUs on a 64-core host): `os.cpu_count()` sees neither, and
a pool sized from it runs more threads than cores, which then wait for each other at every
parallel region. `usable_cpus` reads the affinity mask and the cgroup quota (v2 ``cpu.max``, v1
``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``, on the process's own cgroup and those above it);
`resolve_threads` turns a user's request (``--threads N``, the environment variable
SCUBE_SIM_THREADS, else all usable CPUs) into the count every pool gets; `use_threads` gives it
to the pools a command starts (torch, OpenMP, BLAS) and, through the environment, to its workers.
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

from .errors import InputError

THREADS_ENV = "SCUBE_SIM_THREADS"
CGROUP_ROOT = Path("/sys/fs/cgroup")
PROC_CGROUP = Path("/proc/self/cgroup")


def affinity_cpus() -> int:
    """CPUs in this process's affinity mask (os.cpu_count() where the platform has no mask)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except OSError:
        return None


def _quota_v2(folder: Path) -> float | None:
    """CPUs allowed by ``cpu.max`` ("max 100000" or "<quota> <period>" in microseconds)."""
    text = _read(folder / "cpu.max")
    if not text:
        return None
    parts = text.split()
    if parts[0] == "max" or len(parts) != 2:
        return None
    try:
        quota, period = int(parts[0]), int(parts[1])
    except ValueError:
        return None
    return quota / period if quota > 0 and period > 0 else None


def _quota_v1(folder: Path) -> float | None:
    """CPUs allowed by ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us`` (-1: no quota)."""
    quota, period = _read(folder / "cpu.cfs_quota_us"), _read(folder / "cpu.cfs_period_us")
    try:
        q, p = int(quota), int(period)
    except (TypeError, ValueError):
        return None
    return q / p if q > 0 and p > 0 else None


def _upwards(root: Path, rel: str) -> list[Path]:
    """The cgroup folder of `rel` under `root` and every folder above it up to `root` (a quota on a
    parent limits its children; inside a container the namespace root is the container's own)."""
    parts = [p for p in rel.strip("/").split("/") if p and p != ".."]
    out = [root.joinpath(*parts[:i]) for i in range(len(parts), -1, -1)]
    return list(dict.fromkeys(out))


def cgroup_cpus(root: Path | None = None, proc_cgroup: Path | None = None) -> float | None:
    """The tightest CPU quota over this process's cgroups (v2 and v1), in CPUs; None without one.
    root, proc_cgroup: the cgroup mount and the process's cgroup list (default CGROUP_ROOT and
    PROC_CGROUP)."""
    root = CGROUP_ROOT if root is None else Path(root)
    text = _read(PROC_CGROUP if proc_cgroup is None else Path(proc_cgroup))
    if text is None:
        return None
    quotas = []
    for line in text.splitlines():
        fields = line.split(":", 2)
        if len(fields) != 3:
            continue
        _, controllers, rel = fields
        if controllers == "":  # cgroup v2: one unified hierarchy
            quotas += [q for f in _upwards(root, rel) if (q := _quota_v2(f)) is not None]
        elif "cpu" in controllers.split(","):
            for mount in (root / controllers, root / "cpu", root / "cpu,cpuacct"):
                quotas += [q for f in _upwards(mount, rel) if (q := _quota_v1(f)) is not None]
    return min(quotas) if quotas else None


_QUOTAS: dict[tuple[Path, Path], float | None] = {}  # the process's own cgroup quota, read once


def usable_cpus(root: Path | None = None, proc_cgroup: Path | None = None) -> int:
    """CPUs this process may run on at once: its affinity mask capped by its cgroup quota
    (rounded up: a quota of 1.5 CPUs keeps two threads busy part of the time), at least 1.
    The quota of the default cgroup files is read once per process (every trace call asks, and a
    container's quota is set when it starts); the affinity mask, a system call, at each call."""
    n = affinity_cpus()
    if root is None and proc_cgroup is None:
        key = (CGROUP_ROOT, PROC_CGROUP)
        if key not in _QUOTAS:
            _QUOTAS[key] = cgroup_cpus(*key)
        quota = _QUOTAS[key]
    else:
        quota = cgroup_cpus(root, proc_cgroup)
    if quota is not None:
        n = min(n, max(1, math.ceil(quota - 1e-9)))
    return max(1, n)


def resolve_threads(requested: int | None = None, *, where: str = "--threads") -> int:
    """The thread count a command's pools get: `requested` when given (0 or None: not given),
    else the environment variable SCUBE_SIM_THREADS, else `usable_cpus()`. A count above the
    usable CPUs is kept (the user asked for it); a negative or non-integer one is an InputError
    naming `where` or the variable."""
    if requested is not None and requested != 0:
        if int(requested) != requested or requested < 0:
            raise InputError(f"{where}: expected 0 (all usable CPUs) or a positive count, got {requested}")
        return int(requested)
    env = os.environ.get(THREADS_ENV, "").strip()
    if env:
        try:
            n = int(env)
        except ValueError:
            raise InputError(f"{THREADS_ENV}: expected a positive thread count, got {env!r}") from None
        if n < 0:
            raise InputError(f"{THREADS_ENV}: expected a positive thread count, got {env!r}")
        if n > 0:
            return n
    return usable_cpus()


# Read by the BLAS and OpenMP pools when they start (torch's among them): a process sized by
# `use_threads` before torch loads starts its pools at that size.
POOL_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def use_threads(threads: int) -> int:
    """Size every pool of this process (and of the processes it starts) to `threads` (>= 1): the
    environment variable SCUBE_SIM_THREADS that `resolve_threads` and the compiled cores read,
    the OpenMP / BLAS variables for pools not started yet, and torch's intra-op pool where torch
    is already loaded. Returns `threads`."""
    n = int(threads)
    if n < 1:
        raise InputError(f"threads: expected a positive count, got {threads}")
    os.environ[THREADS_ENV] = str(n)
    torch = sys.modules.get("torch")
    if torch is None:
        for var in POOL_VARS:
            os.environ[var] = str(n)
    else:
        torch.set_num_threads(n)
    return n


def share_threads(workers: int, requested: int | None = None) -> int:
    """Threads per worker when `workers` processes run side by side: `requested` when given, else
    the process's count (`resolve_threads`) split evenly, at least 1."""
    if requested:
        return resolve_threads(requested)
    return max(1, resolve_threads(None) // max(1, int(workers)))
