"""UsdSink: one animated stage per run, flat or with value clips, read back through pxr."""

from __future__ import annotations

import math
import os
import weakref

import numpy as np
import pytest

pytest.importorskip("pxr")
from pxr import Sdf, Usd, UsdGeom, UsdVol  # noqa: E402

from scube_sim.lidar.model import POINT_DTYPE  # noqa: E402
from scube_sim.sim.frame import Frame, SensorFrame  # noqa: E402
from scube_sim.sim.sinks import CallbackSink, RunInfo, SinkError, SinkRunner, UsdSink  # noqa: E402
from scube_sim.sim.sinks.usd import EGO_PATH, POINTS_NAME, SCENE_PATH, SENSORS_PATH  # noqa: E402
from scube_sim.transforms import pose_from_xyz_rpy, transform_points  # noqa: E402
from scube_sim.voxsplat import Gaussians, VoxSplat  # noqa: E402

FAR = np.array([1.0e6 + 0.123, -1.0e6 + 0.456, 35.789])  # world origin far from 0
START = 12.5  # host seconds at time code 0
TCPS = 100.0
TICK = 0.05  # 20 Hz ticks
RATES = {"top": 10.0, "front-left": 30.0}  # slower (no sweep every other tick) and faster than the ticks
PRIM = {"top": "top", "front-left": "front_left"}
PRIMVARS = ("intensity", "ring", "label", "time", "instance")
MOUNTS = {"top": pose_from_xyz_rpy([0.5, 0, 1.8], [0, 0, 0]),
          "front-left": pose_from_xyz_rpy([2.0, 0.7, 0.6], [0, 5, 30])}


def ego_pose(t: float) -> np.ndarray:
    return pose_from_xyz_rpy(FAR + [8.0 * t, 0.5 * t * t, 0.01 * t], [0.3 * t, 0.0, 20.0 * t])


def make_points(rng, n: int) -> np.ndarray:
    p = np.zeros(n, POINT_DTYPE)
    for f in ("x", "y", "z"):
        p[f] = rng.normal(0, 30, n)
    p["intensity"] = rng.random(n)
    p["ring"] = rng.integers(0, 128, n)
    p["time"] = rng.random(n) * 0.1
    p["label"] = rng.integers(-1, 26, n)
    p["instance"] = rng.integers(0, 1 << 20, n)
    p["return_id"] = rng.integers(0, 2, n)
    return p


def make_frames(rng, n_ticks: int = 24, empty_sweep: bool = True) -> list[Frame]:
    """Ticks at 20 Hz; 'top' at 10 Hz (none every other tick), 'front-left' at 30 Hz (one or two
    per tick); varying point counts, one sweep with no points, one tick with an explicit empty list."""
    frames, sweep_no = [], {s: 0 for s in RATES}
    for i in range(n_ticks):
        t = START + TICK * (i + 1)
        sensors = {}
        for name, rate in RATES.items():
            group = []
            while START + (sweep_no[name] + 1) / rate <= t + 1e-12:
                k = sweep_no[name]
                t_end = START + (k + 1) / rate
                t_start, t_ref = t_end - 1 / rate, t_end - 0.5 / rate
                n = 0 if (empty_sweep and name == "top" and k == 3) else int(rng.integers(50, 400))
                group.append(SensorFrame(name, "lidar", make_points(rng, n), t_start, t_end, t_ref,
                                         ego_pose(t_ref) @ MOUNTS[name], ego_pose(t_start) @ MOUNTS[name],
                                         ego_pose(t_end) @ MOUNTS[name], k))
                sweep_no[name] += 1
            if group or name == "top":
                sensors[name] = group  # 'top' gets an explicit [] on its empty ticks
        frames.append(Frame(i, t, ego_pose(t), sensors))
    assert any(f.sensors["top"] == [] for f in frames) and any(len(f.sensors["front-left"]) == 2 for f in frames)
    return frames


def run_info(scene=None) -> RunInfo:
    sensors = {name: {"kind": "lidar", "rate_hz": r, "mount": MOUNTS[name]} for name, r in RATES.items()}
    sensors["cam"] = {"kind": "camera"}
    return RunInfo(sensors=sensors, scene=scene, origin=FAR.copy(), time_codes_per_second=TCPS, start_time=START)


