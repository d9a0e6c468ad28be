"""`scube-sim batch`: tasks skipped when complete, retried when they fail or their worker dies,
a driver interrupted and rerun, the same bytes as the single commands and on every executor.

The tasks are tiny scenario replays (a world at 1 m voxels, a VLP-16, a few ticks: seconds each). The
expectations are independent of the batch code: a task folder equals what `scube-sim replay`
writes for the same scenario, seed and edit (an edit written into the scenario file itself)."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from scube_sim.cli import app
from scube_sim.parallel.runner import BatchError, expand_inputs, run_batch
from scube_sim.run_manifest import is_complete, read_manifest
from scube_sim.runs.batch_jobs import make_job
from scube_sim.runs.replay import replay_manifest
from tests.conftest import one_line_error

runner = CliRunner()

TINY = {"name": "tiny", "seed": 4, "duration_s": 0.3,
        "scene": {"world": {"style": "suburban", "seed": 3, "layout": "straight", "length_m": 60},
                  "representation": "voxsplat", "voxel_size": 1.0, "gaussians_per_voxel": 1},
        "trajectory": {"source": "world"}, "sensors": [{"preset": "vlp16"}], "outputs": {"files": ["npz"]}}
LEFT = {"lateral_offset_m": 2.0}


def tree(folder: Path) -> dict[str, str]:
    """Relative path -> SHA-256 of every file (digests: a failing `==` on raw bytes makes pytest
    diff megabytes)."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and "scene_chunks" not in p.parts}


def frames(folder: Path) -> dict[str, str]:
    return {k: v for k, v in tree(folder).items() if k.startswith("frames/")}


def scenario(tmp_path: Path, name: str = "tiny", **over) -> Path:
    p = tmp_path / f"{name}.yaml"
    p.write_text(yaml.safe_dump({**TINY, **over}))
    return p


def cli(*args):
    return runner.invoke(app, [str(a) for a in args])


def test_inputs_expand_from_lists_globs_and_list_files(tmp_path):
    for n in ("b", "a", "c"):
        (tmp_path / f"{n}.yaml").write_text("")
    listing = tmp_path / "runs.txt"
    listing.write_text(f"# campaign\n{tmp_path / 'c.yaml'}\n\n{tmp_path / 'a.yaml'}  # again\n")
    got = expand_inputs([f"{tmp_path}/*.yaml", f"@{listing}", "x,y , x"])
    assert got == [str(tmp_path / f"{n}.yaml") for n in "abc"] + ["x", "y"]
    with pytest.raises(BatchError, match=r"matches nothing"):
        expand_inputs([f"{tmp_path}/*.pcd"])
    with pytest.raises(BatchError, match=r"no such list file"):
        expand_inputs([f"@{tmp_path}/none.txt"])


def test_bad_batches_are_refused_before_any_task_runs(tmp_path):
    one_line_error(cli("batch", "mosaic", "-i", "x", "-o", tmp_path / "o"), "unknown job 'mosaic'", "replay")
    one_line_error(cli("batch", "worlds", "-i", "train:5-2", "-o", tmp_path / "o"), "train:5-2", "FIRST <= LAST")
    one_line_error(cli("batch", "replay", "-i", tmp_path / "none.yaml", "-o", tmp_path / "o"), "none.yaml",
                   "no such scenario")
    scen = scenario(tmp_path)
    one_line_error(cli("batch", "replay", "-i", scen, "-o", tmp_path / "o", "--set", "seeds=[1, -2]"), "seeds", "-2")
    one_line_error(cli("batch", "replay", "-i", scen, "-o", tmp_path / "o", "--set", "edits={a: {speed: 2}}"),
                   "edits.a.speed")
    one_line_error(cli("batch", "replay", "-i", scen, "-o", tmp_path / "o", "--executor", "slurm"), "--executor",
                   "slurm")
    other = tmp_path / "b" / "tiny.yaml"
    other.parent.mkdir()
    other.write_text(scen.read_text())
    one_line_error(cli("batch", "replay", "-i", f"{scen},{other}", "-o", tmp_path / "o"), "share the name 'tiny'")
    one_line_error(cli("batch", "build", "-i", tmp_path, "-o", tmp_path / "o", "--set", "dataset=nuscenes",
                       "--set", "options={voxel: 1}"), "options.voxel", "voxel_size")


