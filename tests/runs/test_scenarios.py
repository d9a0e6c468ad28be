"""Scenario files, the replay command, and the USD stage of a whole run against its frames."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from scube_sim.cli import app
from scube_sim.io.pointcloud import read_kitti_bin, read_pcd
from scube_sim.lidar.config import ConfigError
from scube_sim.runs.scenario import build_run, load_scenario
from scube_sim.sim.sinks import CallbackSink

REPO = Path(__file__).resolve().parents[2]
runner = CliRunner()

TINY = """
name: tiny
seed: 4
duration_s: 0.6
scene:
  world: {style: suburban, seed: 3, layout: straight, length_m: 60}
  representation: mesh
trajectory: {source: world}
sensors:
  - {preset: vlp16}
  - {preset: vlp16, name: rear, mount: {xyz: [-1.0, 0.0, 1.6], rpy_deg: [0, 0, 180]}, phase_s: 0.05}
outputs: {files: [pcd, bin], usd: run.usda}
"""


def write(tmp_path, text, name="s.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize("name", sorted(p.stem for p in (REPO / "scenarios").glob("*.yaml")))
def test_shipped_scenarios_validate(name):
    sc, base = load_scenario(REPO / "scenarios" / f"{name}.yaml")
    assert sc.name == name and sc.sensors


def test_scenario_errors_name_the_key(tmp_path):
    bad = write(tmp_path, TINY.replace("seed: 4", "sead: 4"))
    with pytest.raises(ConfigError, match=r"s.yaml: sead: unknown key"):
        load_scenario(bad)
    two = write(tmp_path, TINY.replace("representation: mesh", "representation: mesh\n  voxsplat: x.npz"), "two.yaml")
    with pytest.raises(ConfigError, match="exactly one of world, voxsplat, ply, chunks or frames"):
        load_scenario(two)
    can = write(tmp_path, TINY.replace("{source: world}", "{source: can}"), "can.yaml")
    with pytest.raises(ConfigError, match="trajectory: .*'can' section"):
        load_scenario(can)
    sensor = write(tmp_path, TINY.replace("{preset: vlp16}", "{preset: vlp16, overrides: {range: {max_m: -1}}}"),
                   "sensor.yaml")
    sc, base = load_scenario(sensor)
    with pytest.raises(ConfigError, match="range.max_m"):
        build_run(sc, base, tmp_path / "out")


@pytest.mark.parametrize("usd", ["../x.usdc", "a/../../x.usdc", "/tmp/x.usdc", "~/x.usdc", "C:\\x.usdc",
                                 "..\\x.usdc", " "])
def test_outputs_stay_inside_the_output_folder(tmp_path, usd):
    """A scenario's output path that leaves -o (parent links, absolute, home, a drive) is refused
    when the file is read, naming the key; nothing is written."""
    text = TINY.replace("usd: run.usda", f"usd: {json.dumps(usd)}")
    assert text != TINY
    bad = write(tmp_path, text)
    with pytest.raises(ConfigError, match=r"s\.yaml: outputs\.usd: .*inside the output folder"):
        load_scenario(bad)
    res = runner.invoke(app, ["replay", str(bad), "-o", str(tmp_path / "r")])
    assert res.exit_code == 2 and "outputs.usd" in res.output and not (tmp_path / "r").exists()
    ok = write(tmp_path, TINY.replace("usd: run.usda", "usd: stages/run.usdc"), "ok.yaml")
    assert load_scenario(ok)[0].outputs.usd == "stages/run.usdc"


def test_trajectory_edits_that_leave_no_time_or_run_backwards_are_refused(tmp_path):
    """A time shift past the trajectory's end simulated '0 ticks (-97 s)' before; a lane-change
    ramp that ends before it starts failed without the file or key."""
    past = write(tmp_path, TINY.replace("{source: world}", "{source: world, edit: {time_shift_s: 1000}}"), "past.yaml")
    sc, base = load_scenario(past)
    with pytest.raises(ConfigError, match=r"trajectory: the run would simulate no time .*time_shift_s 1000"):
        build_run(sc, base, tmp_path / "out")
    res = runner.invoke(app, ["replay", str(past), "-o", str(tmp_path / "r")])
    assert res.exit_code == 2 and "simulate no time" in res.output
    ramp = write(tmp_path, TINY.replace("{source: world}", "{source: world, edit: {lateral_offset_m: 3.5, "
                                                           "lateral_ramp_s: [2.0, 1.0]}}"), "ramp.yaml")
    with pytest.raises(ConfigError, match=r"ramp\.yaml: trajectory\.edit\.lateral_ramp_s: .*end > start"):
        load_scenario(ramp)


def test_run_usd_samples_equal_the_frames(tmp_path):
    """The stage of a run opens, validates, and holds exactly the sweeps the callback got."""
    from pxr import Usd, UsdGeom

    sc, base = load_scenario(write(tmp_path, TINY))
    sim, src, t0, t1 = build_run(sc, base, tmp_path / "out")
    got = []
    sim.sinks.append(CallbackSink(got.append))
    frames = list(sim.run(src, t_start=t0, t_end=t1, dt=0.1))
    assert [f.index for f in got] == [f.index for f in frames] == list(range(7))
    stage = Usd.Stage.Open(str(tmp_path / "out" / "run.usda"))
    tcps = stage.GetTimeCodesPerSecond()
    n_sweeps = 0
    for f in got:
        for s in f.sweeps():
            prim = UsdGeom.Points(stage.GetPrimAtPath(f"/World/Sensors/{s.name}/Points"))
            code = (s.t_end - t0) * tcps
            pts = np.asarray(prim.GetPointsAttr().Get(code))
            want = np.stack([s.points["x"], s.points["y"], s.points["z"]], 1)
            np.testing.assert_array_equal(pts, want)
            xf = UsdGeom.Xformable(stage.GetPrimAtPath(f"/World/Sensors/{s.name}"))
            np.testing.assert_allclose(np.asarray(xf.GetLocalTransformation(code)).T, s.pose, atol=1e-12)
            n_sweeps += 1
    assert n_sweeps == 11  # vlp16: 6 sweeps ending at 0.1 .. 0.6; rear (phase 0.05): 5 ending at 0.15 .. 0.55
    last = max(s.t_end for f in got for s in f.sweeps())
    assert stage.GetEndTimeCode() == pytest.approx((last - t0) * tcps)
    from tests.io.test_usd import validation_errors  # the UsdValidation check used for the exports

    assert not validation_errors(stage)
    # and the files beside it
    lines = [json.loads(x) for x in (tmp_path / "out" / "frames" / "frames.jsonl").read_text().splitlines()]
    assert len(lines) == n_sweeps
    for rec in lines:
        pcd, bin_ = (tmp_path / "out" / "frames" / f for f in rec["files"])
        assert len(read_pcd(pcd)) == len(read_kitti_bin(bin_)) == rec["points"]


def test_replay_command(tmp_path):
    scen = write(tmp_path, TINY)
    res = runner.invoke(app, ["replay", str(scen), "-o", str(tmp_path / "r"), "--duration", "0.3"])
    assert res.exit_code == 0, res.output
    assert "tiny: 4 ticks" in res.output and "ticks/s" in res.output
    assert (tmp_path / "r" / "run.usda").exists()
    res = runner.invoke(app, ["replay", str(write(tmp_path, "name: x\n", "bad.yaml")), "-o", str(tmp_path / "b")])
    assert res.exit_code == 2
    assert res.output.strip().startswith("error: ") and "bad.yaml" in res.output


def test_replay_twice_gives_the_same_frames(tmp_path):
    scen = write(tmp_path, TINY)
    for out in ("a", "b"):
        assert runner.invoke(app, ["replay", str(scen), "-o", str(tmp_path / out)]).exit_code == 0
    fa = sorted((tmp_path / "a" / "frames").rglob("*.bin"))
    fb = sorted((tmp_path / "b" / "frames").rglob("*.bin"))
    assert len(fa) == len(fb) == 11
    for x, y in zip(fa, fb):
        assert x.read_bytes() == y.read_bytes()


def test_an_openscenario_trajectory_into_a_ros_bag_a_viewer_recording_and_las_files(tmp_path):
    """A scenario driven by an OpenSCENARIO polyline writes a ROS 2 bag (Autoware layout for one
    sensor), a Foxglove recording and LAS files; each reads back with another library."""
    import laspy
    from rosbags.highlevel import AnyReader

    from scube_sim.io.openscenario import write_openscenario
    from scube_sim.sim.sinks.viewer import read_recording
    from scube_sim.transforms import make_pose

    times = np.array([0.0, 1.0, 2.0])
    poses = np.stack([make_pose(np.eye(3), [x, 0.0, 0.0]) for x in (0.0, 8.0, 16.0)])
    write_openscenario(tmp_path / "ego.xosc", times, poses)
    text = TINY.replace("trajectory: {source: world}", "trajectory: {source: openscenario, file: ego.xosc}")
    text = text.replace("outputs: {files: [pcd, bin], usd: run.usda}",
                        "outputs: {files: [las], usd: null, rosbag: {folder: bag, layouts: {rear: autoware_xyzirc}},"
                        " viewer: run.mcap}")
    sc, base = load_scenario(write(tmp_path, text))
    sim, src, t0, t1 = build_run(sc, base, tmp_path / "out")
    got = []
    sim.sinks.append(CallbackSink(got.append))
    list(sim.run(src, t_start=t0, t_end=t1, dt=0.1))  # the run closes its sinks at the end
    # the ego follows the polyline: 8 m/s along x
    for f in got:
        assert f.ego_pose[0, 3] == pytest.approx(8.0 * f.time, abs=1e-3) and abs(f.ego_pose[1, 3]) < 1e-9
    sweeps = [(f.index, s) for f in got for s in f.sweeps()]
    with AnyReader([tmp_path / "out" / "bag"]) as reader:
        clouds = [c for c in reader.connections if c.msgtype == "sensor_msgs/msg/PointCloud2"]
        counts = {c.topic: c.msgcount for c in clouds}
        rear = next(c for c in clouds if "rear" in c.topic)
        msg = reader.deserialize(next(reader.messages(connections=[rear]))[2], rear.msgtype)
    assert sum(counts.values()) == len(sweeps)
    assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity", "return_type", "channel"] and msg.point_step == 16
    first_rear = next(s for _, s in sweeps if s.name == "rear")
    assert msg.width * msg.height == len(first_rear.points)
    rec = read_recording(tmp_path / "out" / "run.mcap")
    assert sum(len(v) for v in rec.clouds.values()) == len(sweeps)
    las = sorted((tmp_path / "out" / "frames").rglob("*.las"))
    assert len(las) == len(sweeps)
    idx, s = sweeps[0]
    f0 = laspy.read(next(p for p in las if p.parent.name == s.name and p.name.startswith(f"{idx:06d}_")))
    np.testing.assert_allclose(np.asarray(f0.x), s.points["x"], atol=1e-3)  # LAS stores millimetres


def test_a_frames_scene_takes_context_from_disk_or_a_rendered_world(tmp_path):
    from scube_sim.runs.scenario import FramesSpec

    assert FramesSpec(path="some/drive", dataset="kitti_raw", context=2).context == 2
    assert FramesSpec(world={"style": "urban", "seed": 1}, context=1).context == 1
    assert FramesSpec(path="x").context is None  # the profile's own
    with pytest.raises(ValueError, match="greater than or equal to 0"):
        FramesSpec(path="x", context=-1)