def run_through(frames, sink: UsdSink, run: RunInfo, fail_after: int | None = None) -> list[Frame]:
    """The frames through a SinkRunner with [sink, callback]; returns what the callback received
    (with fail_after=k the callback raises on the k-th frame, after the sink wrote it)."""
    got = []

    def collect(frame):
        got.append(frame)
        if fail_after is not None and len(got) == fail_after:
            raise RuntimeError("interrupted")

    runner = SinkRunner([sink, CallbackSink(collect)], run, maxsize=2)
    runner.start()
    try:
        for f in frames:
            runner.put(f)
    finally:
        runner.close()
    return got


def tc(t: float) -> float:
    return (t - START) * TCPS


def matrix(attr, time) -> np.ndarray:
    m = attr.Get(time)
    assert type(m).__name__ == "Matrix4d"
    return np.array(m, dtype=np.float64).T  # Gf is row-vector: the transpose is our pose


def validation_errors(stage) -> list[str]:
    from pxr import UsdValidation  # usd-core 26.11: no UsdUtils.ComplianceChecker

    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    return [f"{e.GetType()} {e.GetName()}: {e.GetMessage()}" for e in errors]


def check_stage(stage, frames: list[Frame]) -> None:
    """Every sample of the stage equals the frames, bit for bit; nothing else is sampled."""
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == "/World"
    assert stage.GetTimeCodesPerSecond() == TCPS
    assert stage.GetRootLayer().customLayerData["scube_sim:startTime"] == START

    ego = UsdGeom.Xform(stage.GetPrimAtPath(EGO_PATH))
    ops = ego.GetOrderedXformOps()
    assert [o.GetOpName() for o in ops] == ["xformOp:transform"]
    assert ops[0].GetPrecision() == UsdGeom.XformOp.PrecisionDouble
    assert ops[0].GetAttr().GetTimeSamples() == [tc(f.time) for f in frames]
    for f in frames:
        np.testing.assert_array_equal(matrix(ops[0].GetAttr(), tc(f.time)), f.ego_pose)
        assert ego.GetPrim().GetAttribute("scube_sim:frameIndex").Get(tc(f.time)) == f.index
    all_tc = [tc(f.time) for f in frames]

    for name, prim_name in PRIM.items():
        sweeps = [s for f in frames for s in f.sensors.get(name, [])]
        times = [tc(s.t_end) for s in sweeps]
        all_tc += times
        xf = stage.GetPrimAtPath(f"{SENSORS_PATH}/{prim_name}")
        pts = UsdGeom.Points(stage.GetPrimAtPath(f"{SENSORS_PATH}/{prim_name}/{POINTS_NAME}"))
        assert xf.IsA(UsdGeom.Xform) and pts
        assert pts.GetWidthsInterpolation() == UsdGeom.Tokens.constant and not pts.GetWidthsAttr().GetNumTimeSamples()
        xop = UsdGeom.Xform(xf).GetOrderedXformOps()[0]
        assert xop.GetPrecision() == UsdGeom.XformOp.PrecisionDouble
        pv = UsdGeom.PrimvarsAPI(pts.GetPrim())
        for attr in [xop.GetAttr(), pts.GetPointsAttr(), pts.GetExtentAttr()] + [pv.GetPrimvar(f).GetAttr()
                                                                                  for f in PRIMVARS]:
            assert attr.GetTimeSamples() == times, attr.GetPath()
        for s, t in zip(sweeps, times):
            np.testing.assert_array_equal(matrix(xop.GetAttr(), t), s.pose)  # float64, exact
            assert xf.GetAttribute("scube_sim:tRef").Get(t) == s.t_ref
            assert xf.GetAttribute("scube_sim:tStart").Get(t) == s.t_start
            assert xf.GetAttribute("scube_sim:sweepIndex").Get(t) == s.sweep_index
            got = np.asarray(pts.GetPointsAttr().Get(t))
            want = np.stack([s.points["x"], s.points["y"], s.points["z"]], axis=1)
            assert got.dtype == np.float32 and got.shape == (len(s.points), 3)
            np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))  # bit for bit
            for f in PRIMVARS:
                p = pv.GetPrimvar(f)
                assert p.GetInterpolation() == UsdGeom.Tokens.vertex
                value = np.asarray(p.Get(t))
                assert value.shape == (len(s.points),)
                if s.points.dtype[f].kind == "f":
                    assert value.dtype == np.float32
                    np.testing.assert_array_equal(value.view(np.uint32), s.points[f].view(np.uint32))
                else:  # integers widened exactly (USD has no int16 / uint16)
                    np.testing.assert_array_equal(value, s.points[f].astype(np.int64), err_msg=f)
            ext = np.asarray(pts.GetExtentAttr().Get(t))
            if len(got):
                assert np.all(ext[0] <= got.min(0)) and np.all(ext[1] >= got.max(0))
    assert stage.GetStartTimeCode() == min(all_tc) and stage.GetEndTimeCode() == max(all_tc)
    assert not stage.GetPrimAtPath(f"{SENSORS_PATH}/cam")  # cameras are not LiDAR tracks