def test_a_sweep_over_seeds_and_edits_equals_the_single_replays_and_resumes(tmp_path):
    scen = scenario(tmp_path)
    out = tmp_path / "out"
    settings = {"seeds": [1, 2], "edits": {"left": LEFT}}
    rep = run_batch(make_job("replay", settings), [str(scen)], out, executor="local", workers=2, progress=False)
    assert (rep.status, rep.total, rep.completed, rep.skipped, rep.attempts) == ("complete", 2, 2, 0, 2)
    # the independent expectation: `scube-sim replay` of a scenario file with the edit written in
    edited = scenario(tmp_path, "edited", trajectory={"source": "world", "edit": LEFT})
    for seed in (1, 2):
        res = cli("replay", edited, "-o", tmp_path / f"direct{seed}", "--seed", seed)
        assert res.exit_code == 0, res.output
        task = out / "tiny" / f"seed-{seed}" / "left"
        assert frames(task) == frames(tmp_path / f"direct{seed}") and frames(task)
        assert read_manifest(task).settings["scenario"]["seed"] == seed
    assert frames(out / "tiny/seed-1/left") != frames(out / "tiny/seed-2/left")  # the seed reached the noise
    # the runs shared one chunk cache outside their folders
    (cache,) = (out / ".cache").iterdir()
    assert cache.name.startswith("tiny-") and list(cache.glob("chunk_*.npz"))
    assert not (out / "tiny/seed-1/left/scene_chunks").exists()
    summary = json.loads((out / "batch.json").read_text())
    assert summary["status"] == "complete" and summary["counts"] == {"complete": 2}
    for key, rec in summary["tasks"].items():
        assert rec["attempts"] == 1 and rec["seconds"] > 0 and rec["peak_mb"] > 0
        assert rec["outputs"] == read_manifest(out / key).outputs
    assert not list((out / ".batch" / "running").iterdir())
    # rerun: nothing to do; a damaged output reruns that task alone, to the same bytes
    before = tree(out / "tiny/seed-2/left")
    rep = run_batch(make_job("replay", settings), [str(scen)], out, workers=2, progress=False)
    assert (rep.completed, rep.skipped) == (0, 2)
    victim = next(p for p in (out / "tiny/seed-2/left/frames").rglob("*.npz"))
    victim.write_bytes(b"damaged")
    res = cli("batch", "replay", "-i", scen, "-o", out, "--set", "seeds=[1, 2]", "--set", "edits={left: "
              "{lateral_offset_m: 2.0}}", "--no-progress")
    assert res.exit_code == 0, res.output
    assert "1 done, 1 already complete, 0 failed" in res.output
    assert tree(out / "tiny/seed-2/left") == before


def test_a_failing_task_is_retried_then_recorded_and_the_others_finish(tmp_path):
    good = scenario(tmp_path)
    # valid YAML, valid scenario, but a trajectory that ends before it starts: fails when run
    bad = scenario(tmp_path, "late", trajectory={"source": "world", "edit": {"time_shift_s": 1e4}})
    broken = tmp_path / "broken.yaml"
    broken.write_text(yaml.safe_dump({**TINY, "sead": 3}))
    out = tmp_path / "out"
    for _ in range(2):  # the second run: the broken file's folder exists, and it is still a task's failure
        res = cli("batch", "replay", "-i", f"{good},{bad},{broken}", "-o", out, "--retries", "2", "--no-progress")
        assert res.exit_code == 1, res.output
    assert "0 done, 1 already complete, 2 failed" in res.output and "late" in res.output
    assert "broken.yaml: sead: unknown key" in res.output
    summary = json.loads((out / "batch.json").read_text())
    assert summary["status"] == "failed"
    late = summary["tasks"]["late"]
    assert late["status"] == "failed" and late["attempts"] == 3 and "would simulate no time" in late["error"]
    assert summary["tasks"]["broken"]["status"] == "failed"
    assert read_manifest(out / "late").status == "failed"
    assert is_complete(out / "tiny", replay_manifest(good)[2])
    attempts = [json.loads(ln) for ln in (out / ".batch" / "attempts.jsonl").read_text().splitlines()]
    assert [a["attempt"] for a in attempts if a["key"] == "late"] == [1, 2, 3] * 2


