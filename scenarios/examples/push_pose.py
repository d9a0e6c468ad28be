"""Host loop that pushes its own poses: the host owns time and pose (here a circle of 15 m radius
at 8 m/s through a generated intersection) and calls `step` each tick; frames also go to files.

    .venv/bin/python scenarios/examples/push_pose.py [seconds] [out_dir]
"""

import sys

import numpy as np

from scube_sim.lidar import load_lidar_config
from scube_sim.raytrace import Tracer
from scube_sim.sim import FileSink, LidarSensor, Part, SimScene, Simulator
from scube_sim.transforms import pose_from_xyz_rpy
from scube_sim.worlds.generator import WorldConfig, generate_world

seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 2.0
out = sys.argv[2] if len(sys.argv) > 2 else "out/push_pose"
world = generate_world(WorldConfig(style="intersection", seed=11, layout="x_junction"))
junction = world.layout.junction
scene = SimScene(static=[Part(Tracer(world.static))])
lidar = LidarSensor.from_config(load_lidar_config("hdl32e"))
radius, speed = 15.0, 8.0
with Simulator(scene, [lidar], [FileSink(out, ("bin",))]) as sim:  # closes the sinks even on Ctrl-C
    for k in range(int(seconds * 20) + 1):
        t = k * 0.05  # the host ticks at 20 Hz, like the HDL-32E
        a = speed * t / radius
        xy = junction + radius * np.array([np.sin(a), 1.0 - np.cos(a)]) - [0.0, radius]
        pose = pose_from_xyz_rpy([xy[0], xy[1], 0.0], [0.0, 0.0, np.degrees(a)])
        frame = sim.step(t, pose)
        for sweep in frame.sweeps():
            print(f"t={t:5.2f} s  {sweep.name} sweep {sweep.sweep_index}: {len(sweep.points)} points")
print(f"frames in {out}/")
