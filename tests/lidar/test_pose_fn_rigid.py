"""Poses are checked rigid wherever they enter a sweep: a pose function's poses (for the sweep's
ends and per distinct fire time), the static start / end poses, the ego pose a mount is applied
to, a scene part's fixed pose and pose function, a recorded trajectory. A scaled, sheared,
reflected or non-finite matrix, or one with a wrong last row, is refused by one check
(`scube_sim.transforms.check_poses`) naming where it came from, which pose (index and time) and
what a rigid pose is; float round-off is not refused."""

from __future__ import annotations

import re

import numpy as np
import pytest

from scube_sim.errors import InputError
from scube_sim.lidar.config import config_from_dict
from scube_sim.lidar.model import Lidar
from scube_sim.raytrace.tracer import Tracer
from scube_sim.sim.scene import Part, SimScene
from scube_sim.sim.simulator import LidarSensor, Simulator
from scube_sim.sim.sources import TrajectorySource
from scube_sim.transforms import pose_from_xyz_rpy
from scube_sim.worlds import primitives as pr

EXPECTED = ("expected a rigid pose: rotation orthonormal with det +1 (within 1e-05), last row [0, 0, 0, 1]")
T0 = 2.0


def lidar() -> Lidar:
    return Lidar(config_from_dict({"name": "ring", "pattern": {"type": "spinning", "columns": 90, "rotation_hz": 10.0,
                                                                "channels": {"elevation_deg": [-4.0, 0.0, 4.0]}},
                                   "range": {"min_m": 0.3, "max_m": 100.0}}))


def wall() -> Tracer:
    return Tracer(pr.box([0.0, 0.0, 0.0], [60.0, 60.0, 20.0]))


def path(times) -> np.ndarray:
    """A rigid moving sensor: (N,) seconds -> (N, 4, 4)."""
    times = np.atleast_1d(np.asarray(times, np.float64))
    return np.stack([pose_from_xyz_rpy([3.0 * t - 6.0, 0.2 * t, 1.5], [0.0, 0.0, 40.0 * t]) for t in times])


def scaled(p):
    p = p.copy()
    p[:3, :3] *= 1.01  # 1 % scale
    return p, r"rotation part is not orthonormal with det \+1 \(max \|R R\^T - I\| = 0\.0201: scaled or sheared\)"


def sheared(p):
    p = p.copy()
    p[0, :3] += 0.05 * p[1, :3]
    return p, r"rotation part is not orthonormal with det \+1 \(max \|R R\^T - I\| = 0\.05\d*: scaled or sheared\)"


def mirrored(p):
    p = p.copy()
    p[:3, 1] *= -1  # a proper-looking orthonormal matrix of det -1
    return p, r"rotation part is not orthonormal with det \+1 \(det -1\.000: a reflection\)"


def nan(p):
    p = p.copy()
    p[1, 3] = np.nan
    return p, r"contains NaN or Inf"


def inf(p):
    p = p.copy()
    p[0, 0] = np.inf
    return p, r"contains NaN or Inf"


def last_row(p):
    p = p.copy()
    p[3] = [0.0, 0.0, 0.1, 1.0]
    return p, r"last row must be \[0, 0, 0, 1\], got \[0\.0, 0\.0, 0\.1, 1\.0\]"


BAD = [scaled, sheared, mirrored, nan, inf, last_row]


def distinct_times(ld: Lidar) -> np.ndarray:
    return T0 + np.unique(ld.pattern.time)


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("call, index", [("ends", 1), ("rays", 0), ("rays", 37), ("rays", -1)])
def test_a_pose_function_s_bad_pose_is_refused_naming_it(bad, call, index):
    ld = lidar()
    times = distinct_times(ld)
    asked = []

    def fn(t):
        asked.append(len(t))
        out = path(t)
        if (call == "ends") == (len(asked) == 1):
            out[index], _ = bad(out[index])
        return out

    _, problem = bad(np.eye(4))
    if call == "ends":
        where = rf"pose_fn \(asked for the sweep's start and end\): pose 1 of 2 \(time {T0 + 0.1:.6f} s\)"
    else:
        i = index % len(times)
        where = (rf"pose_fn \(asked for each distinct fire time\): pose {i} of {len(times)} "
                 rf"\(time {times[i]:.6f} s\)")
    with pytest.raises(InputError, match="^" + where + ": " + problem + "; " + re.escape(EXPECTED) + "$"):
        ld.scan(wall(), None, pose_fn=fn, t_start=T0)
    assert asked == ([2] if call == "ends" else [2, len(times)])  # refused before any ray was traced


