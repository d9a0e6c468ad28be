"""Atomic file output: write to a temporary name beside the target, then rename; and write errors
that name the file they were writing (a full disk reports "[Errno 28]" with no path otherwise)."""

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
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        if isinstance(exc, OSError):
            raise with_path(exc, path) from exc
        raise


def with_path(exc: OSError, path: str | Path) -> OSError:
    """`exc` itself if it names a file already, else the same error (same class, errno and
    message) naming `path`."""
    if exc.filename is not None or exc.errno is None:
        return exc
    return type(exc)(exc.errno, exc.strerror, str(path))
