"""Frame conventions in scube_sim.transforms against independent expectations: each convention's
documented axes as unit vectors, CARLA's rotation semantics and the carla_ros_bridge conversion
(scipy as the Euler oracle), USD's own fallbacks (pxr), OpenSCENARIO angles (scipy), and real
nuScenes calibration (LIDAR_TOP and CAM_FRONT extrinsics)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from scube_sim.transforms import (
    FRAME_CONVENTIONS,
    carla_rotation_matrix,
    carla_transform_to_pose,
    check_rotation,
    frame_convention,
    hpr_to_rotmat,
    make_pose,
    points_from_ours,
    points_to_ours,
    pose_from_ours,
    pose_to_carla_transform,
    pose_to_ours,
    rotmat_to_hpr,
    transform_points,
    usd_frame_convention,
)
from tests.conftest import look_at, require

PROPS = settings(max_examples=50, deadline=None)
FWD, LEFT, UP = np.eye(3)
RIGHT, DOWN, BACK = -LEFT, -UP, -FWD

# Each convention's x, y, z axes as its documentation states them, in our words.
DOCUMENTED = {
    "ours": (FWD, LEFT, UP, 1.0),
    "rep103": (FWD, LEFT, UP, 1.0),
    "carla": (FWD, RIGHT, UP, 1.0),
    "unreal": (FWD, RIGHT, UP, 0.01),
    "opencv": (RIGHT, DOWN, FWD, 1.0),
    "nuscenes_lidar": (RIGHT, FWD, UP, 1.0),
    "usd_z_up": (FWD, LEFT, UP, 1.0),
    "usd_y_up": (FWD, UP, RIGHT, 1.0),
}


@pytest.mark.parametrize("name", sorted(DOCUMENTED))
def test_each_convention_maps_its_unit_axes_as_documented(name):
    *axes, mpu = DOCUMENTED[name]
    got = points_to_ours(np.eye(3), name)  # rows: the convention's x, y, z unit vectors
    np.testing.assert_allclose(got, np.array(axes) * mpu, atol=1e-15)
    np.testing.assert_allclose(points_from_ours(np.array(axes) * mpu, name), np.eye(3), atol=1e-15)
    assert frame_convention(name).right_handed == (name not in ("carla", "unreal"))


def test_every_convention_is_listed_and_unknown_names_say_which_exist():
    assert set(FRAME_CONVENTIONS) == set(DOCUMENTED)
    with pytest.raises(ValueError, match="'gazebo'.*carla.*opencv"):
        frame_convention("gazebo")


# --- CARLA --------------------------------------------------------------------------------------

def test_carla_rotation_semantics():
    # From CARLA's docs and Unreal's axes: yaw turns forward towards +y (right, a clockwise turn
    # seen from above), pitch raises the nose, roll lowers the right side.
    np.testing.assert_allclose(carla_rotation_matrix(0, 90, 0) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(carla_rotation_matrix(90, 0, 0) @ [1, 0, 0], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(carla_rotation_matrix(0, 0, 90) @ [0, 1, 0], [0, 0, -1], atol=1e-15)
    # yaw first, then pitch and roll about the turned axes: R = Yaw @ Pitch @ Roll
    y, p, r = carla_rotation_matrix(0, 30, 0), carla_rotation_matrix(-20, 0, 0), carla_rotation_matrix(0, 0, 10)
    np.testing.assert_allclose(carla_rotation_matrix(-20, 30, 10), y @ p @ r, atol=1e-15)


def test_carla_yaw_right_turn_is_a_right_turn_in_our_frame():
    pose = carla_transform_to_pose([0, 0, 0], [0, 90, 0])  # facing CARLA's +y: to the right
    np.testing.assert_allclose(pose[:3, 0], RIGHT, atol=1e-15)


angles = st.tuples(st.floats(-89, 89), st.floats(-180, 180), st.floats(-180, 180))
locations = st.tuples(*[st.floats(-1e4, 1e4)] * 3)


@PROPS
@given(locations, angles)
def test_carla_transform_matches_the_ros_bridge_rule(loc, rot):
    # carla_ros_bridge: x, -y, z and roll, -pitch, -yaw with R = Rz Ry Rx (scipy intrinsic ZYX).
    pitch, yaw, roll = rot
    expected = make_pose(Rotation.from_euler("ZYX", [-yaw, -pitch, roll], degrees=True).as_matrix(),
                         [loc[0], -loc[1], loc[2]])
    np.testing.assert_allclose(carla_transform_to_pose(loc, rot), expected, atol=1e-9)


@PROPS
@given(locations, angles)
def test_carla_transform_round_trips(loc, rot):
    got_loc, got_rot = pose_to_carla_transform(carla_transform_to_pose(loc, rot))
    np.testing.assert_allclose(got_loc, loc, atol=1e-9)
    np.testing.assert_allclose(got_rot, rot, atol=1e-7)


def test_carla_points_and_poses_round_trip_unchanged(rng):
    p = rng.normal(0, 50, (100, 3))
    np.testing.assert_allclose(points_from_ours(points_to_ours(p, "carla"), "carla"), p, atol=1e-12)
    m = make_pose(carla_rotation_matrix(12.0, -135.0, 4.0), [10.0, -20.0, 1.5])
    back = pose_from_ours(pose_to_ours(m, "carla"), "carla")
    np.testing.assert_allclose(back, m, atol=1e-12)
    # and a point moved by the pose is the same point whichever frame does the moving
    local = rng.normal(0, 3, (20, 3))
    np.testing.assert_allclose(transform_points(pose_to_ours(m, "carla"), points_to_ours(local, "carla")),
                               points_to_ours(transform_points(m, local), "carla"), atol=1e-9)


# An asymmetric object in CARLA terms: a car 4 m long with a mirror on its right side only.
CAR_NOSE, RIGHT_MIRROR = np.array([2.0, 0.0, 0.5]), np.array([0.5, 1.0, 1.0])  # CARLA body frame


def test_a_pose_converted_without_the_y_flip_mirrors_the_object():
    m = make_pose(carla_rotation_matrix(0.0, 30.0, 0.0), [100.0, 40.0, 0.0])  # 30 deg right of +x, 40 m right
    parts = np.stack([CAR_NOSE, RIGHT_MIRROR])
    truth = points_to_ours(transform_points(m, parts), "carla")  # where the parts are, in our axes
    pose = pose_to_ours(m, "carla")
    body = points_to_ours(parts, "carla")  # the car model in our body axes: mirror at y = -1
    np.testing.assert_allclose(transform_points(pose, body), truth, atol=1e-12)
    assert body[1, 1] < 0

    # Half a conversion (the y flip on the world side only: S R, S t) is a reflection: the car
    # lands at the right place and heading, but as its mirror image (mirror on the left)...
    s = np.diag([1.0, -1.0, 1.0])
    half = make_pose(s @ m[:3, :3], s @ m[:3, 3])
    assert np.linalg.det(half[:3, :3]) == pytest.approx(-1.0)
    placed = transform_points(half, body)
    np.testing.assert_allclose(placed[0], truth[0], atol=1e-12)  # the nose, on the symmetry plane
    seen_from_car = transform_points(np.linalg.inv(pose), placed)
    np.testing.assert_allclose(seen_from_car, body * [1, -1, 1], atol=1e-12)  # mirror now at y = +1
    with pytest.raises(ValueError, match="reflection"):  # ...and the check refuses it
        check_rotation(half[:3, :3])

    # No conversion at all (CARLA's numbers taken as ours) keeps det +1: the check cannot see it,
    # but the pose is the mirror image of the true one across the x axis: 40 m left, turning left.
    np.testing.assert_allclose(m[:3, 3], pose[:3, 3] * [1, -1, 1])
    np.testing.assert_allclose(rotmat_to_hpr(m[:3, :3])[0], -rotmat_to_hpr(pose[:3, :3])[0])


def test_half_a_flip_is_a_reflection_and_is_refused():
    s = np.diag([1.0, -1.0, 1.0])
    m = carla_rotation_matrix(5.0, 30.0, -3.0)
    assert np.linalg.det(s @ m) == pytest.approx(-1.0)  # the y flip applied to one side only
    with pytest.raises(ValueError, match="reflection.*handedness"):
        check_rotation(s @ m, "half-flipped CARLA pose")
    np.testing.assert_array_equal(check_rotation(s @ m @ s), s @ m @ s)  # both sides: proper
    # a right-handed child inside a left-handed parent has no proper rotation: refused too
    with pytest.raises(ValueError, match=r"carla -> ours.*reflection"):
        pose_to_ours(make_pose(m), "carla", child_frame="ours")
    with pytest.raises(ValueError, match="not orthonormal"):
        check_rotation(2 * np.eye(3))


def test_unreal_centimetres():
    pose = pose_to_ours(make_pose(None, [250.0, 100.0, 30.0]), "unreal")
    np.testing.assert_allclose(pose[:3, 3], [2.5, -1.0, 0.3])
    with pytest.raises(ValueError, match="units"):
        pose_to_ours(np.eye(4), "unreal", child_frame="carla")


# --- OpenCV, nuScenes, USD, OpenSCENARIO -------------------------------------------------------

def test_opencv_camera_pose_to_a_body_pose():
    # conftest's look_at builds an OpenCV camera-to-world pose independently.
    cam = look_at([1.0, 2.0, 1.5], [11.0, 2.0, 1.5])  # looking along +x
    body = pose_to_ours(cam, "ours", child_frame="opencv")
    np.testing.assert_allclose(body[:3, :3], np.eye(3), atol=1e-12)  # body x forward = optical axis
    np.testing.assert_allclose(pose_from_ours(body, "ours", child_frame="opencv"), cam, atol=1e-12)


def test_real_nuscenes_extrinsics_follow_the_documented_axes(shared_data):
    from scube_sim.io.safe_pickle import load_pickle

    folder = require(shared_data / "nuscenes-mmdet3d-demo")
    info = load_pickle(next(folder.glob("*.pkl")))["data_list"][0]
    lidar2ego = np.asarray(info["lidar_points"]["lidar2ego"])[:3, :3]
    cam2ego = np.asarray(info["images"]["CAM_FRONT"]["cam2ego"])[:3, :3]
    # calibrated extrinsics are within a degree or so of the nominal axes
    for measured, name in ((lidar2ego, "nuscenes_lidar"), (cam2ego, "opencv")):
        angle = Rotation.from_matrix(measured.T @ frame_convention(name).basis).magnitude()
        assert np.degrees(angle) < 2.0, name


def test_usd_fallbacks_are_usds_own():
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateInMemory()  # nothing authored
    assert not stage.HasAuthoredMetadata("upAxis") and not stage.HasAuthoredMetadata("metersPerUnit")
    unset = usd_frame_convention(None, None)
    assert UsdGeom.GetStageUpAxis(stage) == "Y"
    assert unset.meters_per_unit == UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    np.testing.assert_allclose(points_to_ours([[0.0, 250.0, 0.0]], unset), [[0.0, 0.0, 2.5]])
    ours = usd_frame_convention("Z", 1.0)
    np.testing.assert_array_equal(ours.basis, np.eye(3))
    with pytest.raises(ValueError, match="upAxis"):
        usd_frame_convention("X", 1.0)


@PROPS
@given(st.floats(-np.pi, np.pi), st.floats(-1.5, 1.5), st.floats(-np.pi, np.pi))
def test_openscenario_heading_pitch_roll(h, p, r):
    # ASAM: heading about z, then pitch about the new y, then roll about the new x (scipy "ZYX").
    expected = Rotation.from_euler("ZYX", [h, p, r]).as_matrix()
    np.testing.assert_allclose(hpr_to_rotmat(h, p, r), expected, atol=1e-12)
    np.testing.assert_allclose(hpr_to_rotmat(*rotmat_to_hpr(expected)), expected, atol=1e-9)


def test_openscenario_angle_senses():
    np.testing.assert_allclose(hpr_to_rotmat(np.pi / 2) @ FWD, LEFT, atol=1e-15)  # heading CCW from above
    np.testing.assert_allclose(hpr_to_rotmat(0, 0.1) @ FWD, [np.cos(0.1), 0, -np.sin(0.1)], atol=1e-15)  # nose down
    np.testing.assert_allclose(hpr_to_rotmat(0, 0, 0.1) @ LEFT, [0, np.cos(0.1), np.sin(0.1)], atol=1e-15)


# --- the CARLA-style host example, end to end ----------------------------------------------------

def test_carla_host_example_runs_and_returns_carla_frame_points(monkeypatch):
    import importlib.util
    import sys

    from tests.conftest import REPO

    spec = importlib.util.spec_from_file_location("carla_host", REPO / "scenarios" / "examples" / "carla_host.py")
    mod = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "carla_host", mod)  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    records = mod.main(["--seconds", "0.3", "--hz", "20", "--quiet"])
    assert [r["sim_index"] for r in records] == list(range(7))  # one step per host tick
    assert np.all(np.diff([r["host_frame"] for r in records]) == 1)
    sweeps = [s for r in records for s in r["sweeps"]]
    assert len(sweeps) == 3  # a 10 Hz LiDAR on a 20 Hz host
    for s in sweeps:
        labels, world, sensor = s["labels"], s["world_xyz"], s["sensor_xyz"]
        # The host's map, in its own CARLA coordinates: the building's face at y = +7.8 (right),
        # the fence's at y = -8.9 (left). A missed y flip would swap the sides.
        assert np.median(world[labels == mod.BUILDING, 1]) == pytest.approx(7.8, abs=0.1)
        assert np.median(world[labels == mod.FENCE, 1]) == pytest.approx(-8.9, abs=0.1)
        assert np.median(sensor[labels == mod.BUILDING, 1]) > 5 and np.median(sensor[labels == mod.FENCE, 1]) < -5
        assert s["sensor_location"][2] == pytest.approx(1.8)
    # the sensor turns right with the ego: CARLA yaw grows, and its path bends to +y
    yaws = [s["sensor_rotation"][1] for s in sweeps]
    assert yaws[0] < yaws[1] < yaws[2] and sweeps[-1]["sensor_location"][1] > 0
