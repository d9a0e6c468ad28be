"""The worlds' surface detail: fixed to the surfaces (world or object frame), filtered by the pixel
footprint without moving its mean, view-dependent on glass only."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.boxes import Box
from scube_sim.labels import label_id
from scube_sim.transforms import make_pose
from scube_sim.worlds.textures import ObjectFrames, albedo, lines

SIDEWALK, BUILDING, CAR, ROAD = label_id("sidewalk"), label_id("building"), label_id("car"), label_id("road")


def _wall(n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """Points on the wall x = 5 (normal -x), y in [0, 10), z in [0, 3): below the first storey's
    windows, so the facade's material only."""
    p = np.stack([np.full(n, 5.0), rng.uniform(0, 10, n), rng.uniform(0.0, 3.0, n)], 1)
    return p, np.tile([-1.0, 0.0, 0.0], (n, 1))


def test_lines_are_an_exact_box_filter():
    x = np.linspace(0.0, 6.0, 120_001)[:-1]  # ten periods
    sharp = lines(x, 0.6, 0.012, 1e-6)
    assert np.mean((sharp > 1e-9) & (sharp < 1 - 1e-9)) < 1e-3  # an indicator but at the edges
    assert sharp.mean() == pytest.approx(0.012 / 0.6, rel=1e-3)
    for fw in (0.005, 0.05, 0.3, 2.0):
        wide = lines(x, 0.6, 0.012, fw)
        assert np.all((wide >= -1e-12) & (wide <= 1 + 1e-12))
        assert wide.mean() == pytest.approx(0.012 / 0.6, rel=1e-3)  # a box filter keeps the mean
        # and spreads a thin line's weight: a window holds at most floor(fw / P) + 1 lines
        assert wide.max() <= min(1.0, (np.floor(fw / 0.6) + 1) * 0.012 / fw) + 1e-9


@pytest.mark.parametrize("label", [SIDEWALK, BUILDING, ROAD])
def test_detail_fades_with_the_footprint_and_keeps_the_mean(label):
    """Seen from far away (a footprint of metres) a surface is one tone: its close-up mean. The
    detail's variance falls as the footprint grows."""
    rng = np.random.default_rng(0)
    n = 60_000
    if label == BUILDING:
        p, nrm = _wall(n, rng)
    else:
        p = np.stack([rng.uniform(0, 10, n), rng.uniform(0, 10, n), np.zeros(n)], 1)
        nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    base = np.tile([0.5, 0.45, 0.4], (n, 1))
    inst = np.full(n, 7)
    spread = []
    for fw in (0.002, 0.02, 0.1, 0.5, 4.0):
        c = albedo(p, nrm, np.full(n, label), base, inst, footprint=fw)
        spread.append(float(c[:, 1].std()))
    assert spread == sorted(spread, reverse=True) and spread[-1] < 0.5 * spread[0], spread
    fine = albedo(p, nrm, np.full(n, label), base, inst, footprint=0.002)[:, 1].mean()
    # (a footprint well inside the sampled patch: a box filter wider than it averages in what lies
    # outside, e.g. the storeys above the wall's lowest 3 m)
    blurred = albedo(p, nrm, np.full(n, label), base, inst, footprint=0.5)[:, 1].mean()
    assert blurred == pytest.approx(fine, rel=0.08)


def test_glass_alone_depends_on_the_view():
    rng = np.random.default_rng(1)
    n = 4000
    p, nrm = _wall(n, rng)
    p[:, 2] = rng.uniform(3.6, 30.0, n)  # the upper storeys: windows and wall
    base = np.tile([0.6, 0.5, 0.4], (n, 1))
    lab, inst = np.full(n, BUILDING), np.full(n, 3)
    v1 = np.tile([1.0, 0.0, 0.0], (n, 1))
    v2 = np.tile([0.6, 0.8, 0.0], (n, 1))
    a = albedo(p, nrm, lab, base, inst, footprint=0.01, view=v1)
    b = albedo(p, nrm, lab, base, inst, footprint=0.01, view=v2)
    moved = np.any(np.abs(a - b) > 1e-6, axis=1)
    assert 0.05 < moved.mean() < 0.9  # the windows' share of the facade, not all of it
    ground = np.stack([rng.uniform(0, 9, n), rng.uniform(0, 9, n), np.zeros(n)], 1)
    up = np.tile([0.0, 0.0, 1.0], (n, 1))
    for label in (ROAD, SIDEWALK):
        c1 = albedo(ground, up, np.full(n, label), base, inst, footprint=0.01, view=v1 * 0.6 - up * 0.8)
        c2 = albedo(ground, up, np.full(n, label), base, inst, footprint=0.01, view=v2 * 0.6 - up * 0.8)
        assert np.array_equal(c1, c2)


