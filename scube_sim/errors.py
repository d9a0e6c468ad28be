"""The one error base. Every error a user can cause derives from `ScubeSimError`, so the CLI
reports ours in one line (exit 2) and lets anything else show as the bug it is."""

from __future__ import annotations


class ScubeSimError(Exception):
    """Base of scube-sim's typed errors; the message names the file, key or argument at fault."""

    def __init__(self, *args):
        if len(args) == 1 and isinstance(args[0], str):
            args = (_worker_message(type(self), args[0]),)
        super().__init__(*args)


def _worker_message(cls: type, msg: str) -> str:
    """Our own message of an error raised in a torch DataLoader worker: torch re-raises it in the
    main process as ``cls("Caught <cls> in DataLoader worker process N.\\nOriginal Traceback ...")``
    with the worker's whole traceback; keep what follows its last ``<module>.<class>: `` line."""
    if not msg.startswith("Caught ") or "\nOriginal Traceback" not in msg:
        return msg
    head = f"\n{cls.__module__}.{cls.__qualname__}: "
    at = msg.rfind(head)
    return msg[at + len(head):].strip() if at >= 0 else msg


class InputError(ScubeSimError, ValueError):
    """A value, array or file content the caller gave that cannot be used (a `ValueError` too,
    so code written against the plain exception keeps working)."""


class NotFoundError(ScubeSimError, KeyError):
    """A name that is not there (a label, a sensor, a camera); the message lists what is."""

    def __str__(self) -> str:  # KeyError's str() quotes its message
        return str(self.args[0]) if self.args else ""


class OutOfRangeError(ScubeSimError, IndexError):
    """An index past the end (a dataset sample, a frame); an `IndexError`, so iteration stops."""


class ScubeSimWarning(UserWarning):
    """Something a user's input made us change and say so (a clamp, a skipped record); the
    message names the file or key and counts what changed. The CLI prints it as one line."""
