"""Rebuilding the firing grid of a spinning sweep stored as returns only (Argoverse 2 keeps
returns only): a synthetic VLP-32C-like sweep with known dropped cells, and the real log."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from scube_sim.datasets.base import LidarSweep
from scube_sim.errors import InputError
from scube_sim.lidar.config import load_lidar_config
from scube_sim.realdata.raydrop import blind_sector, measure_cycle_us, rebuild_firing_grid
from scube_sim.transforms import make_pose

CYCLE_US = 55.296  # the VLP-32C's firing cycle
AV2 = Path(os.environ.get("SCUBE_SIM_SHARED_DATA", Path(__file__).resolve().parents[3] / "shared" / "data")) \
    / "argoverse2-sensor-log-7fab2350"


def synthetic_sweep(cycles=900, drop_share=0.12, seed=0):
    """A VLP-32C sweep as a returns-only log stores it: each (cycle, channel) fires at cycle start
    + the channel's fire time, times rounded to whole ns plus up to 0.5 us of packet jitter; the
    rotation speed wobbles by 2 % (so azimuth is not linear in the cycle index); each channel
    sits at its table azimuth offset with 0.01 degree jitter; a known set of cells (random, plus
    a run of 40 cycles on 5 channels) returns nothing. Returns the sweep, the config, the dropped
    mask (cycles, 32) and the true directions (cycles, 32, 3)."""
    cfg = load_lidar_config("VLP-32C")
    ch = cfg.pattern.channels
    el = np.deg2rad(ch.elevation_deg)
    off = np.deg2rad(ch.azimuth_offset_deg)
    fire = np.asarray(ch.fire_time_us)
    rng = np.random.default_rng(seed)
    k = np.arange(cycles)
    t_start = 3000.0 + k * CYCLE_US  # us after the sweep timestamp
    omega = 2 * np.pi * 10.0 * 1e-6 * (1 + 0.02 * np.sin(2 * np.pi * k / cycles))  # rad / us, wobbling
    enc = 0.3 - np.concatenate([[0.0], np.cumsum(omega[:-1] * CYCLE_US)])  # clockwise
    az = enc[:, None] + off[None, :] + np.deg2rad(0.01) * rng.standard_normal((cycles, 32))
    e = np.broadcast_to(el, (cycles, 32))
    d = np.stack([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)], -1)
    t = np.round((t_start[:, None] + fire[None, :]) * 1e3 + rng.uniform(-500, 500, (cycles, 32))) * 1e-9
    dropped = rng.random((cycles, 32)) < drop_share
    dropped[100:140, 3:8] = True
    r = rng.uniform(5, 60, (cycles, 32))
    keep = ~dropped.ravel()
    order = rng.permutation(int(keep.sum()))  # a log need not keep firing order
    pts = (d * r[..., None]).reshape(-1, 3)[keep][order]
    ring = np.tile(np.arange(32), cycles)[keep][order].astype(np.int16)
    sweep = LidarSweep("vlp", pts, make_pose(), 100.0, intensity=np.full(len(pts), 50, np.float32),
                       intensity_max=255.0, ring=ring, time_offset=t.ravel()[keep][order], motion_compensated=False,
                       pose_fn=lambda times: np.broadcast_to(make_pose(), (len(np.atleast_1d(times)), 4, 4)))
    return sweep, cfg, dropped, d


def test_synthetic_grid_recovers_exactly_the_dropped_cells():
    sweep, cfg, dropped, d = synthetic_sweep()
    g = rebuild_firing_grid(sweep, cfg)
    assert g.cycle_us == pytest.approx(CYCLE_US, abs=0.002)
    assert g.occupancy.shape == dropped.shape
    assert (g.occupancy >= 2).sum() == 0
    np.testing.assert_array_equal(g.occupancy == 0, dropped)
    np.testing.assert_array_equal(~g.rays.hit, dropped.ravel())
    assert g.rays.no_returns_known and len(g.rays) == dropped.size
    np.testing.assert_array_equal(g.rays.ring, np.tile(np.arange(32), dropped.shape[0]))
    assert np.max(np.abs(g.timing_residual_us)) < 0.51  # the jitter, plus the fitted phase's error
    # Rebuilt directions of the dropped cells: within 0.05 degrees of where the laser pointed
    # (its offset and the wobbling encoder are measured, not assumed).
    miss = dropped.ravel()
    cosang = np.einsum("ij,ij->i", g.rays.directions[miss], d.reshape(-1, 3)[miss])
    assert np.rad2deg(np.arccos(np.clip(cosang, -1, 1))).max() < 0.05
    # Measured offsets: the table's, up to a common shift.
    off = g.azimuth_offset_deg - np.asarray(cfg.pattern.channels.azimuth_offset_deg)
    assert np.ptp(off) < 0.02
    # Fire times of the dropped cells on the lattice.
    t_true = (3000.0 + np.arange(dropped.shape[0])[:, None] * CYCLE_US + np.asarray(
        cfg.pattern.channels.fire_time_us)[None, :]) * 1e-6
    np.testing.assert_allclose(g.rays.time[miss], t_true.ravel()[miss], atol=1e-6)


def test_times_off_the_lattice_are_refused():
    sweep, cfg, _, _ = synthetic_sweep(cycles=200)
    rng = np.random.default_rng(1)
    bad = LidarSweep("vlp", sweep.points, make_pose(), 100.0, ring=sweep.ring,
                     time_offset=rng.uniform(0, 0.1, len(sweep)), motion_compensated=True)
    with pytest.raises(InputError):
        rebuild_firing_grid(bad, cfg)


def test_cycle_period_from_gaps():
    t = np.array([0.0, 55.296, 3 * 55.296, 10 * 55.296, 11 * 55.296]) + 7.0
    assert measure_cycle_us(t, np.zeros(5, np.int64), 1e6 / 18000) == pytest.approx(55.296, abs=1e-9)


def test_blind_sector_wraps_through_the_rear():
    test = blind_sector(make_pose(), (170.0, -160.0), max_elevation_deg=10.0)
    a = np.deg2rad([180.0, 175.0, -165.0, 165.0, -150.0, 0.0, 180.0])
    e = np.deg2rad([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 20.0])
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], 1)
    np.testing.assert_array_equal(test(d), [True, True, True, False, False, False, False])


@pytest.mark.skipif(not AV2.is_dir(), reason=f"the Argoverse 2 log is not at {AV2} (../shared/data absent)")
def test_argoverse2_grid_from_timing():
    from scube_sim.datasets import open_dataset

    ds = open_dataset("argoverse2", AV2)
    sample = ds[0]
    for sweep in sample.sweeps:
        cfg = sample.lidars[sweep.sensor].config
        g = rebuild_firing_grid(sweep, cfg)
        # Every return on the 55.296 us lattice (to AV2's whole-us rounding), one per cell, a
        # rotation at 10 Hz (1800-1812 cycles in the sweep).
        assert g.cycle_us == pytest.approx(CYCLE_US, abs=0.01)
        assert np.max(np.abs(g.timing_residual_us)) < 0.6
        assert (g.occupancy >= 2).sum() == 0
        assert 1795 <= g.cycles <= 1815
        # Returns of one cycle agree on the encoder azimuth, once each laser's offset is removed.
        assert np.percentile(np.abs(g.azimuth_residual_deg), 99) < 0.05
        # The measured offsets are the VLP-32C calibration table's (rot_correction), up to a shift
        # (and its sign: the down unit is mounted upside down).
        table = np.asarray(cfg.pattern.channels.azimuth_offset_deg)
        m = g.azimuth_offset_deg - np.mean(g.azimuth_offset_deg)
        assert np.max(np.abs(m - (table - table.mean()))) < 0.15
        assert 0.08 < (g.occupancy == 0).mean() < 0.2


def test_the_fitted_vlp32c_profile_loads():
    from scube_sim.lidar.drop import DropModel

    m = DropModel.load(Path(__file__).resolve().parents[2] / "sensors" / "lidar" / "vlp32c.drop.yaml")
    assert m.sensor == "VLP-32C" and "up_lidar" in m.source and "log_range" in m.coefficients
