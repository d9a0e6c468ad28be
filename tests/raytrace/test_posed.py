"""`PosedScene`: a scene traced in its own frame and placed by a rigid pose gives the hits of the
same scene moved into the world, by hand on a mesh square and on a converted-style VoxSplat."""

import numpy as np
import pytest

from scube_sim.errors import InputError
from scube_sim.mesh import TriangleMesh
from scube_sim.raytrace.posed import PosedScene, place_scene
from scube_sim.raytrace.tracer import Tracer
from scube_sim.transforms import pose_from_xyz_rpy
from scube_sim.voxsplat import VoxSplat


def _wall(x: float) -> TriangleMesh:
    """A 20 m square in the plane x = `x` of its own frame, facing -x."""
    v = np.array([[x, -10, -10], [x, 10, -10], [x, 10, 10], [x, -10, 10]], float)
    return TriangleMesh(v, [[0, 1, 2], [0, 2, 3]])


def test_a_posed_wall_is_hit_where_the_pose_puts_it():
    pose = pose_from_xyz_rpy([1.0e6, -2.0e6, 30.0], [0.0, 0.0, 90.0])  # yaw 90 deg: scene x is world y
    scene = PosedScene(Tracer(_wall(5.0)), pose)
    origin = pose[:3, 3] + np.array([0.0, 1.0, 0.0])  # 1 m along world y from the scene origin
    h = scene.trace_world(origin[None], np.array([[0.0, 1.0, 0.0]]))
    assert h.hit[0] and h.t[0] == pytest.approx(4.0, abs=1e-9)
    np.testing.assert_allclose(h.points[0], pose[:3, 3] + [0.0, 5.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(h.normals[0], [0.0, -1.0, 0.0], atol=1e-6)  # facing the ray, in the world
    miss = scene.trace_world(origin[None], np.array([[1.0, 0.0, 0.0]]))
    assert not miss.hit[0] and np.isnan(miss.points[0]).all()
    with pytest.raises(InputError):
        PosedScene(Tracer(_wall(5.0)), np.full((4, 4), np.nan))


def test_place_scene_poses_chunk_frame_voxsplats_only():
    params = np.zeros((1, 1, 14), np.float32)
    params[..., 3] = 10.0  # opaque
    params[..., 4:7] = np.log(0.2)
    params[..., 7] = 1.0
    pose = pose_from_xyz_rpy([100.0, 50.0, 0.0], [0.0, 0.0, 180.0])
    vs = VoxSplat(np.array([[10, 0, 0]]), params, voxel_size=1.0, origin=np.zeros(3),
                  metadata={"frame": "chunk", "chunk_to_world": pose.tolist()})
    tracer = Tracer(vs, mode="entry")
    placed = place_scene(tracer, vs)
    assert isinstance(placed, PosedScene)
    # the Gaussian sits at chunk (10.5, 0.5, 0.5); yaw 180: world (89.5, 49.5, 0.5)
    o = np.array([[100.0, 49.5, 0.5]])
    h = placed.trace_world(o, np.array([[-1.0, 0.0, 0.0]]))
    assert h.hit[0] and h.t[0] == pytest.approx(10.5 - 3 * 0.2, abs=1e-6)
    vs.metadata = {}
    assert place_scene(tracer, vs) is tracer
