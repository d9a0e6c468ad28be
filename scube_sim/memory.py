"""Process memory probes (Linux /proc): resident set size and its peak, which the kernel lets a
process reset, so one step's peak can be read on its own. Used by evaluations and `bench/`."""

from __future__ import annotations


def _status_mb(key: str) -> float:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def rss_mb() -> float:
    """Resident set size now, MB (nan where /proc is missing)."""
    return _status_mb("VmRSS:")


def peak_mb() -> float:
    """Peak resident set size since the process started or the last `reset_peak`, MB."""
    return _status_mb("VmHWM:")


def reset_peak() -> bool:
    """Reset the kernel's peak-RSS counter (VmHWM) of this process; False if not allowed."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def available_bytes() -> int | None:
    """Memory the machine can give a new allocation now (MemAvailable of /proc/meminfo, capped
    by a cgroup limit where one is set), bytes; None where neither can be read."""
    avail = None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    for path, used in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                       ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            with open(path) as fh, open(used) as fu:
                limit = fh.read().strip()
                if limit.isdigit() and int(limit) < 1 << 60:
                    room = max(int(limit) - int(fu.read().strip()), 0)
                    avail = room if avail is None else min(avail, room)
            break
        except (OSError, ValueError):
            continue
    return avail


def format_bytes(n: float) -> str:
    for unit, size in (("TB", 1 << 40), ("GB", 1 << 30), ("MB", 1 << 20), ("kB", 1 << 10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} B"


def check_fits(nbytes: float, what: str, error: type[Exception] = ValueError, hint: str = "") -> None:
    """Raise `error` before allocating when `what` (a sentence naming the key and the size, e.g.
    'sky_size [100000, 200000] = 2e+10 panorama pixels') would need more memory than the machine
    has available now: 'WHAT needs about 7.5 TB of memory; 12.3 GB is available' (then `hint`,
    what the user can do, after a semicolon)."""
    avail = available_bytes()
    if avail is not None and nbytes > avail:
        raise error(f"{what} needs about {format_bytes(nbytes)} of memory; {format_bytes(avail)} is available"
                    + (f"; {hint}" if hint else ""))