def same_samples(a, b) -> None:
    """Every attribute of stage `a` has the same time samples and values in `b`."""
    n = 0
    for prim in a.Traverse():
        for attr in prim.GetAttributes():
            other = b.GetAttributeAtPath(attr.GetPath())
            assert other, attr.GetPath()
            times = attr.GetTimeSamples()
            assert other.GetTimeSamples() == times, attr.GetPath()
            for t in times:
                va, vb = attr.Get(t), other.Get(t)
                if hasattr(va, "__len__") and not isinstance(va, str) and type(va).__name__.endswith("Array"):
                    np.testing.assert_array_equal(np.asarray(va), np.asarray(vb))
                else:
                    assert va == vb, (attr.GetPath(), t)
                n += 1
    assert n > 100


@pytest.fixture
def frames(rng) -> list[Frame]:
    return make_frames(rng)


@pytest.fixture
def voxsplat(rng) -> VoxSplat:
    n = 60
    g = Gaussians(means=rng.uniform(-20, 20, (n, 3)), scales=rng.uniform(0.01, 0.3, (n, 3)),
                  quats=rng.normal(size=(n, 4)), opacities=rng.uniform(0.01, 0.99, n),
                  sh_dc=rng.normal(size=(n, 3)).astype(np.float32), origin=FAR.copy())
    return VoxSplat.from_gaussians(g, 0.5, labels=rng.integers(0, 26, n))


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_flat_stage_matches_frames(tmp_path, frames, voxsplat, suffix):
    sink = UsdSink(tmp_path / f"run{suffix}")
    got = run_through(frames, sink, run_info(voxsplat))
    assert len(got) == len(frames)
    assert sorted(os.listdir(tmp_path)) == [f"run{suffix}"]  # no temporaries, no clips
    stage = Usd.Stage.Open(str(tmp_path / f"run{suffix}"))
    check_stage(stage, got)
    scene = UsdVol.ParticleField3DGaussianSplat(stage.GetPrimAtPath(SCENE_PATH))
    assert scene and len(scene.GetPositionsAttr().Get()) == voxsplat.num_gaussians
    assert not scene.GetPositionsAttr().GetNumTimeSamples()  # static
    assert validation_errors(stage) == []


