"""Converted scenes in the loop (issue 13): `scene.frames` converts on first use and reuses the
cached conversion; moving actors' voxels are cut out by their boxes (ground under them kept);
a host's Frames become a SimScene; every point says whether it was observed."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from scube_sim.boxes import Box
from scube_sim.cli import app
from scube_sim.converter.frames import open_frames
from scube_sim.converter.pipeline import Converter
from scube_sim.fit import FitOptions, fit_voxsplat
from scube_sim.io.pointcloud import read_pcd
from scube_sim.labels import LABEL_IDS
from scube_sim.lidar.config import ConfigError
from scube_sim.mesh import TriangleMesh
from scube_sim.raytrace.tracer import Tracer
from scube_sim.runs.scenario import load_scenario
from scube_sim.sim.converted import remove_boxes, scene_part, simulated_scene
from scube_sim.sim.scene import Part
from scube_sim.transforms import pose_from_xyz_rpy


def _slab(x0, x1, y0, y1, z0, z1, step=0.1):
    g = np.mgrid[x0:x1:step, y0:y1:step, z0:z1:step].reshape(3, -1).T
    return g + step / 2


def test_remove_boxes_cuts_the_actor_and_keeps_the_ground_under_it():
    """A car-labelled block on a road slab, in a chunk frame rotated and moved in the world; the
    box is given in the world: the car's voxels go, the road's stay, a second car outside stays."""
    road, car, other = _slab(-4, 12, -4, 4, -0.2, 0.0), _slab(1, 5, -1, 1, 0.0, 1.6), _slab(8, 10, -1, 1, 0, 1.6)
    pts = np.concatenate([road, car, other])
    labels = np.concatenate([np.full(len(road), LABEL_IDS["road"]), np.full(len(car), LABEL_IDS["car"]),
                             np.full(len(other), LABEL_IDS["car"])])
    vs = fit_voxsplat(pts, 0.4, labels=labels, fit=FitOptions(gaussians_per_voxel=1))
    c2w = pose_from_xyz_rpy([1000.0, -500.0, 20.0], [0, 0, 90])
    vs.metadata.update({"frame": "chunk", "chunk_to_world": c2w.tolist()})
    vs.set_channel("confidence", np.linspace(0, 1, vs.num_voxels, dtype=np.float32))
    box = Box.on_ground(c2w @ pose_from_xyz_rpy([3.0, 0, 0], [0, 0, 0]), np.array([4.0, 2.0, 1.6]))
    out, removed = remove_boxes(vs, [box])
    centres = vs.voxel_centers()
    is_car = vs.labels == LABEL_IDS["car"]
    in_first = is_car & (centres[:, 0] < 7)
    assert removed == int(in_first.sum()) > 10
    assert out.num_voxels == vs.num_voxels - removed
    assert (out.labels == LABEL_IDS["road"]).sum() == (vs.labels == LABEL_IDS["road"]).sum()
    assert (out.labels == LABEL_IDS["car"]).sum() == (is_car & ~in_first).sum()
    # channels follow their voxels
    np.testing.assert_array_equal(out.channel("confidence"), vs.channel("confidence")[~in_first])
    assert out.metadata["removed_actor_voxels"] == removed and "removed_actor_voxels" not in vs.metadata
    assert remove_boxes(vs, [])[1] == 0


def test_a_chunk_frame_scene_is_placed_by_its_pose_and_traced_in_its_mode():
    wall = fit_voxsplat(_slab(9.9, 10.1, -3, 3, 0, 3, 0.05), 0.2, fit=FitOptions(gaussians_per_voxel=1))
    c2w = pose_from_xyz_rpy([100.0, 50.0, 0.0], [0, 0, 90])  # the chunk's x is the world's y
    wall.metadata.update({"frame": "chunk", "chunk_to_world": c2w.tolist(), "trace_mode": "soft"})
    part = scene_part(wall)
    assert part.tracer.mode.name == "soft"
    np.testing.assert_array_equal(part.pose, c2w)
    from scube_sim.sim.scene import SimScene

    h = SimScene(static=[part]).trace_world(np.array([[100.0, 50.0, 1.5]]), np.array([[0.0, 1.0, 0.0]]))
    assert h.hit[0] and h.t[0] == pytest.approx(9.9, abs=0.15)


def test_scene_frames_validation_names_the_key(tmp_path):
    base = {"name": "x", "sensors": [{"preset": "vlp16"}], "trajectory": {"source": "world"}}
    for frames, why in (({}, "exactly one of path"), ({"path": "a", "world": {"seed": 1}}, "exactly one of path")):
        p = tmp_path / "s.yaml"
        p.write_text(yaml.safe_dump({**base, "scene": {"frames": frames}}))
        with pytest.raises(ConfigError, match=why) as e:
            load_scenario(p)
        assert "scene.frames" in str(e.value)
    p.write_text(yaml.safe_dump({**base, "scene": {"frames": "some/sample"}}))
    assert load_scenario(p)[0].scene.frames.path == "some/sample"  # the shorthand


def test_host_frames_become_a_simulated_scene_with_the_actor_cut_out(tiny_converter):
    import scube_sim

    frames = open_frames(tiny_converter["sample"])
    # the tiny model predicts terrain only: make its first voxel a car the actor stands in
    plain = scube_sim.convert(frames, profile=tiny_converter["profile"], sky=False)
    plain.labels[0] = LABEL_IDS["car"]
    c2w = np.asarray(plain.metadata["chunk_to_world"])
    centre = c2w[:3, :3] @ (plain.voxel_centers()[0] + plain.origin) + c2w[:3, 3]
    mesh = TriangleMesh(np.array([[0, 0, 0.0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]))
    pose = c2w.copy()
    pose[:3, 3] = centre - c2w[:3, 2] * 0.5  # the box's footprint half a metre under the voxel centre
    actor = Part(Tracer(mesh), pose_fn=lambda t, p=pose: np.repeat(p[None], len(np.atleast_1d(t)), 0), instance=9,
                 label=LABEL_IDS["car"], size=np.array([1.0, 1.0, 1.0]))
    scene, vs = simulated_scene(frames, plain, actors=[actor])
    assert scene.actors == [actor] and scene.has_provenance
    # the car voxel is gone; the terrain voxels beside it (inside the grown box too) stay
    assert vs.metadata["removed_actor_voxels"] == 1 and vs.num_voxels == plain.num_voxels - 1
    assert (vs.labels == LABEL_IDS["car"]).sum() == 0
    np.testing.assert_array_equal(vs.ijk, plain.ijk[1:])


def test_replay_converts_frames_once_and_points_carry_observed_and_confidence(tiny_converter, tmp_path, monkeypatch):
    scen = tmp_path / "conv.yaml"
    scen.write_text(yaml.safe_dump({
        "name": "conv", "duration_s": 0.2, "tick_hz": 10,
        "scene": {"frames": {"path": str(tiny_converter["sample"]), "profile": str(tiny_converter["profile"])}},
        "trajectory": {"source": "file", "file": str(_held_trajectory(tmp_path, tiny_converter))},
        "sensors": [{"preset": "vlp16"}], "outputs": {"files": ["pcd"], "usd": None}}))
    r = CliRunner().invoke(app, ["replay", str(scen), "-o", str(tmp_path / "r1")])
    assert r.exit_code == 0, r.output
    cached = tmp_path / "r1" / "scene_chunks" / "converted.npz"
    assert cached.is_file()
    pcds = sorted((tmp_path / "r1" / "frames").rglob("*.pcd"))
    p = read_pcd(pcds[0])
    assert {"observed", "confidence"} <= set(p.dtype.names) and len(p) > 100
    assert set(np.unique(p["observed"])) <= {0, 1} and ((p["confidence"] > 0) & (p["confidence"] <= 1)).all()
    # a rerun into the same folder reuses the conversion: the converter is not called
    monkeypatch.setattr(Converter, "convert", lambda *a, **k: pytest.fail("converted twice"))
    before = cached.read_bytes()
    r = CliRunner().invoke(app, ["replay", str(scen), "-o", str(tmp_path / "r1"), "--overwrite"])
    assert r.exit_code == 0, r.output
    assert cached.read_bytes() == before


def _held_trajectory(tmp_path, tiny_converter):
    """An .npz trajectory (times, poses) holding the ego at the frames' pose for a second."""
    frames = open_frames(tiny_converter["sample"])
    path = tmp_path / "poses.npz"
    np.savez(path, times=np.array([0.0, 1.0]), poses=np.stack([frames.ego_pose, frames.ego_pose]))
    return path



