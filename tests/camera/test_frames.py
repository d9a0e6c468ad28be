"""`Frames` / `CameraImage`: validation errors name the camera; lookup by camera name."""

from __future__ import annotations

import numpy as np
import pytest

from scube_sim.camera.frames import CameraImage, Frames
from scube_sim.camera.model import Intrinsics

INTR = Intrinsics(64, 48, 50.0, 50.0, 32.0, 24.0)


def pose(x=0.0, yaw=0.0):
    c, s = np.cos(yaw), np.sin(yaw)
    t = np.eye(4)
    t[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    t[0, 3] = x
    return t


def image(name="FRONT", *, size=(48, 64), intr=INTR, cam_to_world=None, timestamp=1.25, **kw):
    return CameraImage(name, np.zeros(size + (3,), np.uint8), intr,
                       pose() if cam_to_world is None else cam_to_world, timestamp, **kw)


def test_valid_image_keeps_a_float64_pose():
    im = image(cam_to_world=pose(3.0, 0.4).tolist())
    assert isinstance(im.cam_to_world, np.ndarray) and im.cam_to_world.dtype == np.float64
    np.testing.assert_array_equal(im.cam_to_world, pose(3.0, 0.4))


@pytest.mark.parametrize("size", [(64, 48), (48, 63), (47, 64)])
def test_image_size_must_match_intrinsics(size):
    with pytest.raises(ValueError) as exc:
        image("SIDE_LEFT", size=size)
    msg = str(exc.value)
    assert "'SIDE_LEFT'" in msg and f"{size[1]}x{size[0]}" in msg and "64x48" in msg


@pytest.mark.parametrize("bad, words", [
    (np.where(np.eye(4, dtype=bool), np.nan, 0.0), ["NaN"]),
    (np.full((4, 4), np.inf), ["NaN or Inf"]),
    (np.eye(3), ["(4, 4)"]),
    (np.diag([1.0, 1.0, -1.0, 1.0]), ["orthonormal"]),  # a reflection
    (np.diag([2.0, 1.0, 1.0, 1.0]), ["orthonormal"]),
])
def test_bad_pose_names_the_camera(bad, words):
    with pytest.raises(ValueError) as exc:
        image("FRONT_RIGHT", cam_to_world=bad)
    msg = str(exc.value)
    assert "'FRONT_RIGHT'" in msg and "cam_to_world" in msg
    for w in words:
        assert w in msg, msg


def test_nan_in_translation_names_the_camera():
    p = pose()
    p[1, 3] = np.nan
    with pytest.raises(ValueError, match="'REAR'.*NaN"):
        image("REAR", cam_to_world=p)


@pytest.mark.parametrize("t", [np.nan, np.inf, -np.inf])
def test_non_finite_timestamp_names_the_camera(t):
    with pytest.raises(ValueError, match="camera 'SIDE_RIGHT': timestamp is not finite"):
        image("SIDE_RIGHT", timestamp=t)


def test_frames_lookup_by_name():
    ims = [image("FRONT", timestamp=0.05), image("SIDE_LEFT", cam_to_world=pose(1.0, 1.5), timestamp=0.02),
           image("SIDE_RIGHT", timestamp=0.07)]
    frames = Frames(ims, pose(10.0), 0.0, {"dataset": "test"})
    assert len(frames) == 3 and frames.names == ["FRONT", "SIDE_LEFT", "SIDE_RIGHT"]
    assert frames["SIDE_LEFT"] is ims[1] and frames["FRONT"] is ims[0]
    np.testing.assert_array_equal(frames["SIDE_LEFT"].cam_to_world, pose(1.0, 1.5))
    with pytest.raises(KeyError) as exc:
        frames["BACK"]
    msg = str(exc.value)
    assert "'BACK'" in msg and "FRONT, SIDE_LEFT, SIDE_RIGHT" in msg


def test_frames_ego_pose_is_validated():
    p = pose()
    p[2, 2] = np.nan
    with pytest.raises(ValueError, match="Frames.ego_pose.*NaN"):
        Frames([image()], p, 0.0)
    with pytest.raises(ValueError, match="Frames.ego_pose"):
        Frames([image()], np.eye(3), 0.0)


@pytest.mark.parametrize("t", [np.nan, np.inf])
def test_frames_non_finite_timestamp_is_rejected(t):
    with pytest.raises(ValueError, match="timestamp"):
        Frames([image()], pose(), t)


def test_around_makes_another_instant_the_reference():
    intr = Intrinsics(4, 3, 2.0, 2.0, 2.0, 1.5)

    def instant(k):
        pose = np.eye(4)
        pose[0, 3] = float(k)
        im = CameraImage("cam", np.full((3, 4, 3), k + 10, np.uint8), intr, pose, 0.1 * k)
        return Frames([im], pose, 0.1 * k, log="log", offset=k)

    ctx = [instant(k) for k in (-2, -1, 1)]
    frames = Frames(instant(0).images, np.eye(4), 0.0, log="log", context=ctx)
    at = frames.around(-2)
    # the instant 2 back is the reference, offsets counted from it; nothing else changes
    assert at.offset == 0 and at.timestamp == pytest.approx(-0.2) and at.ego_pose[0, 3] == -2.0
    assert [c.offset for c in at.context] == [1, 2, 3]
    assert [float(c.ego_pose[0, 3]) for c in at.context] == [-1.0, 0.0, 1.0]
    assert at.images[0].image[0, 0, 0] == 8 and at.log == "log"
    assert frames.around(0) is frames
    # and back: the same instants as before
    back = at.around(2)
    assert [c.offset for c in back.context] == [-2, -1, 1] and back.timestamp == 0.0
    with pytest.raises(KeyError, match=r"offset 2; have \[-2, -1, 0, 1\]"):
        frames.around(2)
