"""What a killed atomic write leaves (its hidden ``.NAME.tmp-PID`` temporary) is removed by the
next write of the same target, by any command; the temporaries of running writers are not."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from scube_sim.atomic import atomic_path, pid_running, remove_stale_temporaries, temporary_name
from scube_sim.cli import app
from scube_sim.voxsplat import VoxSplat

ROOT = Path(__file__).resolve().parents[1]

# A writer inside atomic_path: half its bytes written, it says so, then waits for a line on stdin
# (or its SIGKILL) before it finishes.
WRITER = f"""
import sys
sys.path.insert(0, {str(ROOT)!r})
from pathlib import Path
from scube_sim.atomic import atomic_path
with atomic_path(sys.argv[1]) as tmp:
    Path(tmp).write_bytes(b"half of it")
    print("writing", tmp, flush=True)
    sys.stdin.readline()
    Path(tmp).write_bytes(b"the writer's own")
print("done", flush=True)
"""


def start_writer(target: Path) -> tuple[subprocess.Popen, Path]:
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(target)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, cwd=ROOT)
    word, tmp = proc.stdout.readline().split()
    assert word == "writing" and Path(tmp) == temporary_name(target, proc.pid)
    return proc, Path(tmp)


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    assert not pid_running(proc.pid)
    return proc.pid


def test_a_killed_writer_s_temporary_goes_at_the_next_command_into_the_folder(tmp_path):
    src = VoxSplat(ijk=np.zeros((1, 3)), params=np.zeros((1, 1, 14)), voxel_size=0.1).save(tmp_path / "s.npz")
    out = tmp_path / "out" / "copy.npz"
    proc, tmp = start_writer(out)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    proc.stdin.close()
    proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    assert tmp.name.startswith(".copy.npz.tmp-") and tmp.read_bytes() == b"half of it"  # what the kill left

    res = CliRunner().invoke(app, ["export", str(src), "--to", "npz", "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.parent.iterdir()) == ["copy.npz"]  # the stale temporary is gone
    assert len(VoxSplat.load(out).ijk) == 1


def test_a_running_writer_s_temporary_is_kept_and_it_finishes(tmp_path):
    target = tmp_path / "t.txt"
    proc, tmp = start_writer(target)
    try:
        with atomic_path(target) as mine:  # another writer of the same target meanwhile
            Path(mine).write_text("ours")
        assert target.read_text() == "ours" and tmp.read_bytes() == b"half of it"  # its temporary untouched
        proc.stdin.write("go\n")
        proc.stdin.flush()
        assert proc.stdout.readline().strip() == "done"
    finally:
        proc.kill()
        proc.wait(timeout=30)
        proc.stdin.close()
        proc.stdout.close()
    assert target.read_bytes() == b"the writer's own" and sorted(p.name for p in tmp_path.iterdir()) == ["t.txt"]


@pytest.mark.parametrize("target", ["frame.npz", "metadata.yaml", "run.json", "a.b.tmp-3"])
def test_only_dead_writers_temporaries_of_the_same_target_are_removed(tmp_path, target):
    path = tmp_path / target
    dead = dead_pid()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    zombie = subprocess.Popen([sys.executable, "-c", "pass"])  # ended, not yet reaped by us
    try:
        zombie_pid = zombie.pid
        while True:  # wait until it has ended (without reaping it)
            stat = Path(f"/proc/{zombie_pid}/stat")
            if not stat.exists() or stat.read_text().rsplit(")", 1)[1].split()[0] == "Z":
                break
            time.sleep(0.01)
        stale = [temporary_name(path, dead), temporary_name(path, zombie_pid)]
        kept = [temporary_name(path, live.pid), temporary_name(path, os.getppid()),  # running writers
                tmp_path / f".{target}.tmp-x{dead}", tmp_path / f".{target}.tmp-",  # not a pid: not ours
                temporary_name(tmp_path / "other.npz", dead),  # another target's
                tmp_path / f"{target}.tmp-{dead}"]  # not hidden: not ours
        for p in stale + kept:
            p.write_bytes(b"x")
        folder = temporary_name(tmp_path / "dir", dead)
        folder.mkdir()  # a folder of that name: not a file atomic_path writes
        kept.append(folder)
        before = set(tmp_path.iterdir())
        with atomic_path(tmp_path / "dir") as tmp:
            Path(tmp).write_text("d")
        assert set(tmp_path.iterdir()) == before | {tmp_path / "dir"}  # dir's own: a folder, kept
        with atomic_path(path) as tmp:
            Path(tmp).write_text("new")
        assert path.read_text() == "new"
        assert not any(p.exists() for p in stale)
        assert all(p.exists() for p in kept)
        assert set(tmp_path.iterdir()) == set(kept) | {path, tmp_path / "dir"}
        assert remove_stale_temporaries(path) == []
    finally:
        live.kill()
        live.wait()
        zombie.wait()
