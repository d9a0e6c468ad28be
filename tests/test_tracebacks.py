"""Issue 46, "tracebacks still reach the user" and "evaluation needs a checkpoint it already ships":
every input below used to end in a traceback, a DataLoader traceback joined with ';', a complaint
about another option, or torch's advice to load with weights_only=False. Each is now one line,
exit code 2, naming the file (and array, sample or stage) at fault, and writes nothing; `eval
geometry` and `eval appearance` run on the shipped paper-route profile's checkpoints."""

from __future__ import annotations

import json
import os
import pickle
import shutil

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from scube_sim.cli import app
from scube_sim.datasets.base import DatasetError
from scube_sim.errors import NotFoundError, OutOfRangeError
from scube_sim.model.checkpoint import FORMAT, VERSION, save_checkpoint
from scube_sim.voxsplat import VoxSplat
from tests.conftest import one_line_error as one_line

runner = CliRunner()

ALWAYS_STAGES = {"appearance", "completion", "geometry", "geometry-vae", "voxel-semantics"}


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


class _Exploit:
    """Pickles to a call of os.system: nothing may unpickle it."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.fixture(scope="module")
def worlds(tmp_path_factory):
    """A one-sample worlds dataset (test split) at the tiny converter's scale."""
    from scube_sim.worlds.dataset import generate_dataset
    from tests.converter.tiny_converter import TINY

    root = tmp_path_factory.mktemp("tb") / "w"
    generate_dataset(root, "test", 1, TINY, progress=False)
    return root


# --- a VoxSplat .npz holding object arrays, or damaged -------------------------------------------

def _scene_arrays(tmp_path) -> dict:
    vs = VoxSplat(ijk=np.zeros((1, 3)), params=np.zeros((1, 1, 14)), voxel_size=0.1)
    vs.set_channel("confidence", np.ones(1, np.float32))  # a version-2 file with a channel
    path = vs.save(tmp_path / "good.npz")
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


SCENE_COMMANDS = {  # how each command that reads a scene is given one, and its output
    "lidar": lambda s, o: ["lidar", s, "--sensor", "vlp16", "-o", o / "x.pcd"],
    "export": lambda s, o: ["export", s, "--to", "ply", "-o", o / "x.ply"],
    "render": lambda s, o: ["render", s, "--rig", "waymo-5", "-o", o / "x.png"],
}


@pytest.mark.parametrize("command", list(SCENE_COMMANDS))
@pytest.mark.parametrize("key", ["params", "ijk", "metadata", "voxel_size", "channel.confidence"])
def test_an_object_array_in_a_voxsplat_is_refused_unopened(tmp_path, command, key):
    marker = tmp_path / "ran"
    arrays = _scene_arrays(tmp_path)
    arrays[key] = np.array([_Exploit(marker), None], dtype=object)
    bad = tmp_path / "obj.npz"
    np.savez(bad, **arrays)
    out = tmp_path / "out"
    out.mkdir()
    line = one_line(invoke(*SCENE_COMMANDS[command](bad, out)))
    assert line == (f"error: {bad}: key {key!r} is an array of Python objects (dtype object), which a VoxSplat "
                    f"never holds; refused without unpickling it")
    assert not marker.exists() and list(out.iterdir()) == []