def test_a_route_converts_one_chunk_per_stop_from_the_rig_held_at_its_origin(tiny_converter, tmp_path):
    from scube_sim.runs.scenario import build_scene, route_stops
    from scube_sim.worlds.generator import WorldConfig, generate_world
    from scube_sim.worlds.groundtruth import chunk_frames

    # the ego drives 120 m: past both chunk origins (20 m and 116 m along the road)
    world = {"style": "suburban", "seed": 3, "layout": "straight", "length_m": 220, "duration_s": 12,
             "ego_speed_mps": 10}
    scen = tmp_path / "route.yaml"
    scen.write_text(yaml.safe_dump({
        "name": "route", "duration_s": 0.2,
        "scene": {"frames": {"world": world, "route": True, "profile": str(tiny_converter["profile"])}},
        "trajectory": {"source": "world"}, "sensors": [{"preset": "vlp16"}]}))
    sc, base = load_scenario(scen)
    built = build_scene(sc, base, tmp_path / "out" / "scene_chunks", reach=100.0)
    specs = built.scene.chunks.chunks
    w = generate_world(WorldConfig(**{**world, "duration_s": built.world.config.duration_s}))
    poses = chunk_frames(w, sc.scene.chunk_spacing_m)
    assert len(specs) == len(poses) == 2
    for spec, pose in zip(specs, poses):
        np.testing.assert_allclose(spec.chunk_to_world, pose, atol=1e-9)
        assert spec.path.is_file()
    stops = route_stops(w, sc.scene.chunk_spacing_m)
    # each stop's instant is when the ego is nearest the chunk origin: within half a tick's travel
    for t, pose in stops:
        assert np.linalg.norm(w.ego_pose_at(t)[:2, 3] - pose[:2, 3]) < 2.0
    assert stops[0][0] < stops[1][0]
    for i in range(2):
        assert (tmp_path / "out" / "scene_chunks" / f"converted_{i:03d}.npz").is_file()
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"name": "b", "scene": {"frames": {"path": "x", "route": True}},
                                   "sensors": [{"preset": "vlp16"}]}))
    with pytest.raises(ConfigError, match="route: needs world"):
        load_scenario(bad)


