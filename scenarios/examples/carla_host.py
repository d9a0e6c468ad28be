"""CARLA-style host loop: a fixed-step host (as CARLA in synchronous mode with
`fixed_delta_seconds`) owns time and the ego; each host tick hands over its frame number and the
ego's carla.Transform (Unreal's LEFT-handed axes: x forward, y right, z up, metres; rotation as
pitch, yaw, roll in degrees). The loop converts the pose into our frame (x forward, y left, z up),
calls `step` once per tick, matches the simulator's frame to the host's by tick number, and hands
the LiDAR points back on CARLA's axes (sensor frame, like carla.LidarMeasurement, and world).

No CARLA needed: `StandInCarlaHost` plays the server, with a street described in CARLA
coordinates (a building on the right, a fence on the left). With a real server, `tick()` becomes
``frame = world.tick(); snap = world.get_snapshot(); tf = ego.get_transform()``.

    .venv/bin/python scenarios/examples/carla_host.py [--seconds 2] [--hz 20] [--sensor vlp16] [--out DIR]
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

import numpy as np

from scube_sim.io.pointcloud import write_pcd
from scube_sim.labels import label_id
from scube_sim.lidar import load_lidar_config
from scube_sim.mesh import TriangleMesh
from scube_sim.raytrace import Tracer
from scube_sim.sim import LidarSensor, Simulator
from scube_sim.transforms import (
    carla_transform_to_pose,
    points_from_ours,
    points_to_ours,
    pose_to_carla_transform,
    transform_points,
)
from scube_sim.worlds import primitives as pr

BUILDING, FENCE, ROAD = label_id("building"), label_id("fence"), label_id("road")
# The host's map in CARLA coordinates: (centre x, y, z), size (x, y, z) metres, label.
CARLA_MAP = [
    ((60.0, 8.0, 3.0), (140.0, 0.4, 6.0), BUILDING),  # right of the road (CARLA +y)
    ((60.0, -9.0, 0.75), (140.0, 0.2, 1.5), FENCE),  # left of the road
    ((60.0, 0.0, -0.05), (140.0, 40.0, 0.1), ROAD),
]
LIDAR_MOUNT = ((0.0, 0.0, 1.8), (0.0, 0.0, 0.0))  # carla.Transform(Location(z=1.8)) on the ego


def scene_from_carla_map(boxes) -> TriangleMesh:
    """CARLA-frame axis-aligned boxes -> one mesh in our frame. A box maps onto a box under the
    y flip (only its centre moves); a general mesh would also need its faces rewound."""
    return TriangleMesh.concatenate([pr.box(points_to_ours([c], "carla")[0], size, label=lab) for c, size, lab in boxes])


@dataclass
class StandInCarlaHost:
    """Plays a CARLA server in synchronous mode: every `tick` advances `dt` seconds and returns
    (frame number, elapsed seconds, ego location (x, y, z) m, rotation (pitch, yaw, roll) deg),
    all on CARLA's axes. The ego drives at `speed` m/s, turning right at `yaw_rate` deg/s
    (positive CARLA yaw is clockwise seen from above)."""

    dt: float = 0.05
    speed: float = 10.0
    yaw_rate: float = 4.0
    frame: int = 4711  # CARLA's frame counter does not start at 0

    def __post_init__(self):
        self.elapsed, self.loc, self.yaw, self._started = 0.0, np.zeros(3), 0.0, False

    def tick(self):
        if self._started:  # the first tick reports the start state
            heading = math.radians(self.yaw)
            self.loc += self.speed * self.dt * np.array([math.cos(heading), math.sin(heading), 0.0])
            self.yaw += self.yaw_rate * self.dt
            self.elapsed += self.dt
        self._started = True
        self.frame += 1
        return self.frame, self.elapsed, self.loc.copy(), np.array([0.0, self.yaw, 0.0])


def main(argv=None) -> list[dict]:
    """Run the loop; one record per host tick (host frame, sim frame index, time, and per
    sweep the points and the sensor transform on CARLA's axes)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--hz", type=float, default=20.0, help="host tick rate (fixed_delta_seconds = 1/hz)")
    ap.add_argument("--sensor", default="vlp16", help="LiDAR preset")
    ap.add_argument("--out", default=None, help="folder for per-sweep PCD files on CARLA's axes")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)

    host = StandInCarlaHost(dt=1.0 / args.hz)
    mount = carla_transform_to_pose(*LIDAR_MOUNT)  # sensor-to-ego, both CARLA-axed -> ours
    lidar = LidarSensor.from_config(load_lidar_config(args.sensor), mount=mount)
    records = []
    with Simulator(Tracer(scene_from_carla_map(CARLA_MAP)), [lidar]) as sim:
        first = None
        for _ in range(int(round(args.seconds * args.hz)) + 1):
            host_frame, t, loc, rot = host.tick()
            first = host_frame if first is None else first
            frame = sim.step(t, carla_transform_to_pose(loc, rot))  # poses in: CARLA -> ours
            if frame.index != host_frame - first:  # frames matched by tick number
                raise RuntimeError(f"host frame {host_frame} got simulator frame {frame.index}")
            rec = {"host_frame": host_frame, "sim_index": frame.index, "time": t, "sweeps": []}
            for sweep in frame.sweeps():
                xyz = np.stack([sweep.points[f] for f in "xyz"], 1).astype(np.float64)
                sensor_carla = points_from_ours(xyz, "carla")  # points out: ours -> CARLA (sensor frame)
                world_carla = points_from_ours(transform_points(sweep.pose, xyz), "carla")
                s_loc, s_rot = pose_to_carla_transform(sweep.pose)
                rec["sweeps"].append({"name": sweep.name, "t_end": sweep.t_end, "labels": sweep.points["label"],
                                      "sensor_xyz": sensor_carla, "world_xyz": world_carla,
                                      "sensor_location": s_loc, "sensor_rotation": s_rot})
                if args.out:
                    out = sweep.points.copy()
                    out["x"], out["y"], out["z"] = sensor_carla.T
                    write_pcd(f"{args.out}/{sweep.name}_{host_frame:06d}.pcd", out)
                if not args.quiet:
                    print(f"host frame {host_frame} (t={t:5.2f} s) -> sim frame {frame.index}: {sweep.name} "
                          f"{len(xyz)} points; sensor at CARLA ({s_loc[0]:.2f}, {s_loc[1]:.2f}, {s_loc[2]:.2f}) "
                          f"yaw {s_rot[1]:.1f} deg")
            records.append(rec)
    return records


if __name__ == "__main__":
    main()