@pytest.mark.parametrize("damage", ["empty", "truncated", "corrupt member"])
@pytest.mark.parametrize("command", list(SCENE_COMMANDS))
def test_a_damaged_voxsplat_is_one_line(tmp_path, command, damage):
    good = VoxSplat(ijk=np.zeros((2, 3)), params=np.zeros((2, 1, 14)), voxel_size=0.1).save(tmp_path / "g.npz")
    b = good.read_bytes()
    data = {"empty": b"", "truncated": b[: len(b) // 2],
            "corrupt member": b[:200] + bytes(x ^ 0xFF for x in b[200:260]) + b[260:]}[damage]
    bad = tmp_path / "bad.npz"
    bad.write_bytes(data)
    out = tmp_path / "out"
    out.mkdir()
    line = one_line(invoke(*SCENE_COMMANDS[command](bad, out)))
    assert line.startswith(f"error: {bad}: ") and ("not a readable .npz" in line or "truncated or corrupt" in line)
    assert list(out.iterdir()) == []


# --- errors raised in a DataLoader worker ----------------------------------------------------------

class _Failing(torch.utils.data.Dataset):
    def __init__(self, exc):
        self.exc = exc

    def __len__(self):
        return 2

    def __getitem__(self, i):
        raise self.exc


@pytest.mark.parametrize("exc", [DatasetError("/d/000000/voxels.npz: missing ground-truth voxels"),
                                 NotFoundError("camera 'X': not in the rig (FRONT, SIDE)"),
                                 OutOfRangeError("sample 5: past the end of split test (2 samples)")])
def test_an_error_of_ours_from_a_worker_keeps_its_own_one_line_message(exc):
    """torch re-raises a worker's error as type(exc)("Caught ... Original Traceback ...")."""
    batches = iter(torch.utils.data.DataLoader(_Failing(exc), num_workers=1))
    try:
        with pytest.raises(type(exc)) as err:
            next(batches)
        got = str(err.value)
    finally:
        batches._shutdown_workers()  # the worker would otherwise outlive the test (held by the traceback)
    assert got == str(exc)


@pytest.mark.parametrize(("stage", "missing", "what"), [
    ("geometry", "voxels.npz", "missing ground-truth voxels"),
    ("appearance", "rgb_00_FRONT.png", "missing image of camera 'FRONT'"),
])
def test_eval_on_a_sample_missing_a_file_names_sample_and_file(worlds, tmp_path, stage, missing, what):
    """The stage's DataLoader reads the sample in a worker process (the checkpoints' num_workers)."""
    data = tmp_path / "w"
    shutil.copytree(worlds, data)
    (data / "test" / "000000" / missing).unlink()
    out = tmp_path / "m.json"
    line = one_line(invoke("eval", "stage", stage, "--data", data, "--no-progress", "-o", out))
    assert line.startswith(f"error: {data / 'test' / '000000' / missing}: {what}"), line
    assert ";" not in line and not out.exists()


def _damage(path, kind):
    b = path.read_bytes()
    if kind == "object array":
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
        arrays[next(iter(arrays))] = np.array([None, 1], dtype=object)
        np.savez(path, **arrays)
        return
    path.write_bytes({"empty": b"", "truncated": b[: len(b) // 2],
                      "corrupt member": b[:300] + bytes(x ^ 0xFF for x in b[300:400]) + b[400:]}[kind])


@pytest.mark.parametrize("kind", ["empty", "truncated", "corrupt member", "object array"])
@pytest.mark.parametrize("name", ["voxels.npz", "frames.npz", "lidar.npz"])
def test_a_damaged_array_file_of_a_worlds_sample_is_one_line(worlds, tmp_path, name, kind):
    from scube_sim.datasets import open_dataset

    data = tmp_path / "w"
    shutil.copytree(worlds, data)
    bad = data / "test" / "000000" / name
    _damage(bad, kind)
    with pytest.raises(DatasetError) as err:
        open_dataset("worlds", data, split="test")[0]
    assert str(err.value).startswith(f"{bad}: not a readable .npz (") and "\n" not in str(err.value)


def test_eval_on_a_truncated_voxels_file_is_one_line(worlds, tmp_path):
    data = tmp_path / "w"
    shutil.copytree(worlds, data)
    bad = data / "test" / "000000" / "voxels.npz"
    _damage(bad, "truncated")
    line = one_line(invoke("eval", "stage", "geometry", "--data", data, "--no-progress", "-o", tmp_path / "m.json"))
    assert line == f"error: {bad}: not a readable .npz (File is not a zip file)"
    assert not (tmp_path / "m.json").exists()


# --- eval's stage name, checked before any option --------------------------------------------------

@pytest.mark.parametrize("more", [[], ["--data", "{w}"], ["--split", "dev"], ["--checkpoint", "nope.pt"],
                                  ["--data-option", "no-equals-sign"]],
                         ids=["alone", "data", "bad-split", "missing-checkpoint", "bad-data-option"])
def test_an_unknown_eval_stage_is_named_with_the_stages_before_any_option(worlds, tmp_path, more):
    out = tmp_path / "m.json"
    line = one_line(invoke("eval", "stage", "bogus-stage", *[m.format(w=worlds) for m in more], "-o", out))
    head = "error: unknown stage 'bogus-stage'; eval stage takes "
    assert line.startswith(head), line
    assert set(line[len(head):].split(", ")) >= ALWAYS_STAGES
    assert not out.exists()


# --- checkpoints that cannot be loaded -------------------------------------------------------------

def _bad_checkpoint(kind: str, path, marker):
    if kind == "code":
        torch.save({"format": FORMAT, "version": VERSION, "stage": "geometry", "x": _Exploit(marker)}, path)
    elif kind == "numpy":
        torch.save({"format": FORMAT, "version": VERSION, "stage": "geometry", "x": np.zeros(3)}, path)
    elif kind == "bare pickle":
        path.write_bytes(pickle.dumps({"format": FORMAT, "version": VERSION, "x": _Exploit(marker)}))
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncated":
        good = save_checkpoint(path.with_suffix(".good"), {"stage": "geometry", "w": torch.arange(1000.0)})
        path.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    elif kind == "an npz":
        np.savez(path.with_suffix(".npz"), a=np.zeros(3))
        path.with_suffix(".npz").rename(path)
    return path


BAD_KINDS = {  # kind -> what the line says after "not a loadable checkpoint ("
    "code": "it holds a pickled Python object (",
    "numpy": "it holds a pickled Python object (numpy",
    "bare pickle": "not the zip archive torch.save writes",
    "empty": "an empty file",
    "truncated": "not the zip archive torch.save writes",
    "an npz": "a damaged torch archive",
}

CHECKPOINT_PLACES = {
    "eval geometry": lambda w, ck, run: ["eval", "stage", "geometry", "--data", w, "--checkpoint", ck, "-o", run / "m.json"],
    "eval appearance": lambda w, ck, run: ["eval", "stage", "appearance", "--data", w, "--checkpoint", ck, "-o", run / "m.json"],
    "eval depth": lambda w, ck, run: ["eval", "depth", "--data", w, "--dataset", "worlds", "--checkpoint", ck,
                                      "--no-progress", "-o", run / "m.json"],
    "train --resume": lambda w, ck, run: ["train", "geometry", "--data", w, "-o", run, "--resume", "--no-progress"],
}


@pytest.mark.parametrize("place", list(CHECKPOINT_PLACES))
@pytest.mark.parametrize("kind", list(BAD_KINDS))
def test_a_checkpoint_that_cannot_be_loaded_is_one_line_without_torchs_advice(worlds, tmp_path, place, kind):
    marker = tmp_path / "ran"
    run = tmp_path / "run"
    run.mkdir()
    ck = _bad_checkpoint(kind, run / "last.pt", marker)
    before = sorted(p.name for p in run.iterdir())
    line = one_line(invoke(*CHECKPOINT_PLACES[place](worlds, ck, run)))
    assert line.startswith(f"error: {ck}: not a loadable checkpoint ({BAD_KINDS[kind]}"), line
    low = line.lower()
    assert "weights_only" not in low and "weights only" not in low and "trust" not in low
    assert not marker.exists() and sorted(p.name for p in run.iterdir()) == before


def test_a_checkpoint_of_another_stage_or_of_none_is_named(worlds, tmp_path):
    line = one_line(invoke("eval", "stage", "geometry", "--data", worlds, "--checkpoint", "appearance-cpu"))
    assert line.endswith("appearance-cpu/model.pt: a checkpoint of stage 'appearance', not 'geometry'")
    nostage = save_checkpoint(tmp_path / "w.pt", {"model": {"w": torch.zeros(2)}})
    line = one_line(invoke("eval", "stage", "appearance", "--data", worlds, "--checkpoint", nostage))
    assert line == f"error: {nostage}: records no stage; expected a checkpoint of stage 'appearance'"


# --- eval without --checkpoint ---------------------------------------------------------------------

@pytest.mark.parametrize(("stage", "shipped", "primary"), [("geometry", "geometry-coarse-cpu", "iou"),
                                                           ("appearance", "appearance-cpu", "psnr")])
def test_eval_defaults_to_the_paper_route_profiles_checkpoint(worlds, tmp_path, stage, shipped, primary):
    """The paper-route profile (cpu) names geometry-coarse-cpu and appearance-cpu (its YAML)."""
    from scube_sim.converter.profile import PAPER_PROFILE, PROFILE_DIR

    assert f"checkpoint: {shipped}" in (PROFILE_DIR / f"{PAPER_PROFILE}.yaml").read_text()
    out = tmp_path / "m.json"
    res = invoke("eval", "stage", stage, "--data", worlds, "--no-progress", "-o", out)
    assert res.exit_code == 0, res.output
    report = json.loads(out.read_text())
    assert report["checkpoint"] == shipped and report["stage"] == stage and primary in report["metrics"]
    assert f"checkpoint: {shipped} (the shipped {PAPER_PROFILE} profile's {stage} checkpoint)" in res.output


@pytest.mark.parametrize(("stage", "listed"), [("geometry-vae", "geometry-vae-coarse-cpu, geometry-vae-fine-cpu"),
                                               ("voxel-semantics", "none ships")])
def test_a_stage_no_profile_names_a_checkpoint_for_still_needs_one(worlds, tmp_path, stage, listed):
    out = tmp_path / "m.json"
    line = one_line(invoke("eval", "stage", stage, "--data", worlds, "-o", out))
    assert line == (f"error: --checkpoint: required to evaluate the {stage} stage (the shipped profiles name no "
                    f"{stage} checkpoint); a run's last.pt or best.pt, or a shipped one: {listed}")
    assert not out.exists()


def test_a_checkpoint_given_where_the_evaluation_uses_none_is_refused(worlds, tmp_path):
    out = tmp_path / "m.json"
    line = one_line(invoke("eval", "depth", "--dataset", "worlds", "--method", "stereo", "--data", worlds,
                           "--checkpoint", "geometry-coarse-cpu", "-o", out))
    assert line.startswith("error: --checkpoint: --method stereo uses no checkpoint") and not out.exists()
    # sensor-to-sensor takes the checkpoints its --profile names: it has no such option
    res = invoke("eval", "sensor-to-sensor", "--data", worlds, "--checkpoint", "geometry-coarse-cpu", "-o", out)
    assert res.exit_code == 2 and "No such option: --checkpoint" in res.output and not out.exists()


def test_eval_without_data_names_the_option_after_the_stage(tmp_path):
    assert one_line(invoke("eval", "stage", "geometry")) == "error: --data: required (the dataset folder)"