def test_scene_soft_alpha_min_reaches_the_tracer_and_drops_fainter_contributions(tmp_path):
    """`scene.soft_alpha_min`: three layers of Gaussians of opacity 0.3 composite to about 0.66
    (a return at the tracer's default floor); with the floor at 0.35 each is dropped (no return)."""
    from scube_sim.runs.scenario import build_scene
    from scube_sim.sim.scene import SimScene

    slab = fit_voxsplat(_slab(9.8, 10.4, -3, 3, 0, 3, 0.05), 0.2, fit=FitOptions(gaussians_per_voxel=1))
    slab.params[..., 3] = np.log(0.3 / 0.7)  # raw opacity: sigmoid -> 0.3
    slab.metadata.update({"trace_mode": "soft"})
    slab.save(tmp_path / "slab.npz")
    base = {"name": "x", "sensors": [{"preset": "vlp16"}], "trajectory": {"source": "world"}}
    o, d = np.array([[0.0, 0.1, 1.5]]), np.array([[1.0, 0.0, 0.0]])
    hits = {}
    for floor in (None, 0.35):
        scene = {"voxsplat": str(tmp_path / "slab.npz"), **({"soft_alpha_min": floor} if floor else {})}
        p = tmp_path / "s.yaml"
        p.write_text(yaml.safe_dump({**base, "scene": scene}))
        sc, where = load_scenario(p)
        built = build_scene(sc, where, tmp_path / "cache", reach=200.0)
        part = built.scene.static[0]
        assert part.tracer.mode.alpha_min == (floor or 1.0 / 255.0)
        hits[floor] = SimScene(static=[part]).trace_world(o, d)
    assert hits[None].hit[0] and hits[None].t[0] == pytest.approx(10.0, abs=0.5)
    assert not hits[0.35].hit[0]
    p.write_text(yaml.safe_dump({**base, "scene": {"voxsplat": "x.npz", "soft_alpha_min": 1.5}}))
    with pytest.raises(ConfigError, match="soft_alpha_min"):
        load_scenario(p)
