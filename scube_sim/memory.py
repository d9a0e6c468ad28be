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
