"""Output folders of `replay`: refused when not empty unless --overwrite or --resume, a run
manifest that proves which run a folder holds, the USD stage kept when another sink fails, and
a chunk cache whose corrupt entries are rebuilt."""

from __future__ import annotations

import errno
import hashlib
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from scube_sim.cli import app
from scube_sim.errors import InputError, ScubeSimWarning
from scube_sim.run_manifest import (
    MANIFEST_NAME,
    OutputFolderError,
    RunManifest,
    finish_run,
    prepare_output,
    read_manifest,
)
from scube_sim.runs.scenario import build as scenario_mod
from scube_sim.runs.scenario import schema as scenario_schema
from scube_sim.sim.sinks import FileSink
from scube_sim.worlds.generator import WorldConfig

runner = CliRunner()

TINY = """
name: tiny
seed: 4
duration_s: 0.4
scene:
  world: {style: suburban, seed: 3, layout: straight, length_m: 60}
  representation: mesh
trajectory: {source: world}
sensors:
  - {preset: vlp16}
outputs: {files: [pcd, bin], usd: run.usda}
"""


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def tree(folder: Path, skip=("scene_chunks",)) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.relative_to(folder).parts[0] not in skip}


def replay(*args):
    return runner.invoke(app, ["replay", *map(str, args)])


@pytest.fixture
def scen(tmp_path) -> Path:
    p = tmp_path / "tiny.yaml"
    p.write_text(TINY)
    return p


def manifest(tmp_path, text="a") -> RunManifest:
    inp = tmp_path / "in.txt"
    inp.write_text(text)
    return RunManifest.for_inputs("replay", {"scenario": inp}, {"seed": 0})


# ------------------------------------------------------------------ the decision, unit by unit
def test_a_new_or_empty_folder_starts_a_run(tmp_path):
    m = manifest(tmp_path)
    assert prepare_output(tmp_path / "new", m) == "new"
    got = read_manifest(tmp_path / "new")
    assert got.status == "running" and got.inputs == {"scenario": hashlib.sha256(b"a").hexdigest()}
    (tmp_path / "cached" / "scene_chunks").mkdir(parents=True)  # a cache alone does not make it "not empty"
    assert prepare_output(tmp_path / "cached", m, keep=("scene_chunks",)) == "new"


def test_a_folder_with_files_is_refused_naming_it_and_the_flags(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputFolderError, match=r"out: the output folder is not empty \(1 entries, no run "
                                                r"manifest\); pass --overwrite .* or --resume"):
        prepare_output(out, manifest(tmp_path))
    # --overwrite never clears a folder that is not a run of ours
    with pytest.raises(OutputFolderError, match="no run manifest .* not ours to clear"):
        prepare_output(out, manifest(tmp_path), overwrite=True)
    with pytest.raises(OutputFolderError, match="--resume: the folder holds no run manifest"):
        prepare_output(out, manifest(tmp_path), resume=True)
    assert (out / "notes.txt").read_text() == "mine"
    with pytest.raises(OutputFolderError, match="give one"):
        prepare_output(out, manifest(tmp_path), overwrite=True, resume=True)
    with pytest.raises(OutputFolderError, match="is a file"):
        prepare_output(out / "notes.txt", manifest(tmp_path))


def test_overwrite_clears_a_run_but_keeps_the_cache(tmp_path):
    out = tmp_path / "out"
    m = manifest(tmp_path)
    prepare_output(out, m, keep=("scene_chunks",))
    (out / "frames").mkdir()
    (out / "frames" / "x.pcd").write_text("old")
    (out / "scene_chunks").mkdir()
    (out / "scene_chunks" / "chunk_000.npz").write_text("cache")
    finish_run(out, m, "complete", keep=("scene_chunks",))
    with pytest.raises(OutputFolderError, match=r"not empty \(a replay run, status complete\)"):
        prepare_output(out, m, keep=("scene_chunks",))
    assert prepare_output(out, manifest(tmp_path, "other"), overwrite=True, keep=("scene_chunks",)) == "new"
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST_NAME, "scene_chunks"]
    assert (out / "scene_chunks" / "chunk_000.npz").read_text() == "cache"


