"""Atomic writes on a failing disk: the target is untouched, no temporary is left, and the error
names the file it was writing (a full device says only "[Errno 28]"); the CLI reports it in one
line with exit code 2, and the sinks' manifests name themselves too."""

from __future__ import annotations

import errno
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from scube_sim.atomic import atomic_path, with_path
from scube_sim.cli import app
from scube_sim.sim.sinks.files import _append
from scube_sim.voxsplat import VoxSplat


def enospc():
    return OSError(errno.ENOSPC, "No space left on device")  # what write() on a full disk raises


def test_a_write_error_names_the_target_and_leaves_it_as_it_was(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(OSError) as info:
        with atomic_path(target) as tmp:
            Path(tmp).write_text("half")
            raise enospc()
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(target)
    assert str(target) in str(info.value)
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_errors_that_name_a_file_or_are_not_os_errors_pass_unchanged(tmp_path):
    named = FileNotFoundError(errno.ENOENT, "No such file or directory", "/elsewhere/x")
    assert with_path(named, tmp_path / "y") is named
    with pytest.raises(ValueError, match="bad value"):
        with atomic_path(tmp_path / "z"):
            raise ValueError("bad value")
    assert not any(tmp_path.iterdir())


def test_a_real_full_device_names_the_manifest():
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full on this system")
    with open("/dev/full", "a", encoding="utf-8") as fh, pytest.raises(OSError) as info:
        _append(fh, "x" * 10_000 + "\n")
    assert info.value.errno == errno.ENOSPC and info.value.filename == "/dev/full"


def test_the_cli_reports_a_full_disk_in_one_line_naming_the_output(tmp_path, monkeypatch):
    src = VoxSplat(ijk=np.zeros((1, 3)), params=np.zeros((1, 1, 14)), voxel_size=0.1).save(tmp_path / "s.npz")

    def full(*args, **kwargs):
        raise enospc()

    monkeypatch.setattr(np, "savez_compressed", full)
    out = tmp_path / "copy.npz"
    res = CliRunner().invoke(app, ["export", str(src), "--to", "npz", "-o", str(out)])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert lines == [f"error: {out}: No space left on device"]
    assert not out.exists()


def test_an_unexpected_exception_still_shows_as_a_bug(tmp_path, monkeypatch):
    """Only our errors and file-system errors become one line: anything else is a bug and keeps
    its traceback (exit code 1, the exception itself)."""
    src = VoxSplat(ijk=np.zeros((1, 3)), params=np.zeros((1, 1, 14)), voxel_size=0.1).save(tmp_path / "s.npz")

    def broken(*args, **kwargs):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(np, "savez_compressed", broken)
    res = CliRunner().invoke(app, ["export", str(src), "--to", "npz", "-o", str(tmp_path / "c.npz")])
    assert res.exit_code == 1 and isinstance(res.exception, ZeroDivisionError)


def _limited_file_size(limit: int):
    """preexec_fn: writes past `limit` bytes fail with EFBIG (SIGXFSZ ignored), as on a full disk."""
    import resource
    import signal

    def apply():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return apply


@pytest.mark.parametrize("to", ["usdc", "npz", "ply"])
def test_export_past_the_file_size_limit_is_one_line_naming_the_output(tmp_path, to):
    """A real failing write (RLIMIT_FSIZE in a child process; pxr's own writer for usdc) ends as
    one line naming the output, exit code 2, and no output file."""
    import subprocess
    import sys

    rng = np.random.default_rng(0)
    n = 20_000
    params = rng.normal(0, 1, (n, 1, 14))
    params[..., 4:7] = np.log(0.05)  # sub-voxel Gaussians: nothing for load to clamp
    src = VoxSplat(ijk=np.stack([np.arange(n), np.zeros(n), np.zeros(n)], 1), params=params,
                   voxel_size=0.1).save(tmp_path / "s.npz")
    out = tmp_path / f"out.{to}"
    res = subprocess.run([sys.executable, "-m", "scube_sim.cli", "export", str(src), "--to", to, "-o", str(out)],
                         capture_output=True, text=True, preexec_fn=_limited_file_size(src.stat().st_size // 4))
    lines = [ln for ln in (res.stdout + res.stderr).splitlines() if ln.strip()]
    assert res.returncode == 2, res.stdout + res.stderr
    assert len(lines) == 1 and str(out) in lines[0] and "large" in lines[0].lower(), lines
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["s.npz"]