def test_the_first_message_in_full():
    ld = lidar()
    times = distinct_times(ld)

    def fn(t):
        out = path(t)
        if len(t) > 2:
            out[5, :3, :3] *= 1.01
        return out

    with pytest.raises(InputError) as info:
        ld.scan(wall(), None, pose_fn=fn, t_start=T0)
    assert str(info.value) == (f"pose_fn (asked for each distinct fire time): pose 5 of {len(times)} (time "
                               f"{times[5]:.6f} s): rotation part is not orthonormal with det +1 (max |R R^T - I| = "
                               f"0.0201: scaled or sheared); {EXPECTED}")


@pytest.mark.parametrize("shape", [(3, 4), (4, 3), (4,)])
def test_a_pose_function_of_the_wrong_shape_is_refused(shape):
    ld = lidar()
    n = len(distinct_times(ld))

    def fn(t):
        return path(t) if len(t) == 2 else np.zeros((len(t), *shape))

    with pytest.raises(InputError, match=re.escape(f"pose_fn (asked for each distinct fire time): expected ({n}, 4, 4) "
                                                   f"pose matrices, got shape ({n}, {', '.join(map(str, shape))})")):
        ld.scan(wall(), None, pose_fn=fn, t_start=T0)
    with pytest.raises(InputError, match=re.escape("pose_fn (asked for the sweep's start and end): expected (2, 4, 4) "
                                                   "pose matrices, got shape (3, 4, 4)")):
        ld.scan(wall(), None, pose_fn=lambda t: path([0.0, 0.1, 0.2]), t_start=T0)


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("where", ["pose_start", "pose_end", "ego_pose", "simulator ego_pose", "part pose",
                                   "part pose_fn", "trajectory"])
def test_every_other_way_a_pose_enters_a_sweep_is_checked_by_the_same_rule(bad, where):
    ld = lidar()
    good = path([T0])[0]
    wrong, problem = bad(good)
    tail = problem + "; " + re.escape(EXPECTED) + "$"
    with pytest.raises(InputError) as info:
        if where == "pose_start":
            ld.scan(wall(), wrong, good, t_start=T0)
        elif where == "pose_end":
            ld.scan(wall(), good, wrong, t_start=T0)
        elif where == "ego_pose":
            ld.sensor_pose(wrong)
        elif where == "simulator ego_pose":
            Simulator(wall(), [LidarSensor(ld, mount=np.eye(4))], seed=0).step(0.0, wrong)
        elif where == "part pose":
            Part(wall(), pose=wrong, name="car")
        elif where == "part pose_fn":
            def fn(t):
                out = path(t)
                out[-1], _ = bad(out[-1])
                return out

            ld.scan(SimScene(actors=[Part(wall(), pose_fn=fn, name="car")]), good, t_start=T0)
        else:
            TrajectorySource([0.0, 1.0, 2.0], np.stack([good, good, wrong]), name="drive")
    head = {"pose_start": "pose_start: ", "pose_end": "pose_end: ", "ego_pose": "ego_pose: ",
            "simulator ego_pose": "ego_pose: ", "part pose": "part 'car': pose: ",
            "part pose_fn": r"part 'car': pose_fn: pose \d+ of \d+ \(time \d+\.\d{6} s\): ",
            "trajectory": "drive: pose 2: "}[where]
    assert re.match("^" + head + tail, str(info.value)), str(info.value)


def test_round_off_is_not_refused():
    ld = lidar()

    def fn(t):  # float32 poses, as a log stores them: rotation off by ~1e-7
        return path(t).astype(np.float32)

    sweep = ld.scan(wall(), None, pose_fn=fn, t_start=T0)
    assert len(sweep.points) > 100
    p = path([T0])[0]
    p[:3, :3] *= 1 + 4e-6  # within the tolerance
    assert len(ld.scan(wall(), p, t_start=T0).points) > 100