def _wait_for(pred, timeout=120.0, what="condition"):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        got = pred()
        if got:
            return got
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def _running_marker(out: Path):
    folder = out / ".batch" / "running"
    for p in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        try:
            return json.loads(p.read_text())
        except (OSError, json.JSONDecodeError):
            return None
    return None


def _batch_process(out: Path, scen: Path, *extra) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "scube_sim.cli", "batch", "replay", "-i", str(scen), "-o", str(out),
           "--set", "seeds=[1, 2, 3]", "--set", "duration_s=1.5", "--no-progress", *extra]
    # SIGINT back to its default: a suite run in the background (CI) inherits it ignored
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


@pytest.mark.parametrize("executor", ["local", "ray"])
def test_a_killed_worker_is_retried_and_nothing_is_half_written(tmp_path, executor):
    """A worker killed mid-task is retried; the batch completes; on Ray, the bytes equal the local pool's."""
    if executor == "ray":
        pytest.importorskip("ray", reason="Ray is not installed (pip install 'scube-sim[ray]')")
    scen = scenario(tmp_path)
    out = tmp_path / "out"
    proc = _batch_process(out, scen, "--executor", executor, "--workers", "1")
    try:
        marker = _wait_for(lambda: _running_marker(out), what="a task to start")
        time.sleep(0.5)  # into the replay, past its set-up
        os.kill(marker["pid"], signal.SIGKILL)
        text, _ = proc.communicate(timeout=600)
    finally:
        proc.kill()
    assert proc.returncode == 0, text
    attempts = [json.loads(ln) for ln in (out / ".batch" / "attempts.jsonl").read_text().splitlines()]
    killed = [a for a in attempts if a["key"] == marker["key"]]
    assert [a["status"] for a in killed] == ["crashed", "complete"], killed
    summary = json.loads((out / "batch.json").read_text())
    assert summary["counts"] == {"complete": 3} and summary["tasks"][marker["key"]]["attempts"] == 2
    for seed in (1, 2, 3):
        task = out / "tiny" / f"seed-{seed}"
        assert is_complete(task, replay_manifest(scen, seed=seed, duration=1.5)[2])
        assert not [p for p in task.rglob("*") if ".tmp" in p.name]
    if executor == "ray":
        # Ray workers write the same bytes as the local pool (one Ray start serves both checks).
        job = {"seeds": [1, 2, 3], "duration_s": 1.5}
        local = run_batch(make_job("replay", job), [str(scen)], tmp_path / "local", workers=2, progress=False)
        assert local.completed == 3
        for seed in (1, 2, 3):
            a, b = tree(tmp_path / "local" / "tiny" / f"seed-{seed}"), tree(out / "tiny" / f"seed-{seed}")
            assert a == b and "manifest.json" in a


def test_an_interrupted_driver_reruns_only_what_is_missing(tmp_path):
    scen = scenario(tmp_path)
    out = tmp_path / "out"
    proc = _batch_process(out, scen, "--workers", "1")
    try:
        log = out / ".batch" / "attempts.jsonl"
        _wait_for(lambda: log.is_file() and log.read_text().strip(), what="the first task to finish")
        proc.send_signal(signal.SIGINT)
        text, _ = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 130, text
    summary = json.loads((out / "batch.json").read_text())
    assert summary["status"] == "interrupted", (text, summary)
    done = [k for k, r in summary["tasks"].items() if r["status"] == "complete"]
    assert 1 <= len(done) < 3 and "interrupted" in {r["status"] for r in summary["tasks"].values()}, summary
    rep = run_batch(make_job("replay", {"seeds": [1, 2, 3], "duration_s": 1.5}), [str(scen)], out, progress=False)
    # a task whose worker finished its folder just as the driver stopped is complete on disk: skipped too
    assert rep.skipped >= len(done) and rep.skipped + rep.completed == 3 and rep.status == "complete", rep.records
