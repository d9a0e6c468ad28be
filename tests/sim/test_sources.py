"""Pose sources against closed forms: straight and circular paths, rigid poses, held ends,
lateral edits on a circle, poses held within a sweep, and the `PoseSource` contract."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.sim.can import CanTrajectory
from scube_sim.sim.contracts import PoseSource
from scube_sim.sim.sources import EditedTrajectory, HeldPoses, TrajectorySource, track_pose_fn
from scube_sim.sim.vehicle import DeadReckoner
from scube_sim.transforms import interpolate_poses, pose_from_xyz_rpy

R, OMEGA = 20.0, 0.5  # circle radius (m) and yaw rate (rad/s): 10 m/s, turning left


def circle_pose(t: float) -> np.ndarray:
    """On a left circle of radius R about (0, R), starting at the origin heading +x."""
    a = OMEGA * t
    return pose_from_xyz_rpy([R * np.sin(a), R * (1.0 - np.cos(a)), 0.0], [0.0, 0.0, np.degrees(a)])


def circle(dt: float = 0.5, span: float = 6.0) -> TrajectorySource:
    times = np.arange(0.0, span + 1e-9, dt)
    return TrajectorySource(times, [circle_pose(t) for t in times])


def assert_rigid(poses: np.ndarray) -> None:
    r = poses[:, :3, :3]
    np.testing.assert_allclose(np.einsum("nji,njk->nik", r, r), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    np.testing.assert_array_equal(poses[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (len(poses), 4)))


def test_a_straight_path_is_interpolated_exactly():
    # x = 2 + 7 t, y = -1, heading 30 deg, samples at uneven times.
    times = np.array([0.0, 0.3, 1.1, 1.2, 4.0])
    yaw = 30.0
    src = TrajectorySource(times, [pose_from_xyz_rpy([2 + 7 * t, -1.0, 0.5], [0, 0, yaw]) for t in times])
    q = np.linspace(0.0, 4.0, 97)
    p = src.poses_at(q)
    np.testing.assert_allclose(p[:, 0, 3], 2 + 7 * q, atol=1e-12)
    np.testing.assert_allclose(p[:, 1:3, 3], np.broadcast_to([-1.0, 0.5], (len(q), 2)), atol=1e-12)
    np.testing.assert_allclose(np.degrees(np.arctan2(p[:, 1, 0], p[:, 0, 0])), yaw, atol=1e-10)
    assert_rigid(p)
    assert (src.t_start, src.t_end) == (0.0, 4.0)
    np.testing.assert_allclose(src.pose_at(2.5)[:3, 3], [2 + 7 * 2.5, -1.0, 0.5], atol=1e-12)


def test_a_circle_turns_at_a_constant_rate_and_moves_along_its_chords():
    src = circle(dt=0.5)
    q = np.linspace(0.0, 6.0, 121)
    p = src.poses_at(q)
    assert_rigid(p)
    # SLERP about one axis: the heading is exactly omega t
    np.testing.assert_allclose(np.unwrap(np.arctan2(p[:, 1, 0], p[:, 0, 0])), OMEGA * q, atol=1e-10)
    # the position moves linearly along the chord between the bracketing samples ...
    k = np.minimum(np.floor(q / 0.5 + 1e-12), 11).astype(int)
    s = (q - 0.5 * k) / 0.5
    a0, a1 = OMEGA * 0.5 * k, OMEGA * 0.5 * (k + 1)
    chord = (1 - s)[:, None] * np.column_stack([R * np.sin(a0), R * (1 - np.cos(a0))]) + \
        s[:, None] * np.column_stack([R * np.sin(a1), R * (1 - np.cos(a1))])
    np.testing.assert_allclose(p[:, :2, 3], chord, atol=1e-12)
    # ... so it stays within the sagitta R (1 - cos(omega dt / 2)) inside the circle, and on it at the samples
    dist = np.linalg.norm(p[:, :2, 3] - [0.0, R], axis=1)
    sagitta = R * (1 - np.cos(OMEGA * 0.5 / 2))
    assert np.all(dist <= R + 1e-12) and np.all(dist >= R - sagitta - 1e-12)
    at = np.isclose(s, 0.0) | np.isclose(s, 1.0)
    np.testing.assert_allclose(dist[at], R, atol=1e-12)


def test_track_pose_fn_holds_its_ends_and_a_single_sample():
    times = np.array([1.0, 2.0, 3.0])
    poses = np.stack([circle_pose(t) for t in times])
    fn = track_pose_fn(times, poses)
    p = fn(np.array([-5.0, 0.999, 1.0, 3.0, 3.001, 100.0]))
    for i in (0, 1, 2):
        np.testing.assert_allclose(p[i], poses[0], atol=1e-15)
    for i in (3, 4, 5):
        np.testing.assert_allclose(p[i], poses[-1], atol=1e-15)
    one = track_pose_fn([2.0], poses[1:2])
    np.testing.assert_array_equal(one(np.array([0.0, 2.0, 9.0])), np.broadcast_to(poses[1], (3, 4, 4)))
    # a scalar time gives one pose
    assert fn(2.5).shape == (1, 4, 4)


def test_track_poses_are_the_same_in_any_query_order_and_match_one_segment_at_a_time():
    # A sweep's ordered fire times go through one slice per segment with cached segments; any
    # other order through masks. Both against the straightforward formula: each time on its own,
    # interpolated between the two samples around it.
    times = np.array([0.0, 0.1, 0.2, 0.35, 0.5])
    poses = np.stack([circle_pose(3.0 * t) for t in times])  # 1.5 rad/s: the SLERP branch
    fn = track_pose_fn(times, poses)
    q = np.r_[np.linspace(0.05, 0.45, 3001), times, -1.0, 2.0]
    q.sort()
    want = []
    for tq in q:
        tc = np.clip(tq, times[0], times[-1])
        k = min(int(np.searchsorted(times, tc, side="right")) - 1, len(times) - 2)
        want.append(interpolate_poses(poses[k], poses[k + 1], [(tc - times[k]) / (times[k + 1] - times[k])])[0])
    want = np.stack(want)
    ordered = fn(q)
    np.testing.assert_array_equal(ordered, fn(q))  # the cached segments give the same bytes again
    perm = np.random.default_rng(3).permutation(len(q))
    np.testing.assert_array_equal(fn(q[perm]), ordered[perm])
    np.testing.assert_allclose(ordered, want, rtol=0, atol=1e-15)
    # and on the circle itself, between samples: the chord's position, the exact heading
    mid = fn(np.array([0.05]))[0]
    np.testing.assert_allclose(mid[:3, :3], circle_pose(0.15)[:3, :3], atol=1e-14)


def test_a_lateral_edit_on_a_circle_moves_towards_its_centre():
    # Left of the heading on a left turn is towards the centre: the edited path is the circle of
    # radius R - offset at the samples (inside it between them, by the chords' sagitta).
    base = circle(dt=0.5)
    offset = 3.5
    e = EditedTrajectory(base, lateral_offset_m=offset)
    q = np.arange(0.0, 6.01, 0.5)
    p = e.poses_at(q)
    assert_rigid(p)
    np.testing.assert_allclose(np.linalg.norm(p[:, :2, 3] - [0.0, R], axis=1), R - offset, atol=1e-12)
    np.testing.assert_allclose(p[:, :3, :3], base.poses_at(q)[:, :3, :3], atol=0)
    # ramped in: nothing before the ramp, all of it after, half at its middle (smoothstep)
    ramp = EditedTrajectory(base, lateral_offset_m=offset, lateral_ramp=(1.0, 3.0))
    d = np.linalg.norm(ramp.poses_at(np.array([0.5, 1.0, 2.0, 3.0, 4.0]))[:, :2, 3] - [0.0, R], axis=1)
    np.testing.assert_allclose(d, [R, R, R - offset / 2, R - offset, R - offset], atol=1e-12)


def test_held_poses_give_every_time_of_a_query_its_last_pose():
    base = circle(dt=0.5)
    held = HeldPoses(base)
    q = np.linspace(1.0, 1.1, 50)
    p = held.poses_at(q)
    np.testing.assert_array_equal(p, np.broadcast_to(base.poses_at(q[-1:])[0], (50, 4, 4)))
    assert (held.t_start, held.t_end) == (base.t_start, base.t_end)


def test_can_trajectory_presents_dead_reckoning_as_a_pose_source():
    # A log read at once (not paced): constant 12 m/s straight ahead from a start pose.
    rk = DeadReckoner(start_pose=pose_from_xyz_rpy([5.0, 1.0, 0.0], [0, 0, 90.0]))
    for k in range(31):
        rk.update(0.1 * k, speed=12.0, steer_deg=0.0)

    class Read:  # what CanTrajectory reads of a CanPoseSource
        realtime, finished = False, True
        duration = rk.last_time
        pose_at = staticmethod(rk.pose_at)

    src = CanTrajectory(Read(), duration=3.0)
    p = src.poses_at(np.array([0.0, 1.25, 3.0]))
    np.testing.assert_allclose(p[:, :2, 3], [[5.0, 1.0], [5.0, 16.0], [5.0, 37.0]], atol=1e-9)
    assert_rigid(p)
    assert (src.t_start, src.t_end) == (0.0, 3.0) and rk.last_time == pytest.approx(3.0)


def test_every_source_is_a_pose_source():
    base = circle()
    for src in (base, EditedTrajectory(base, speed_scale=2.0), HeldPoses(base)):
        assert isinstance(src, PoseSource)
        assert_rigid(src.poses_at(np.linspace(src.t_start, src.t_end, 7)))