def test_resume_needs_the_same_run_and_redoes_an_incomplete_or_changed_one(tmp_path):
    out = tmp_path / "out"
    m = manifest(tmp_path)
    prepare_output(out, m)
    (out / "a.bin").write_bytes(b"1234")
    finish_run(out, m, "complete")
    rec = read_manifest(out)
    assert rec.outputs == {"a.bin": {"sha256": hashlib.sha256(b"1234").hexdigest(), "bytes": 4}}
    again = manifest(tmp_path)
    assert prepare_output(out, again, resume=True) == "complete"  # nothing touched
    assert again.outputs == rec.outputs and again.status == "complete"
    assert (out / "a.bin").read_bytes() == b"1234"
    # another input: not the same run, named
    with pytest.raises(OutputFolderError, match=r"not the same run \(input scenario \(changed\)\)"):
        prepare_output(out, manifest(tmp_path, "b"), resume=True)
    other = RunManifest.for_inputs("replay", {"scenario": tmp_path / "in.txt"}, {"seed": 1})
    with pytest.raises(OutputFolderError, match=r"setting seed"):
        prepare_output(out, other, resume=True)
    # an output changed since: the run is redone (cleared, manifest running again)
    (out / "a.bin").write_bytes(b"12x4")
    m2 = manifest(tmp_path, "a")  # the input as the run had it
    assert prepare_output(out, m2, resume=True) == "redo"
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST_NAME] and read_manifest(out).status == "running"
    # a failed run is redone too
    finish_run(out, m2, "failed", "boom")
    assert read_manifest(out).error == "boom"
    assert prepare_output(out, m2, resume=True) == "redo"


def test_a_broken_manifest_is_an_error_naming_it(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / MANIFEST_NAME).write_text("{not json")
    with pytest.raises(InputError, match=r"manifest\.json: not valid JSON"):
        prepare_output(out, manifest(tmp_path), resume=True)
    (out / MANIFEST_NAME).write_text(json.dumps({"format": "scube-sim-run", "version": 99}))
    with pytest.raises(InputError, match=r"manifest\.json: run manifest version 99"):
        prepare_output(out, manifest(tmp_path), resume=True)
    (out / MANIFEST_NAME).write_text(json.dumps({"format": "scube-sim-run", "version": 1, "command": "replay",
                                                 "inputs": {}, "settings": {}, "outputs": {}, "status": "done"}))
    with pytest.raises(InputError, match=r"manifest\.json: key 'status': expected one of running"):
        prepare_output(out, manifest(tmp_path), resume=True)
    with pytest.raises(InputError, match=r"scenario: .*nope\.yaml: no such input file"):
        RunManifest.for_inputs("replay", {"scenario": tmp_path / "nope.yaml"}, {})


# ------------------------------------------------------------------ the replay command
def test_rerun_into_a_folder_is_refused_and_resume_or_overwrite_give_the_same_bytes(tmp_path, scen):
    out = tmp_path / "r"
    res = replay(scen, "-o", out)
    assert res.exit_code == 0, res.output
    first = tree(out)
    rec = read_manifest(out)
    assert rec.status == "complete" and rec.error is None
    assert rec.inputs == {"scenario": sha(scen)}
    assert rec.settings["scenario"]["seed"] == 4 and rec.settings["sensors"][0]["name"]
    listed = {k: v["sha256"] for k, v in rec.outputs.items()}
    assert listed == {k: hashlib.sha256(v).hexdigest() for k, v in first.items() if k != MANIFEST_NAME}
    assert "run.usda" in listed and "frames/frames.jsonl" in listed
    n_lines = len((out / "frames" / "frames.jsonl").read_text().splitlines())

    res = replay(scen, "-o", out)  # before: appended to frames.jsonl, stale and duplicated ticks
    assert res.exit_code == 2
    assert res.output.strip().splitlines() == [
        f"error: {out}: the output folder is not empty (a replay run, status complete); "
        "pass --overwrite to clear it or --resume to continue the same run"]
    assert tree(out) == first

    res = replay(scen, "-o", out, "--resume")
    assert res.exit_code == 0 and f"already holds this run, complete ({len(listed)} output files" in res.output
    assert tree(out) == first

    res = replay(scen, "-o", out, "--overwrite")
    assert res.exit_code == 0, res.output
    assert tree(out) == first  # byte for byte: manifest included (it holds no timings)
    assert len((out / "frames" / "frames.jsonl").read_text().splitlines()) == n_lines

    res = replay(scen, "-o", out, "--resume", "--seed", "5")
    assert res.exit_code == 2 and "not the same run (setting scenario.seed)" in res.output


def test_a_failing_sink_keeps_the_usd_stage_and_resume_finishes_the_run(tmp_path, scen, monkeypatch):
    """The file sink hits a full disk at tick 3: the USD stage holds the ticks before it, the
    manifest says failed and why, and --resume then gives the bytes of an uninterrupted run."""
    from pxr import Usd

    clean = tmp_path / "clean"
    assert replay(scen, "-o", clean).exit_code == 0

    real_write = FileSink.write

    def full_at_3(self, frame):
        if frame.index == 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.folder / "vlp16" / "000003_0.pcd"))
        real_write(self, frame)

    monkeypatch.setattr(FileSink, "write", full_at_3)
    out = tmp_path / "r"
    res = replay(scen, "-o", out)
    assert res.exit_code == 2
    lines = res.output.strip().splitlines()
    assert lines[-1].startswith("error: sink FileSink failed: [Errno 28] No space left on device: ")
    assert "000003_0.pcd" in lines[-1] and not any("Traceback" in ln for ln in lines)
    rec = read_manifest(out)
    assert rec.status == "failed" and "No space left on device" in rec.error
    assert set(rec.outputs) == set(tree(out)) - {MANIFEST_NAME}  # every file there, checksummed
    stage = Usd.Stage.Open(str(out / "run.usda"))
    pts = stage.GetPrimAtPath("/World/Sensors/vlp16/Points").GetAttribute("points")
    ticks = [json.loads(x)["tick"] for x in (out / "frames" / "frames.jsonl").read_text().splitlines()]
    assert ticks == [1, 2]  # vlp16 at 10 Hz: its sweeps end at ticks 1, 2, (3 failed)
    assert len(pts.GetTimeSamples()) == 2  # the stage of the completed ticks, not lost

    monkeypatch.setattr(FileSink, "write", real_write)
    res = replay(scen, "-o", out, "--resume")
    assert res.exit_code == 0 and "earlier attempt was incomplete" in res.output
    assert tree(out) == tree(clean)


