"""Poses estimated once per log (`datasets.odometry`): both estimators recover a known motion in
a synthetic street, the second command on the same sweeps reads the cache (no estimate), a
changed sweep or a damaged entry is estimated again, and a bad estimator name is one line."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.datasets import odometry
from scube_sim.transforms import invert_pose, pose_from_xyz_rpy


def _street(rng) -> np.ndarray:
    """World points (M, 3): two building fronts, a ground plane and posts along a 120 m street."""
    n = 12_000
    x = rng.uniform(-60, 60, n)
    wall = np.c_[x, np.where(rng.random(n) < 0.5, -8.0, 9.0) + rng.normal(0, 0.01, n), rng.uniform(0, 8, n)]
    ground = np.c_[rng.uniform(-60, 60, n), rng.uniform(-8, 9, n), rng.normal(0, 0.01, n)]
    posts = np.concatenate([np.c_[np.full(400, px) + rng.normal(0, 0.1, 400), np.full(400, py) + rng.normal(0, 0.1, 400),
                                  rng.uniform(0, 4, 400)] for px in range(-55, 60, 11) for py in (-6.0, 7.0)])
    return np.concatenate([wall, ground, posts])


def _sweeps(rng, steps):
    """Sweeps (sensor frame, within 50 m) from poses chained by `steps` (K - 1, 4, 4), and those poses."""
    world = _street(rng)
    poses = [pose_from_xyz_rpy([-20.0, 0.0, 1.8], [0, 0, 0])]
    for s in steps:
        poses.append(poses[-1] @ s)
    out = []
    for p in poses:
        local = (world - p[:3, 3]) @ p[:3, :3]
        keep = np.linalg.norm(local, axis=1) < 50
        out.append(local[keep] + rng.normal(0, 0.005, (int(keep.sum()), 3)))
    return out, np.stack(poses)


@pytest.mark.parametrize("method", ["icp", "kiss-icp"])
def test_both_estimators_recover_a_known_motion(method, rng):
    steps = [pose_from_xyz_rpy([1.0, 0.02 * k, 0.0], [0, 0, np.radians(0.5)]) for k in range(4)]
    sweeps, truth = _sweeps(rng, steps)
    est = odometry.odometry(method).estimate(sweeps)
    assert est.method == method and est.poses.shape == (5, 4, 4) and len(est.steps) == 4
    np.testing.assert_array_equal(est.poses[0], np.eye(4))
    want = invert_pose(truth[0]) @ truth  # world = the first sweep's frame
    assert np.abs(est.poses[:, :3, 3] - want[:, :3, 3]).max() < 0.05
    for s, t in zip(est.steps, steps):
        assert np.linalg.norm(s.pose[:3, 3] - t[:3, 3]) < 0.03 and s.fitness > 0.8 and s.rmse < 0.1


def test_a_second_command_reads_the_cache_and_a_changed_sweep_misses_it(rng, tmp_path, monkeypatch):
    monkeypatch.setenv(odometry.CACHE_ENV, str(tmp_path / "cache"))
    sweeps, _ = _sweeps(rng, [pose_from_xyz_rpy([1.0, 0, 0], [0, 0, 0])] * 2)
    files = []
    for k, s in enumerate(sweeps):
        files.append(tmp_path / f"{k}.npy")
        np.save(files[-1], s)
    calls = []

    def read(path):
        calls.append(path)
        return np.load(path)

    first = odometry.log_poses(files, read, "icp")
    assert len(calls) == 3 and len(list((tmp_path / "cache" / "poses").glob("*.npz"))) == 1
    again = odometry.log_poses(files, read, "icp")
    assert len(calls) == 3  # nothing read, nothing estimated
    assert again.poses.tobytes() == first.poses.tobytes() and again.method == "icp"
    assert [s.fitness for s in again.steps] == [s.fitness for s in first.steps]
    np.save(files[2], sweeps[2] + [0.3, 0.0, 0.0])  # the sweep changed: estimated again
    odometry.log_poses(files, read, "icp")
    assert len(calls) == 6
    entries = list((tmp_path / "cache" / "poses").glob("*.npz"))
    assert len(entries) == 2
    for e in entries:
        e.write_bytes(b"not an npz")  # a damaged entry is estimated again, not trusted
    odometry.log_poses(files, read, "icp")
    assert len(calls) == 9


def test_the_cache_folder_and_a_bad_name(monkeypatch, tmp_path):
    monkeypatch.setenv(odometry.CACHE_ENV, str(tmp_path / "c"))
    assert odometry.cache_dir() == tmp_path / "c"
    monkeypatch.delenv(odometry.CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert odometry.cache_dir() == tmp_path / "xdg" / "scube-sim"
    with pytest.raises(ValueError, match="odometry: expected one of icp, kiss-icp, got 'gps'"):
        odometry.odometry("gps")
