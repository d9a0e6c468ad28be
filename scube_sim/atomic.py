"""Atomic file output: write to a temporary name beside the target, then rename; and write errors
that name the file they were writing (a full disk reports "[Errno 28]" with no path otherwise).

The temporary of target NAME is the hidden ``.NAME.tmp-PID`` (PID: the writing process). A kill
leaves it behind; the next atomic write of the same target removes those whose process is gone
(never one of a running process)."""

from __future__ import annotations

import contextlib
import errno
import os
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | Path):
    """Yield a temporary path in the target's folder; on success rename it over `path`.

    On an exception the temporary file is removed and `path` is left as it was, so a reader
    never sees a half-written file.
    """
    path = Path(path)
    if path.is_dir():  # else the rename fails naming the temporary file
        raise IsADirectoryError(errno.EISDIR, "is a folder; expected a file path", str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = temporary_name(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        if isinstance(exc, OSError):
            raise with_path(exc, path) from exc
        raise


def temporary_name(path: str | Path, pid: int | None = None) -> Path:
    """The temporary `atomic_path` writes `path` to in process `pid` (this one by default)."""
    path = Path(path)
    return path.with_name(f".{path.name}{TMP_MARK}{os.getpid() if pid is None else int(pid)}")


TMP_MARK = ".tmp-"


def pid_running(pid: int) -> bool:
    """Whether process `pid` exists on this machine and has not ended (a zombie has ended; a
    process of another user exists). Unsure counts as running."""
    if pid <= 0:
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    with contextlib.suppress(OSError, IndexError):  # Linux: an ended process not yet reaped is a zombie
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat[stat.rindex(")") + 2] not in "ZX"
    return True


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Remove the temporaries of target `path` (``.NAME.tmp-PID`` files beside it) that a killed
    writer left: those whose process PID no longer runs. Returns the paths removed."""
    path = Path(path)
    prefix = f".{path.name}{TMP_MARK}"
    removed = []
    try:
        names = [n for n in os.listdir(path.parent) if n.startswith(prefix)]
    except OSError:
        return removed
    for name in names:
        pid = name[len(prefix):]
        if not (pid.isdigit() and pid.isascii()) or int(pid) == os.getpid() or pid_running(int(pid)):
            continue
        stale = path.parent / name
        if stale.is_symlink() or not stale.is_file():
            continue  # only the plain files atomic_path writes
        with contextlib.suppress(FileNotFoundError):  # another writer removed it first
            stale.unlink()
            removed.append(stale)
    return removed


def with_path(exc: OSError, path: str | Path) -> OSError:
    """`exc` itself if it names a file already, else the same error (same class, errno and
    message) naming `path`."""
    if exc.filename is not None or exc.errno is None:
        return exc
    return type(exc)(exc.errno, exc.strerror, str(path))