def test_when_every_sink_fails_the_message_says_so(tmp_path, scen, monkeypatch):
    from scube_sim.sim.sinks import UsdSink

    def no_space(self, frame):
        raise OSError(errno.ENOSPC, "No space left on device", "x.pcd")

    def close_full(self):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.path))

    monkeypatch.setattr(FileSink, "write", no_space)
    monkeypatch.setattr(UsdSink, "close", close_full)
    res = replay(scen, "-o", tmp_path / "r")
    assert res.exit_code == 2
    last = res.output.strip().splitlines()[-1]
    assert "sink FileSink failed" in last and "closing UsdSink failed too" in last and "run.usda" in last


# ------------------------------------------------------------------ the chunk cache
def test_a_corrupt_chunk_cache_entry_is_rebuilt_not_fatal(tmp_path):
    from scube_sim.voxsplat import VoxSplat
    from scube_sim.worlds.generator import generate_world

    world = generate_world(WorldConfig(style="suburban", seed=3, layout="straight", length_m=40, duration_s=2))
    spec = scenario_schema.SceneSpec(world=world.config, voxel_size=1.0, gaussians_per_voxel=1)
    specs = scenario_mod._world_chunks(world, spec, tmp_path / "scene_chunks")
    first = specs[0].path
    meta = json.loads(first.with_suffix(".json").read_text())
    assert meta["sha256"] == sha(first)
    good = first.read_bytes()
    assert not [p for p in (tmp_path / "scene_chunks").iterdir() if "tmp" in p.name]
    # reused as it is: no refit
    mtime = first.stat().st_mtime_ns
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scenario_mod._world_chunks(world, spec, tmp_path / "scene_chunks")
    assert first.stat().st_mtime_ns == mtime
    # truncated npz: rebuilt with a warning naming it, and equal to the first fit
    first.write_bytes(good[: len(good) // 2])
    with pytest.warns(ScubeSimWarning, match=r"chunk_000\.npz: chunk cache entry corrupt"):
        scenario_mod._world_chunks(world, spec, tmp_path / "scene_chunks")
    assert first.read_bytes() == good
    assert VoxSplat.load(first).num_gaussians > 0
    # unreadable metadata: rebuilt too
    first.with_suffix(".json").write_bytes(b"\xff\xfe{")
    with pytest.warns(ScubeSimWarning, match=r"chunk_000\.json: chunk cache entry unreadable"):
        scenario_mod._world_chunks(world, spec, tmp_path / "scene_chunks")
    assert first.read_bytes() == good
    # other settings: refit silently (nothing was wrong)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        other = scenario_schema.SceneSpec(world=world.config, voxel_size=2.0, gaussians_per_voxel=1)
        scenario_mod._world_chunks(world, other, tmp_path / "scene_chunks")
    assert np.isclose(VoxSplat.load(first).voxel_size, 2.0)


def test_ctrl_c_leaves_whole_files_a_stage_and_an_interrupted_manifest(tmp_path):
    """A real process, a real SIGINT: exit 130 with one line, the manifest says interrupted,
    frames.jsonl lists only sweeps whose files are all there, the USD stage is written."""
    import os
    import signal
    import subprocess
    import sys
    import time

    scen = tmp_path / "long.yaml"
    scen.write_text(TINY.replace("duration_s: 0.4", "duration_s: 60"))
    out = tmp_path / "r"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.Popen([sys.executable, "-m", "scube_sim.cli", "replay", str(scen), "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    frames = out / "frames" / "frames.jsonl"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not (frames.exists() and len(frames.read_text().splitlines()) >= 3):
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "interrupted: the outputs written so far are complete files"
    rec = read_manifest(out)
    assert rec.status == "interrupted" and rec.error == "KeyboardInterrupt"
    listed = [json.loads(x) for x in frames.read_text().splitlines()]
    assert len(listed) >= 3
    for line in listed:
        for f in line["files"]:
            assert (out / "frames" / f).is_file()
    assert (out / "run.usda").is_file() and "run.usda" in rec.outputs
    assert not [p for p in out.rglob("*") if ".tmp-" in p.name]
