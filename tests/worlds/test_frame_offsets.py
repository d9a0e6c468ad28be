"""Frame offsets before T (layout version 3): the file-name tags, the config's rule, the ego path
and actor tracks before t = 0, and a tiny sample with context instants written next to one with
the default offsets: the default one is the version-2 layout (names, version, world config), and
the instants both store are the same bytes (a history changes nothing from t = 0)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from scube_sim.camera.rig import load_rig
from scube_sim.worlds.dataset import (
    DATASET_VERSION,
    EVAL_OFFSETS,
    DatasetConfig,
    dataset_version,
    frame_tag,
    make_sample,
    parse_frame_tag,
    sample_world_config,
)
from scube_sim.worlds.generator import WorldConfig, generate_world

TINY = dict(image_scale=0.04, visibility_scale=0.04, fine_voxel_m=0.4, coarse_factor=2, lidar="vlp16")
DEFAULT = DatasetConfig(**TINY)  # the default frame offsets, 0, 5, 10
CONTEXT = DatasetConfig(**TINY, frame_offsets=[-4, -1, 0, 2, 5])
FAST = 1  # train sample 1 is a suburban world: the quickest to make


def test_frame_tags_read_back_one_way():
    assert [frame_tag(k) for k in (0, 1, 5, 10, 123, -1, -4, -12)] == \
        ["00", "01", "05", "10", "123", "m01", "m04", "m12"]
    for k in range(-120, 121):
        tag = frame_tag(k)
        assert parse_frame_tag(tag) == k and "_" not in tag
    for bad in ("5", "m4", "m00", "-04", "x05", "", "m", "005"):
        with pytest.raises(ValueError):
            parse_frame_tag(bad)
    # the tags of one sign sort by magnitude; the two signs never mix
    assert sorted(frame_tag(k) for k in (-8, -4, -2)) == ["m02", "m04", "m08"]
    assert sorted(frame_tag(k) for k in (10, 2, 5)) == ["02", "05", "10"]


def test_config_takes_offsets_before_t_and_every_new_dataset_is_version_4():
    # version 4 (texture version 2) whatever the offsets; 2 and 3 only differed by them
    assert DatasetConfig().frame_offsets == [0, 5, 10] and dataset_version(DatasetConfig()) == 4
    cfg = DatasetConfig(frame_offsets=[-8, -4, -2, -1, 0, 1, 2, 4, 5, 8, 10])
    assert dataset_version(cfg) == DATASET_VERSION == 4
    for bad in ([1, 5], [-2, 5], [0, 5, 5], [5, 0], [0, -1]):
        with pytest.raises(ValueError, match="include 0"):
            DatasetConfig(frame_offsets=bad)
    assert EVAL_OFFSETS == (5, 10)


def test_world_history_only_where_asked():
    # no history: the config dumps as before (no new key), so meta.json's `world` keeps its bytes
    plain = sample_world_config("train", FAST, DEFAULT)
    assert plain.history_s == 0 and "history_s" not in plain.model_dump()
    assert "history_s" not in plain.model_dump_json()
    ctx = sample_world_config("train", FAST, CONTEXT)
    assert ctx.history_s == pytest.approx(0.4 + 0.5)
    assert WorldConfig(**ctx.model_dump()) == ctx
    after = sample_world_config("train", FAST, CONTEXT.model_copy(update={"frame_offsets": [0, 2, 5]}))
    assert ctx.model_copy(update={"history_s": 0.0}) == after  # the same world otherwise


def test_history_extends_the_path_backwards_and_keeps_it_from_zero():
    cfg = WorldConfig(style="urban", seed=5, duration_s=1.0, layout="curved")
    a, b = generate_world(cfg), generate_world(cfg.model_copy(update={"history_s": 1.0}))
    assert b.ego_times[0] == pytest.approx(-1.0) and np.all(np.diff(b.ego_times) > 0)
    assert len(a.actors) == len(b.actors) and np.array_equal(a.static.vertices, b.static.vertices)
    for t in (0.0, 0.03, 0.45, 1.0):  # from t = 0: the same numbers
        assert np.array_equal(a.ego_pose_at(t), b.ego_pose_at(t))
        for x, y in zip(a.actors, b.actors):
            assert np.array_equal(x.pose_at(t), y.pose_at(t))
    # before 0: the same lane at the same speed, heading along the road (a curve here)
    ts = np.arange(-1.0, 0.5, 0.05)
    p = np.array([b.ego_pose_at(t)[:3, 3] for t in ts])
    step = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
    assert np.allclose(step, step[-1], rtol=1e-3) and step[-1] > 0
    yaw = np.array([np.arctan2(b.ego_pose_at(t)[1, 0], b.ego_pose_at(t)[0, 0]) for t in ts])
    assert np.all(np.abs(np.diff(np.unwrap(yaw))) < 0.05)
    main = b.layout.main
    centre = main.at(np.linspace(0.0, main.length, 4000), 0.0)[0]
    dist = [np.min(np.linalg.norm(centre - q[:2], axis=1)) for q in p]
    assert max(dist) < main.half_width  # on the road
    # moving actors move before 0 too (without a history they hold their pose at 0)
    movers = [i for i, x in enumerate(b.actors) if not np.allclose(x.pose_at(0.0), x.pose_at(0.5))]
    assert movers
    for i in movers:
        assert not np.allclose(b.actors[i].pose_at(-0.5), b.actors[i].pose_at(0.0))
        assert np.allclose(a.actors[i].pose_at(-0.5), a.actors[i].pose_at(0.0))


@pytest.fixture(scope="module")
def samples() -> tuple[dict, dict]:
    return make_sample("train", FAST, DEFAULT), make_sample("train", FAST, CONTEXT)


def test_default_offsets_write_the_version_2_file_layout(samples):
    plain, _ = samples
    cams = [c.name for c in load_rig(DEFAULT.rig).cameras]
    assert sorted(plain["images"]) == sorted(f"rgb_{k}_{c}.png" for k in ("00", "05", "10") for c in cams)
    assert sorted(plain["frames"]) == sorted(f"{m}_{k}_{c}" for m in ("depth", "semantic", "instance")
                                             for k in ("00", "05", "10") for c in cams)
    meta = plain["meta"]
    assert meta["version"] == 4 and meta["texture_version"] == 2 and "history_s" not in meta["world"]
    assert [f["offset"] for f in meta["frames"]] == [0, 5, 10]


def test_context_sample_names_instants_by_the_rule_and_keeps_t(samples):
    plain, ctx = samples
    meta = ctx["meta"]
    assert meta["version"] == 4 and meta["world"]["history_s"] == pytest.approx(0.9)
    assert [f["offset"] for f in meta["frames"]] == [-4, -1, 0, 2, 5]
    assert [f["time"] for f in meta["frames"]] == pytest.approx([-0.4, -0.1, 0.0, 0.2, 0.5])
    tags = sorted({name.split("_")[1] for name in ctx["images"]})
    assert tags == ["00", "02", "05", "m01", "m04"]
    assert {parse_frame_tag(t) for t in tags} == set(CONTEXT.frame_offsets)
    # what both store is the same bytes: T, T+5, the voxels and the sweep (waymo-5 fires after T)
    for name in plain["images"]:
        if name.split("_")[1] in ("00", "05"):
            assert np.array_equal(plain["images"][name], ctx["images"][name]), name
    for key in plain["frames"]:
        if key.split("_")[1] in ("00", "05"):
            assert np.array_equal(plain["frames"][key], ctx["frames"][key]), key
    for key in plain["voxels"]:
        assert np.array_equal(plain["voxels"][key], ctx["voxels"][key]), key
    assert np.array_equal(plain["lidar"], ctx["lidar"])
    p_meta = {f["offset"]: f for f in plain["meta"]["frames"]}
    for f in meta["frames"]:
        if f["offset"] in p_meta:
            assert json.dumps(f) == json.dumps(p_meta[f["offset"]])
    assert meta["chunk_to_world"] == plain["meta"]["chunk_to_world"]
    # the instants before T see the ego further back, with their own camera times
    world = generate_world(WorldConfig(**meta["world"]))
    rig = load_rig(CONTEXT.rig)
    for f in meta["frames"]:
        assert np.allclose(f["ego_pose"], world.ego_pose_at(f["time"]))
        assert [c["timestamp"] for c in f["cameras"]] == pytest.approx([f["time"] + c.time_offset_s
                                                                         for c in rig.cameras])
    front_m4 = ctx["images"]["rgb_m04_FRONT.png"]
    assert not np.array_equal(front_m4, ctx["images"]["rgb_00_FRONT.png"])


def test_rendered_context_instants_are_the_datasets_instants():
    """The demo's frames with context (`render_frames_with_context`) hold the images and poses a
    dataset with those frame offsets stores, instant for instant."""
    from scube_sim.worlds.dataset import render_frames_with_context, sample_frames, sample_rig

    cfg = DatasetConfig(**TINY, frame_offsets=[-1, 0, 1])
    sample = make_sample("train", FAST, cfg)
    world = generate_world(sample_world_config("train", FAST, cfg))
    frames = render_frames_with_context(world, sample_rig(FAST, cfg), 1, cfg.image_scale, log="x")
    assert [c.offset for c in frames.context] == [-1, 1] and {c.log for c in frames.context} == {"x"}
    for i, f in enumerate([frames.context[0], frames, frames.context[1]]):
        stored = sample_frames(sample, i)
        assert stored.offset == f.offset
        assert [b.to_json() for b in f.boxes] == sample["meta"]["frames"][i]["boxes"] and f.boxes
        np.testing.assert_allclose(f.ego_pose, stored.ego_pose, atol=1e-9)
        for a, b in zip(f.images, stored.images):
            assert a.name == b.name and a.timestamp == b.timestamp
            np.testing.assert_allclose(a.cam_to_world, b.cam_to_world, atol=1e-9)
            assert np.array_equal(a.image, b.image)


def test_a_held_rig_s_context_instants_move_with_the_ego():
    """A route chunk's rig held off the ego's path (`ego_pose`): its context rigs keep that
    offset from the ego, so between instants they move exactly as the ego does."""
    from scube_sim.transforms import invert_pose
    from scube_sim.worlds.dataset import render_frames_with_context, sample_rig

    cfg = DatasetConfig(**TINY)
    world = generate_world(sample_world_config("train", FAST, cfg))
    t, rate = 1.0, cfg.frame_rate_hz
    held = world.ego_pose_at(t).copy()
    held[:3, 3] += held[:3, 1] * 4.0  # 4 m to the ego's left
    frames = render_frames_with_context(world, sample_rig(FAST, cfg), 1, 0.02, t_ref=t, ego_pose=held)
    np.testing.assert_allclose(frames.ego_pose, held, atol=1e-12)
    assert frames.timestamp == pytest.approx(t)
    for f in frames.context:
        ego_step = world.ego_pose_at(t + f.offset / rate) @ invert_pose(world.ego_pose_at(t))
        np.testing.assert_allclose(f.ego_pose, ego_step @ held, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(f.ego_pose[:3, 3] - held[:3, 3]),
                                   np.linalg.norm(ego_step[:3, 3] + ego_step[:3, :3] @ held[:3, 3] - held[:3, 3]))
