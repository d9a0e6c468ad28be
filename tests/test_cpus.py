"""The thread policy (`scube_sim.cpus`): a faked cgroup quota of 1 CPU sizes the pools to 1, the
affinity mask caps them, and a bad request names its flag or variable."""

from __future__ import annotations

import os

import pytest

from scube_sim import cpus


def _v2(tmp_path, cpu_max: str, rel: str = "/pod/app"):
    proc = tmp_path / "cgroup"
    proc.write_text(f"0::{rel}\n")
    folder = tmp_path / "fs" / rel.strip("/")
    folder.mkdir(parents=True)
    (folder / "cpu.max").write_text(cpu_max + "\n")
    return tmp_path / "fs", proc


def test_a_v2_quota_of_one_cpu_gives_one_thread(tmp_path, monkeypatch):
    root, proc = _v2(tmp_path, "100000 100000")
    monkeypatch.setattr(cpus, "affinity_cpus", lambda: 64)
    assert cpus.cgroup_cpus(root, proc) == pytest.approx(1.0)
    assert cpus.usable_cpus(root, proc) == 1
    monkeypatch.setattr(cpus, "CGROUP_ROOT", root)
    monkeypatch.setattr(cpus, "PROC_CGROUP", proc)
    monkeypatch.delenv(cpus.THREADS_ENV, raising=False)
    assert cpus.resolve_threads(None) == 1 and cpus.resolve_threads(0) == 1


def test_a_parent_quota_limits_the_child_and_fractions_round_up(tmp_path, monkeypatch):
    root, proc = _v2(tmp_path, "max 100000", rel="/pod/app")
    (root / "pod" / "cpu.max").write_text("150000 100000\n")  # 1.5 CPUs on the parent
    monkeypatch.setattr(cpus, "affinity_cpus", lambda: 8)
    assert cpus.usable_cpus(root, proc) == 2


def test_a_v1_quota_and_no_quota(tmp_path, monkeypatch):
    proc = tmp_path / "cgroup"
    proc.write_text("5:cpu,cpuacct:/docker/abc\n3:memory:/docker/abc\n")
    folder = tmp_path / "fs" / "cpu,cpuacct" / "docker" / "abc"
    folder.mkdir(parents=True)
    (folder / "cpu.cfs_quota_us").write_text("300000\n")
    (folder / "cpu.cfs_period_us").write_text("100000\n")
    monkeypatch.setattr(cpus, "affinity_cpus", lambda: 16)
    assert cpus.usable_cpus(tmp_path / "fs", proc) == 3
    (folder / "cpu.cfs_quota_us").write_text("-1\n")
    assert cpus.cgroup_cpus(tmp_path / "fs", proc) is None
    assert cpus.usable_cpus(tmp_path / "fs", proc) == 16
    assert cpus.usable_cpus(tmp_path / "fs", tmp_path / "missing") == 16  # no cgroup file at all


def test_the_affinity_mask_caps_the_count():
    if not hasattr(os, "sched_getaffinity"):
        pytest.skip("no affinity mask on this platform")
    assert cpus.affinity_cpus() == len(os.sched_getaffinity(0))
    assert 1 <= cpus.usable_cpus() <= cpus.affinity_cpus()


def test_requests_and_the_environment(monkeypatch):
    monkeypatch.delenv(cpus.THREADS_ENV, raising=False)
    assert cpus.resolve_threads(3) == 3
    monkeypatch.setenv(cpus.THREADS_ENV, "2")
    assert cpus.resolve_threads(None) == 2 and cpus.resolve_threads(5) == 5
    monkeypatch.setenv(cpus.THREADS_ENV, "many")
    with pytest.raises(ValueError, match="SCUBE_SIM_THREADS: expected a positive thread count, got 'many'"):
        cpus.resolve_threads(None)
    monkeypatch.delenv(cpus.THREADS_ENV)
    with pytest.raises(ValueError, match="--threads: expected 0 .* got -2"):
        cpus.resolve_threads(-2)
