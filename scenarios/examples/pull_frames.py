"""Host loop that pulls frames: the simulator drives itself along a generated world's ego path and
the host consumes each frame as it comes (here: counts points per class and prints a line).

    .venv/bin/python scenarios/examples/pull_frames.py [seconds]
"""

import sys

import numpy as np

from scube_sim.labels import LABEL_NAMES
from scube_sim.lidar import load_lidar_config
from scube_sim.raytrace import Tracer
from scube_sim.sim import LidarSensor, Part, SimScene, Simulator, TrajectorySource, track_pose_fn
from scube_sim.worlds.generator import WorldConfig, generate_world

seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 2.0
world = generate_world(WorldConfig(style="urban", seed=7, layout="x_junction", duration_s=seconds + 0.5))
scene = SimScene(
    static=[Part(Tracer(world.static))],  # the world's exact mesh; a VoxSplat works the same way
    actors=[Part(Tracer(a.mesh), pose_fn=track_pose_fn(a.times, a.poses), instance=a.instance, label=a.label,
                 size=a.size) for a in world.actors],
    static_boxes=world.boxes_static,
)
sim = Simulator(scene, [LidarSensor.from_config(load_lidar_config("vlp32c"))], seed=0)
for frame in sim.run(TrajectorySource(world.ego_times, world.ego_poses), t_end=seconds):
    for sweep in frame.sweeps():
        labels, counts = np.unique(sweep.points["label"], return_counts=True)
        top = ", ".join(f"{LABEL_NAMES[k]} {c}" for k, c in sorted(zip(labels, counts), key=lambda x: -x[1])[:3])
        print(f"t={frame.time:4.1f} s  {sweep.name}: {len(sweep.points):6d} points ({top}); "
              f"{len(frame.boxes)} boxes")
