"""`TriangleMesh.distance`: points at known distances from a unit square, the mesh kept in a
local frame far from the world's origin."""

from __future__ import annotations

import numpy as np

from scube_sim.mesh import TriangleMesh


def test_distance_to_a_unit_square_in_a_far_local_frame():
    origin = np.array([5000.0, -3000.0, 100.0])
    square = TriangleMesh(np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]), np.array([[0, 1, 2], [0, 2, 3]]),
                          origin=origin)
    pts = origin + np.array([[0.5, 0.5, 2.0],  # above the face: its height
                             [0.25, 0.75, -0.3],  # below it
                             [3.0, 0.5, 0.0],  # beside an edge, in its plane
                             [4.0, 5.0, 0.0],  # off a corner: 3-4-5
                             [0.4, 0.6, 0.0]])  # on it
    np.testing.assert_allclose(square.distance(pts), [2.0, 0.3, 2.0, 5.0, 0.0], atol=1e-5)
