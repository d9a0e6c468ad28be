"""The ground's plane and height field (`reconstruct.ground`) on an analytic road: a 2 % slope,
a 0.15 m kerb, a car standing on it, a stretch nobody measured and outliers."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.errors import InputError
from scube_sim.reconstruct.ground import fit_ground_plane, fit_height_field

SLOPE, KERB_Y, KERB_M = 0.02, 4.0, 0.15
EXTENT = (0.0, 40.0, -10.0, 10.0)


def _truth(x, y):
    return SLOPE * x + np.where(y >= KERB_Y, KERB_M, 0.0)


def _road(seed: int = 0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform([0.0, -10.0], [40.0, 10.0], (16000, 2))
    car = (xy[:, 0] > 10) & (xy[:, 0] < 14) & (np.abs(xy[:, 1]) < 1)  # hidden under the car
    hole = (xy[:, 0] > 25) & (xy[:, 0] < 30)  # measured by nobody
    xy = xy[~car & ~hole]
    ground = np.column_stack([xy, _truth(xy[:, 0], xy[:, 1]) + rng.normal(0, 0.02, len(xy))])
    # the car: its sides and roof, its underside 0.3 m over the road
    u = rng.uniform([10.0, -1.0, 0.3], [14.0, 1.0, 1.5], (3000, 3))
    u[:1000, 2] = 0.3
    u[:, 2] += SLOPE * u[:, 0]
    outliers = np.column_stack([rng.uniform([0, -10], [40, 10], (300, 2)), rng.uniform(-3, 3, 300)])
    return np.concatenate([ground, u, outliers])


def test_the_plane_follows_the_road():
    plane = fit_ground_plane(_road())
    assert plane is not None
    assert np.degrees(np.arccos(plane.normal[2])) == pytest.approx(np.degrees(np.arctan(SLOPE)), abs=0.3)


def test_the_height_field_keeps_the_kerb_and_bridges_what_nobody_saw():
    field = fit_height_field(_road(), EXTENT, cell=1.0)
    c = field.centres()
    truth = _truth(c[..., 0], c[..., 1])
    err = np.abs(field.heights - truth)
    under_car = (c[..., 0] > 10) & (c[..., 0] < 14) & (np.abs(c[..., 1]) < 1)
    hole = (c[..., 0] > 25) & (c[..., 0] < 30)
    assert not field.observed[under_car].any() and not field.observed[hole].any()
    assert field.observed[~under_car & ~hole].all()
    assert err[field.observed].max() < 0.03, err[field.observed].max()  # the kerb stays a step
    # the slope is bridged; where the kerb runs through the hole nobody saw where it steps: a blend
    near_kerb = np.abs(c[..., 1] - KERB_Y) < 2.0
    assert err[under_car].max() < 0.03 and err[hole & ~near_kerb].max() < 0.03
    assert err[hole & near_kerb].max() < KERB_M
    # bilinear between centres: a point on the slope, away from the kerb
    assert field.height_at(np.array([[20.0, -5.0]]))[0] == pytest.approx(SLOPE * 20.0, abs=0.03)


def test_no_ground_no_field_and_bad_extents_refused():
    assert fit_height_field(np.zeros((2, 3)), EXTENT) is None
    wall = np.column_stack([np.zeros(100), np.linspace(0, 5, 100), np.tile(np.linspace(0, 3, 10), 10)])
    assert fit_ground_plane(wall) is None  # vertical: tilted beyond the limit
    with pytest.raises(InputError, match="extent"):
        fit_height_field(_road(), (5.0, 1.0, 0.0, 1.0))


def test_beyond_the_measured_ground_a_rise_decays_to_the_plane():
    # a level road measured from x = 0 to 30 m, its last 4 m raised 0.5 m (far stereo's noisy
    # heights), nothing measured from 30 to 90 m
    rng = np.random.default_rng(3)
    xy = rng.uniform([0.0, -10.0], [30.0, 10.0], (12000, 2))
    z = np.where(xy[:, 0] > 26.0, 0.5, 0.0) + rng.normal(0, 0.01, len(xy))
    pts = np.column_stack([xy, z])
    extent = (0.0, 90.0, -10.0, 10.0)
    carried = fit_height_field(pts, extent, cell=1.0)
    decayed = fit_height_field(pts, extent, cell=1.0, fill_decay_m=8.0)
    far = np.array([[40.0, 0.0], [60.0, 0.0], [88.0, 0.0]])
    plane_z = decayed.plane.z_at(far)
    # carried unchanged: the rise runs on to the edge; decayed: exp(-d / 8 m) of it d metres on
    assert np.all(carried.height_at(far) - plane_z > 0.4)
    rise = decayed.height_at(far) - plane_z
    d = far[:, 0] - 29.5  # from the last measured cells' centres
    assert np.all(np.isfinite(rise)) and np.all(rise > 0)
    assert np.all(np.abs(rise - (carried.height_at(far) - plane_z) * np.exp(-d / 8.0)) < 0.05), rise
    # measured cells are the same either way
    assert np.array_equal(decayed.heights[decayed.observed], carried.heights[carried.observed])
