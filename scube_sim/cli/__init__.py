"""`scube-sim` command line. Errors print one line naming the problem and exit with code 2.
The app and `handle_errors` are in `_common`; each command group is a module here that registers on import."""

from __future__ import annotations

import warnings

import typer

from ..errors import ScubeSimWarning
from . import build, convert, eval, lidar, runs, train, worlds  # noqa: F401  (each registers its commands)
from ._common import EXIT_INTERRUPTED, EXIT_USAGE, CliError, app, datasets_app, handle_errors, worlds_app

__all__ = ["EXIT_INTERRUPTED", "EXIT_USAGE", "CliError", "app", "datasets_app", "handle_errors", "main",
           "worlds_app"]

# the order `scube-sim --help` lists the commands in (then the sub-apps: datasets, worlds)
COMMAND_ORDER = ["lidar", "export", "render", "sensors", "demo", "replay", "build", "convert", "fidelity", "batch",
                 "train", "eval"]
app.registered_commands.sort(key=lambda c: COMMAND_ORDER.index(c.name) if c.name in COMMAND_ORDER
                            else len(COMMAND_ORDER))


def _show_warning(message, category, filename, lineno, file=None, line=None):
    # Ours are for the user, one line each; anyone else's keep Python's format.
    if issubclass(category, ScubeSimWarning):
        typer.echo(f"warning: {message}", err=True)
    else:
        _python_showwarning(message, category, filename, lineno, file, line)


_python_showwarning = warnings.showwarning


def main() -> None:
    warnings.showwarning = _show_warning
    app()
