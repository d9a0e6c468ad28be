"""What every command module shares: the typer app and its sub-apps, the `handle_errors` decorator
that turns errors into one-line messages and exit codes, and option parsing (--pose, index lists)."""

from __future__ import annotations

import functools
import inspect

import numpy as np
import typer

from ..config import Range
from ..errors import ScubeSimError

app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode="rich",
                  help="LiDAR simulation on VoxSplats (SCube): hard-opacity Gaussian ray tracing with Embree.")
datasets_app = typer.Typer(no_args_is_help=True, help="Real sensor datasets: export to the generic folder format.")
app.add_typer(datasets_app, name="datasets")
worlds_app = typer.Typer(no_args_is_help=True, help="Procedural driving worlds and their datasets.")
app.add_typer(worlds_app, name="worlds")

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report it


class CliError(ScubeSimError):
    """An input problem to report in one line (exit code 2)."""


def _fail(msg: str) -> None:
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(EXIT_USAGE)


def handle_errors(command):
    """Decorate a command (under `@app.command`): our errors (`ScubeSimError`) and file-system errors
    become one-line messages and exit code 2, Ctrl-C one line and exit code 130; anything else is
    a bug and shows its traceback. `functools.wraps` keeps the signature typer reads the options from."""

    @functools.wraps(command)
    def run(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except ScubeSimError as exc:
            msg = str(exc).strip().splitlines()
            _fail(msg[0] if len(msg) == 1 else "; ".join(msg))
        except OSError as exc:
            if exc.strerror is None and exc.args:  # raised with a message of ours, e.g. "X: no such scene file"
                _fail(str(exc.args[0]))
            _fail(f"{getattr(exc, 'filename', '') or ''}: {exc.strerror or exc}".lstrip(": "))
        except KeyboardInterrupt:
            # every output is whole (atomic files, sinks closed with the frames completed)
            typer.echo("interrupted: the outputs written so far are complete files", err=True)
            raise typer.Exit(EXIT_INTERRUPTED) from None

    return run


def _option_name(param: inspect.Parameter) -> str:
    decls = getattr(param.default, "param_decls", None) or ()
    longs = [d for d in decls if d.startswith("--")]
    return max(longs, key=len) if longs else (decls[0] if decls else param.name)


def bounded(**ranges: Range):
    """Decorate a command (under `@handle_errors`) with its numeric options' valid ranges, by
    parameter name: each given value is checked before the command runs, and one out of range
    (NaN and infinity too) is a one-line error naming the option and the range
    (`error: --steps: expected an integer from 1 to 1000, got 0`, exit 2). Each option's help
    shows its range."""

    def decorate(command):
        sig = inspect.signature(command)
        names = {}
        for key, rng in ranges.items():
            param = sig.parameters[key]  # a KeyError here is a typo in the decorator
            names[key] = _option_name(param)
            info = param.default
            if hasattr(info, "param_decls"):  # rich markup: no square brackets
                info.help = f"{info.help or ''} (valid: {rng.describe()})".strip()

        @functools.wraps(command)
        def run(*args, **kwargs):
            given = sig.bind_partial(*args, **kwargs).arguments
            for key, rng in ranges.items():
                if key in given:
                    rng.check(given[key], names[key], error=CliError)
            return command(*args, **kwargs)

        return run

    return decorate


def threads_option():
    """A command's --threads option (a new one per command: `bounded` writes its range into the help)."""
    return typer.Option(0, "--threads", help="threads of every pool the command starts: torch, OpenMP, the "
                        "compiled cores, Embree (0: the environment variable SCUBE_SIM_THREADS, else the CPUs "
                        "this process may use: its affinity mask and container CPU quota)")


def start_threads(threads: int) -> int:
    """Size the command's pools (`cpus.use_threads`) from --threads (`cpus.resolve_threads`)."""
    from ..cpus import resolve_threads, use_threads

    return use_threads(resolve_threads(threads))


def parse_pose(text: str) -> np.ndarray:
    """--pose x,y,z,roll,pitch,yaw (metres, degrees) -> (4, 4) pose."""
    from ..transforms import pose_from_xyz_rpy

    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise CliError(f"--pose: expected six numbers x,y,z,roll,pitch,yaw (metres, degrees), got {text!r}")
    if len(vals) != 6 or not np.all(np.isfinite(vals)):
        raise CliError(f"--pose: expected six finite numbers x,y,z,roll,pitch,yaw (metres, degrees), got {text!r}")
    return pose_from_xyz_rpy(vals[:3], vals[3:])


def int_list(text: str, flag: str) -> list[int]:
    """Comma-separated sample indices of option `flag` ("" -> [])."""
    try:
        vals = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise CliError(f"{flag}: expected comma-separated sample indices, got {text!r}")
    for v in vals:
        if v < 0:
            raise CliError(f"{flag}: expected comma-separated sample indices >= 0, got {text!r}")
    return name_list(vals, flag)


def name_list(items: list, flag: str) -> list:
    """`items` of option `flag`, or a CliError naming the one it lists twice:
    `--samples: 0 is listed twice (at [0] and [2])`."""
    from ..config import listed_twice

    msg = listed_twice(items)
    if msg:
        raise CliError(f"{flag}: {msg}")
    return items


def stage_lines(enabled: bool = True):
    """A `status` callback for a long command: each stage's line on stderr, after the seconds since
    the command started (rich's console on a terminal; plain lines in a log file or CI, where they
    appear as each stage starts). None when `enabled` is False (--no-progress)."""
    import sys
    import time

    if not enabled:
        return None
    t0 = time.perf_counter()
    if sys.stderr.isatty():
        from rich.console import Console

        console = Console(stderr=True, highlight=False)
        return lambda line: console.print(f"[dim]{time.perf_counter() - t0:6.1f} s[/dim]  {line}")
    return lambda line: typer.echo(f"{time.perf_counter() - t0:6.1f} s  {line}", err=True)


def track(items, description: str):
    """Iterate `items` (a sized sequence) with progress: rich's bar on a terminal; elsewhere (a log
    file, CI) one line per finished item on stderr with the elapsed time, where rich would print
    nothing until the end."""
    import sys
    import time

    if sys.stderr.isatty():
        from rich.progress import track as rich_track

        yield from rich_track(items, description=description)
        return
    n, t0 = len(items), time.perf_counter()
    for i, item in enumerate(items, 1):
        yield item
        typer.echo(f"{description}: {i}/{n} done, {time.perf_counter() - t0:.0f} s", err=True)
