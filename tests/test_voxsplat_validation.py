"""Every key of a VoxSplat .npz is checked on load: a file broken in one key (dtype, shape, range,
finiteness, version in both directions) is refused with an error that names the file and the
key, and the CLI turns it into one line with exit code 2. Each case starts from a valid file
written by `save` and rewrites one array with numpy, as a foreign writer would."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from scube_sim.cli import app
from scube_sim.errors import InputError
from scube_sim.labels import NUM_LABELS
from scube_sim.voxsplat import VoxSplat


def valid_arrays(tmp_path) -> dict:
    rng = np.random.default_rng(0)
    v, m = 6, 2
    vs = VoxSplat(ijk=np.arange(v * 3).reshape(v, 3), params=rng.normal(0, 1, (v, m, 14)).astype(np.float32),
                  voxel_size=0.2, origin=[1e6, 2e6, 3.0], labels=np.arange(v) % NUM_LABELS,
                  logits=rng.normal(0, 1, (v, 4)).astype(np.float32), metadata={"source": "test"})
    path = vs.save(tmp_path / "ok.npz")
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def rewrite(tmp_path, arrays: dict, **changes):
    a = dict(arrays)
    for k, val in changes.items():
        if val is None:
            a.pop(k)
        else:
            a[k] = val
    path = tmp_path / "bad.npz"
    with open(path, "wb") as fh:
        np.savez(fh, **a)
    return path


def test_the_valid_file_loads(tmp_path):
    a = valid_arrays(tmp_path)
    vs = VoxSplat.load(rewrite(tmp_path, a))
    assert vs.num_voxels == 6 and vs.metadata == {"source": "test"}


CASES = [
    # (key, replacement or callable(arrays) -> replacement, what the message says)
    ("version", np.array(0, np.int32), r"key 'version' is 0: VoxSplat format versions start at 1"),
    ("version", np.array(-3, np.int32), r"key 'version' is -3"),
    ("version", np.array(3, np.int32), r"format version 3 is newer than this scube_sim reads \(2\)"),
    ("version", np.array("2"), r"key 'version': expected an integer scalar"),
    ("version", np.array([1, 2], np.int32), r"key 'version': expected an integer scalar"),
    ("format", np.array("scube_sim.other"), r"key 'format' is 'scube_sim.other'"),
    ("ijk", lambda a: a["ijk"].astype(np.float32), r"key 'ijk': expected integer voxel indices, got dtype float32"),
    ("ijk", lambda a: a["ijk"][:, :2], r"key 'ijk': expected shape \(N, 3\), got \(6, 2\)"),
    ("ijk", lambda a: np.vstack([a["ijk"][:5], a["ijk"][:1]]), r"key 'ijk': 1 duplicate voxel"),
    ("ijk", lambda a: a["ijk"] + (1 << 20), r"key 'ijk': voxel indices beyond \+-2\^20"),
    ("params", lambda a: a["params"][:5], r"key 'params': expected shape \(6, N, 14\), got \(5, 2, 14\)"),
    ("params", lambda a: a["params"][..., :13], r"key 'params': expected shape \(6, N, 14\)"),
    ("params", lambda a: a["params"].astype(np.int32), r"key 'params': expected float raw values"),
    ("params", lambda a: a["params"][:, :0], r"key 'params': expected at least one Gaussian slot"),
    ("params", lambda a: _with(a["params"], (2, 1, 8), np.nan), r"raw quaternion contains NaN or Inf \(voxel 2, slot 1\)"),
    ("params", lambda a: _with(a["params"], (0, 0, 5), np.inf), r"raw scale contains NaN or Inf \(voxel 0, slot 0\)"),
    ("valid", lambda a: a["valid"].astype(np.uint8), r"key 'valid': expected a bool mask \(V, M\), got dtype uint8"),
    ("valid", lambda a: a["valid"][:, :1], r"key 'valid': expected shape \(6, 2\), got \(6, 1\)"),
    ("labels", lambda a: a["labels"][:4], r"key 'labels': expected shape \(6\), got \(4,\)"),
    ("labels", lambda a: np.full(6, NUM_LABELS + 5, np.int16), rf"key 'labels': ids must lie in \[0, {NUM_LABELS}\)"),
    ("labels", lambda a: np.full(6, -1, np.int16), r"key 'labels': ids must lie in"),
    ("logits", lambda a: a["logits"][:3], r"key 'logits': expected shape \(6, N\), got \(3, 4\)"),
    ("logits", lambda a: _with(a["logits"], (1, 1), np.nan), r"key 'logits' contains NaN or Inf"),
    ("voxel_size", np.array(0.0), r"key 'voxel_size': expected a positive finite number, got 0.0"),
    ("voxel_size", np.array(np.inf), r"key 'voxel_size': expected a positive finite number, got inf"),
    ("voxel_size", np.array([0.2, 0.2]), r"key 'voxel_size': expected shape \(\), got \(2,\)"),
    ("offset_range", np.array(-3.0), r"key 'offset_range': expected a positive finite number"),
    ("origin", np.array([0.0, np.nan, 0.0]), r"key 'origin' contains NaN or Inf"),
    ("origin", np.zeros((2, 3)), r"key 'origin': expected shape \(3\), got \(2, 3\)"),
    ("metadata", np.array("{not json"), r"key 'metadata': not valid JSON"),
    ("metadata", np.array(json.dumps([1, 2])), r"key 'metadata': expected a JSON object, got list"),
    ("params", None, r"missing key 'params'"),
]


def _with(arr, idx, value):
    out = arr.copy()
    out[idx] = value
    return out


@pytest.mark.parametrize("key, bad, match", CASES, ids=[f"{k}-{i}" for i, (k, _, _) in enumerate(CASES)])
def test_a_file_broken_in_one_key_is_refused_naming_file_and_key(tmp_path, key, bad, match):
    a = valid_arrays(tmp_path)
    path = rewrite(tmp_path, a, **{key: bad(a) if callable(bad) else bad})
    with pytest.raises(InputError, match=match) as info:
        VoxSplat.load(path)
    assert str(info.value).startswith(f"{path}: ")


def test_a_broken_channel_names_its_key(tmp_path):
    vs = VoxSplat(ijk=np.zeros((2, 3)) + [[0, 0, 0], [1, 0, 0]], params=np.zeros((2, 1, 14)), voxel_size=0.1)
    vs.set_channel("observed", np.array([True, False]))
    path = vs.save(tmp_path / "ch.npz")
    with np.load(path, allow_pickle=False) as z:
        a = {k: z[k] for k in z.files}
    a["channel.observed"] = np.array([True, False, True])
    bad = rewrite(tmp_path, a)
    with pytest.raises(InputError, match=r"key 'channel.observed': channel 'observed' .*expected leading shape \(2,\)"):
        VoxSplat.load(bad)


def test_the_cli_reports_a_broken_scene_in_one_line(tmp_path):
    a = valid_arrays(tmp_path)
    path = rewrite(tmp_path, a, labels=np.full(6, 999, np.int16))
    res = CliRunner().invoke(app, ["lidar", str(path), "--sensor", "vlp16", "-o", str(tmp_path / "x.pcd")])
    assert res.exit_code == 2
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "key 'labels'" in lines[0] and str(path) in lines[0]
    assert not (tmp_path / "x.pcd").exists()