@pytest.mark.parametrize("frames_per_clip", [1, 5])
def test_clips_compose_to_the_flat_stage(tmp_path, frames, frames_per_clip):
    flat = UsdSink(tmp_path / "flat.usdc", write_scene=False)
    run_through(frames, flat, run_info())
    sink = UsdSink(tmp_path / "clip.usda", clips=True, frames_per_clip=frames_per_clip, write_scene=False)
    got = run_through(frames, sink, run_info())

    n_clips = math.ceil(len(frames) / frames_per_clip)
    clip_dir = tmp_path / "clip_clips"
    assert sorted(os.listdir(clip_dir)) == sorted([f"clip_{k:05d}.usdc" for k in range(n_clips)] + ["manifest.usda"])
    assert sink.clip_paths == [clip_dir / f"clip_{k:05d}.usdc" for k in range(n_clips)]
    root = Sdf.Layer.OpenAsAnonymous(str(tmp_path / "clip.usda"))
    assert root.ListAllTimeSamples() == []  # the root holds no samples, only clip metadata
    stage = Usd.Stage.Open(str(tmp_path / "clip.usda"))
    clips = Usd.ClipsAPI(stage.GetPrimAtPath(f"{SENSORS_PATH}/top")).GetClips()["default"]
    top_chunks = {i // frames_per_clip for i, f in enumerate(frames) if f.sensors.get("top")}
    assert len(clips["assetPaths"]) == len(top_chunks)  # only the chunks where 'top' has sweeps
    assert clips["primPath"] == f"{SENSORS_PATH}/top"
    assert clips["manifestAssetPath"].path == "./clip_clips/manifest.usda"

    src = stage.GetAttributeAtPath(f"{SENSORS_PATH}/top/{POINTS_NAME}.points").GetResolveInfo(
        stage.GetEndTimeCode()).GetSource()
    assert src == Usd.ResolveInfoSourceValueClips
    check_stage(stage, got)
    same_samples(Usd.Stage.Open(str(tmp_path / "flat.usdc")), stage)
    assert validation_errors(stage) == []


def test_sensor_appearing_mid_chunk(tmp_path, frames):
    """A sensor not announced in RunInfo and first seen inside a chunk: declared in that chunk and
    the manifest; the clip stage still composes to the flat one."""
    for f in frames[:7]:
        f.sensors.pop("front-left", None)
    run = RunInfo(time_codes_per_second=TCPS, start_time=START)
    run_through(frames, UsdSink(tmp_path / "flat.usda"), run)
    sink = UsdSink(tmp_path / "clip.usdc", clips=True, frames_per_clip=5)
    got = run_through(frames, sink, run)
    stage = Usd.Stage.Open(str(tmp_path / "clip.usdc"))
    check_stage(stage, got)
    same_samples(Usd.Stage.Open(str(tmp_path / "flat.usda")), stage)
    clips = Usd.ClipsAPI(stage.GetPrimAtPath(f"{SENSORS_PATH}/front_left")).GetClips()["default"]
    assert [a.path for a in clips["assetPaths"]] == [f"./clip_clips/clip_{k:05d}.usdc" for k in range(1, 5)]
    assert validation_errors(stage) == []


@pytest.mark.parametrize("clips", [False, True])
def test_interruption_leaves_a_stage_of_the_written_frames(tmp_path, frames, clips):
    k = 11
    sink = UsdSink(tmp_path / "run.usdc", clips=clips, frames_per_clip=4)
    with pytest.raises(SinkError, match="interrupted"):
        run_through(frames, sink, run_info(), fail_after=k)
    assert sink.frames_written == k
    stage = Usd.Stage.Open(str(tmp_path / "run.usdc"))
    check_stage(stage, frames[:k])  # exactly the written frames, nothing more
    assert stage.GetEndTimeCode() == tc(frames[k - 1].time)
    if clips:
        assert len(sink.clip_paths) == math.ceil(k / 4)  # the partial chunk written by close()
    names = os.listdir(tmp_path) + (os.listdir(tmp_path / "run_clips") if clips else [])
    assert not [n for n in names if "tmp" in n]


def test_far_origin_keeps_millimetres(tmp_path, rng):
    t = START + 0.1
    pose = pose_from_xyz_rpy([3.0e6 + 0.1234, -1.0e6 - 0.5678, 12.3456], [1.0, -2.0, 123.0])
    p = make_points(rng, 200)
    frame = Frame(0, t, pose, {"top": [SensorFrame("top", "lidar", p, t - 0.1, t, t, pose, pose, pose, 0)]})
    sink = UsdSink(tmp_path / "far.usda")
    run_through([frame], sink, RunInfo(time_codes_per_second=TCPS, start_time=START))
    stage = Usd.Stage.Open(str(tmp_path / "far.usda"))
    prim = stage.GetPrimAtPath(f"{SENSORS_PATH}/top/{POINTS_NAME}")
    local = np.asarray(UsdGeom.Points(prim).GetPointsAttr().Get(tc(t))).astype(np.float64)
    m = np.array(UsdGeom.XformCache(Usd.TimeCode(tc(t))).GetLocalToWorldTransform(prim), np.float64)
    world = local @ m[:3, :3] + m[3, :3]  # row-vector convention, double precision
    want = transform_points(pose, np.stack([p["x"], p["y"], p["z"]], 1).astype(np.float64))
    np.testing.assert_allclose(world, want, rtol=0, atol=1e-6)  # far below a millimetre
    # float32 world coordinates would have lost it: the spacing of float32 at 3e6 m is 0.25 m
    assert np.abs(want.astype(np.float32).astype(np.float64) - want).max() > 1e-3


def test_clips_memory_stays_bounded(tmp_path, rng):
    """300 frames of 20k points in clips of 25: the sink holds at most one chunk (no frames,
    no point arrays kept), and at most one in-memory clip layer exists at any time."""
    n_frames, n_points, per_clip = 300, 20_000, 25
    base = make_points(rng, n_points)
    sink = UsdSink(tmp_path / "long.usdc", clips=True, frames_per_clip=per_clip, write_scene=False)
    sink.open(RunInfo(time_codes_per_second=TCPS, start_time=START))
    alive, max_frames, max_samples, max_layers = [], 0, 0, 0
    for i in range(n_frames):
        t = START + 0.1 * (i + 1)
        pts = base.copy()
        pts["x"] += np.float32(i)
        alive.append(weakref.ref(pts))
        pose = ego_pose(t)
        sink.write(Frame(i, t, pose, {"top": [SensorFrame("top", "lidar", pts, t - 0.1, t, t, pose, pose, pose, i)]}))
        del pts
        max_frames = max(max_frames, sink.held_frames)
        max_samples = max(max_samples, sink.held_samples)
        max_layers = max(max_layers, sum("scube_sim_clip" in layer.identifier for layer in Sdf.Layer.GetLoadedLayers()))
        if i == 2 * per_clip - 1:  # a completed clip is on disk with a root that covers it
            assert Usd.Stage.Open(str(tmp_path / "long.usdc")).GetEndTimeCode() == tc(t)
    sink.close()
    # a chunk is written (and dropped) by the write that completes it
    assert max_frames == per_clip - 1 and max_samples == (per_clip - 1) * (2 + 4 + 2 + len(PRIMVARS))
    assert max_layers == 1
    assert sum(r() is not None for r in alive) == 0  # no point array kept
    assert len(sink.clip_paths) == n_frames // per_clip
    stage = Usd.Stage.Open(str(tmp_path / "long.usdc"))
    attr = stage.GetAttributeAtPath(f"{SENSORS_PATH}/top/{POINTS_NAME}.points")
    assert attr.GetNumTimeSamples() == n_frames
    t_last = tc(START + 0.1 * n_frames)
    assert stage.GetEndTimeCode() == t_last
    np.testing.assert_array_equal(np.asarray(attr.Get(t_last))[:, 0], base["x"] + np.float32(n_frames - 1))


def test_bad_input(tmp_path, frames):
    with pytest.raises(ValueError, match="unknown USD suffix"):
        UsdSink(tmp_path / "a.usdz")
    with pytest.raises(ValueError, match="frames_per_clip"):
        UsdSink(tmp_path / "a.usda", clips=True, frames_per_clip=0)
    with pytest.raises(ValueError, match="not LiDAR point fields"):
        UsdSink(tmp_path / "a.usda", primvars=("intensity", "colour"))
    sink = UsdSink(tmp_path / "a.usda")
    with pytest.raises(SinkError, match="not after the previous sample"):
        run_through([frames[1], frames[0]], sink, run_info())
    stage = Usd.Stage.Open(str(tmp_path / "a.usda"))  # still closed cleanly: frames[1] only
    assert stage.GetEndTimeCode() == tc(frames[1].time)
