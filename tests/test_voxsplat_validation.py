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


def test_gaussians_wider_than_100_voxels_are_clamped_with_a_counted_warning(tmp_path):
    """Scale logits of +1e4 (finite, so not refused) would be 10 km needles that make a sweep
    crawl: load clamps them to 100 voxels and says how many, leaving the others bit for bit."""
    from scube_sim.errors import ScubeSimWarning

    a = valid_arrays(tmp_path)
    params = a["params"].copy()
    params[0, 0, 4] = 1e4          # valid slot, one axis
    params[1, 1, 4:7] = 50.0       # valid slot, all axes
    valid = a["valid"].copy()
    valid[2, 0] = False
    params[2, 0, 5] = 1e4          # an empty slot: not counted, left as it is
    path = rewrite(tmp_path, a, params=params, valid=valid)
    with pytest.warns(ScubeSimWarning, match=r"bad\.npz: 2 of 11 Gaussians are wider than 100 voxels \(20 m\)"):
        vs = VoxSplat.load(path)
    limit = np.float32(np.log(100 * 0.2))
    assert vs.params[0, 0, 4] == limit and np.all(vs.params[1, 1, 4:7] == limit)
    np.testing.assert_allclose(vs.scales()[0, 0, 0], 20.0, rtol=1e-6)
    assert vs.params[2, 0, 5] == np.float32(1e4)
    untouched = np.ones(params.shape[:2], bool)
    untouched[0, 0] = untouched[1, 1] = False
    np.testing.assert_array_equal(vs.params[untouched], params[untouched])
    # the CLI shows it as one warning line and carries on
    with pytest.warns(ScubeSimWarning):
        res = CliRunner().invoke(app, ["lidar", str(path), "--sensor", "vlp16", "-o", str(tmp_path / "x.pcd")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "x.pcd").exists()


def test_cli_prints_our_warnings_as_one_line(tmp_path):
    import subprocess
    import sys

    a = valid_arrays(tmp_path)
    params = a["params"].copy()
    params[0, 0, 4] = 1e4
    path = rewrite(tmp_path, a, params=params)
    res = subprocess.run([sys.executable, "-m", "scube_sim.cli", "lidar", str(path), "--sensor", "vlp16", "-o",
                          str(tmp_path / "x.pcd")], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    warn = [ln for ln in (res.stdout + res.stderr).splitlines() if ln.startswith("warning")]
    assert warn == [f"warning: {path}: 1 of 12 Gaussians are wider than 100 voxels (20 m); clamped to that"]


def test_ply_gaussians_wider_than_the_scene_are_clamped(tmp_path):
    from scube_sim.errors import ScubeSimWarning
    from scube_sim.io.ply3dgs import read_3dgs_ply, write_3dgs_ply
    from scube_sim.voxsplat import Gaussians

    n = 5
    scales = np.full((n, 3), 0.1)
    scales[3] = [1e4, 0.1, 0.1]
    g = Gaussians(means=np.c_[np.arange(n, dtype=float) * 3, np.zeros(n), np.zeros(n)], scales=scales,
                  quats=np.tile([1.0, 0, 0, 0], (n, 1)), opacities=np.full(n, 0.5), sh_dc=np.zeros((n, 3), np.float32))
    path = write_3dgs_ply(tmp_path / "wide.ply", g)
    with pytest.warns(ScubeSimWarning, match=r"wide\.ply: 1 of 5 Gaussians are wider than the scene \(12 m"):
        h = read_3dgs_ply(path)
    np.testing.assert_allclose(h.scales[3], [12.0, 0.1, 0.1], rtol=1e-6)
    np.testing.assert_allclose(h.scales[[0, 1, 2, 4]], 0.1, rtol=1e-6)