def test_a_vehicle_carries_its_texture_with_it():
    """The same point of a car's body, with the car at two poses, has the same colour when its
    box's frame is given; in world coordinates the texture would slide over the moving car."""
    size = np.array([4.5, 1.8, 1.5])
    rng = np.random.default_rng(2)
    n = 3000
    # points on the car's left side and front, object frame (origin at the bottom centre)
    side = np.stack([rng.uniform(-2.2, 2.2, n), np.full(n, 0.9), rng.uniform(0.45, 1.0, n)], 1)
    front = np.stack([np.full(n, 2.25), rng.uniform(-0.85, 0.85, n), rng.uniform(0.45, 1.0, n)], 1)
    q = np.concatenate([side, front])
    qn = np.concatenate([np.tile([0.0, 1.0, 0.0], (n, 1)), np.tile([1.0, 0.0, 0.0], (n, 1))])
    base = np.tile([0.7, 0.1, 0.1], (2 * n, 1))
    lab, inst = np.full(2 * n, CAR), np.full(2 * n, 42)
    colours = []
    for xy, yaw in (((10.0, 3.0), 0.3), ((25.0, -4.0), 2.0)):
        pose = make_pose(np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]),
                         np.array([xy[0], xy[1], 0.0]))
        frames = ObjectFrames.from_boxes([Box.on_ground(pose, size, label=CAR, instance=42)])
        p = q @ pose[:3, :3].T + pose[:3, 3]
        pn = qn @ pose[:3, :3].T
        colours.append(albedo(p, pn, lab, base, inst, footprint=0.005, objects=frames))
        world_frame = albedo(p, pn, lab, base, inst, footprint=0.005)
    np.testing.assert_allclose(colours[0], colours[1], atol=1e-5)
    assert not np.allclose(world_frame, colours[1], atol=1e-3)
    # and the front has lights and a plate: bright paint-free areas on a red car
    fr = colours[0][n:]
    assert (fr.min(1) > 0.8).mean() > 0.02


def test_object_frames_put_the_box_bottom_centre_at_the_origin():
    pose = make_pose(np.eye(3), np.array([3.0, 4.0, 0.5]))
    f = ObjectFrames.from_boxes([Box.on_ground(pose, [4.0, 2.0, 1.5], instance=9), Box.on_ground(pose, [1, 1, 1])])
    assert f.ids.tolist() == [9]  # boxes without an instance id carry nothing
    np.testing.assert_allclose(f.to_object[0] @ np.array([3.0, 4.0, 0.5, 1.0]), [0, 0, 0, 1], atol=1e-12)
    assert f.lookup(np.array([9, 8, 0])).tolist() == [0, -1, -1]


def test_camera_exposure_is_a_gain_per_camera_that_drifts_slowly():
    from scube_sim.worlds.dataset import camera_exposure

    gains = np.array([[camera_exposure(7, c, t) for t in np.arange(0.0, 6.0, 0.1)] for c in range(5)])
    assert np.all((gains >= 0.88 * 0.97 - 1e-12) & (gains <= 1.12 * 1.03 + 1e-12))
    assert np.ptp(gains[:, 0]) > 0.02  # cameras differ
    assert np.abs(np.diff(gains, axis=1)).max() < 0.01  # within 0.1 s: at most ~1 %
    assert camera_exposure(7, 2, 0.35) == camera_exposure(7, 2, 0.35) != camera_exposure(8, 2, 0.35)
