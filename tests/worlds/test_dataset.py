"""The dataset writer against round trips (in-memory sample -> files -> load_sample), byte
comparisons of two independent runs, file-system state around an interrupted run, and geometric
checks of the ground truth (the road under the ego, depth maps landing in occupied voxels)."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from scube_sim.camera.model import Intrinsics
from scube_sim.camera.rig import load_rig
from scube_sim.cli import app
from scube_sim.labels import LABEL_NAMES, label_id
from scube_sim.lidar import POINT_DTYPE
from scube_sim.transforms import invert_pose
from scube_sim.worlds import dataset as ds_mod
from scube_sim.worlds.dataset import (
    DatasetConfig,
    ensure_dataset_config,
    generate_dataset,
    load_sample,
    make_sample,
    sample_world_config,
    write_sample,
)
from scube_sim.worlds.generator import generate_world
from scube_sim.worlds.groundtruth import CHUNK_CORNER, CHUNK_SIZE, depth_to_points

CFG = DatasetConfig(image_scale=0.04, visibility_scale=0.04, fine_voxel_m=0.4, coarse_factor=2,
                    frame_offsets=[0, 5], lidar="vlp16")
ROAD, LANE = label_id("road"), label_id("lane_marker")
FAST = 1  # index 1 is a suburban world: the quickest to make


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory) -> Path:
    """train samples 0 and 1, written by one generate_dataset run."""
    out = tmp_path_factory.mktemp("ds")
    res = generate_dataset(out, "train", 2, CFG, progress=False)
    assert res["written"] == 2 and res["skipped"] == 0 and res["seconds_per_sample"] > 0
    return out


@pytest.fixture(scope="module")
def fast_sample() -> dict:
    """train sample FAST made in memory, independently of the dataset run."""
    return make_sample("train", FAST, CFG)


def files_of(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# --- determinism -----------------------------------------------------------------------------------


def test_same_sample_twice_gives_the_same_files(dataset_dir, fast_sample, tmp_path):
    """The dataset run's sample and an independent one (another process state, later) agree byte
    for byte in every file."""
    a = files_of(dataset_dir / "train" / f"{FAST:06d}")
    # the dataset run's folder also holds its run manifest, whose checksums are those of the files
    manifest = json.loads(a.pop("manifest.json"))
    assert manifest["status"] == "complete"
    assert manifest["outputs"] == {k: {"sha256": hashlib.sha256(v).hexdigest(), "bytes": len(v)} for k, v in a.items()}
    write_sample(fast_sample, tmp_path / f"{FAST:06d}")
    b = files_of(tmp_path / f"{FAST:06d}")
    assert a.keys() == b.keys()
    assert {"meta.json", "frames.npz", "voxels.npz", "lidar.npz"} <= a.keys()
    assert sum(k.endswith(".png") for k in a) == 5 * len(CFG.frame_offsets)
    for name in a:
        assert a[name] == b[name], f"{name} differs"


def test_same_sample_written_twice_is_byte_identical(tmp_path, monkeypatch):
    write_sample(make_sample("train", FAST, CFG), tmp_path / "a" / "000001")
    real = ds_mod.generate_world

    def slower(cfg):
        time.sleep(0.05)
        return real(cfg)

    monkeypatch.setattr(ds_mod, "generate_world", slower)
    write_sample(make_sample("train", FAST, CFG), tmp_path / "b" / "000001")
    a, b = files_of(tmp_path / "a" / "000001"), files_of(tmp_path / "b" / "000001")
    assert a.keys() == b.keys()
    differ = [k for k in a if a[k] != b[k]]
    assert not differ, f"files differ: {differ}"


# --- round trip --------------------------------------------------------------------------------------


def test_load_sample_round_trip(dataset_dir, fast_sample):
    got = load_sample(dataset_dir / "train" / f"{FAST:06d}")
    assert set(got) == {"meta", "images", "frames", "voxels", "lidar"}
    # images: every camera of every frame, at the scaled size the meta records
    rig = load_rig(CFG.rig)
    names = {f"rgb_{k:02d}_{c.name}.png" for k in CFG.frame_offsets for c in rig.cameras}
    assert set(got["images"]) == names == set(fast_sample["images"])
    for fr in got["meta"]["frames"]:
        for cam in fr["cameras"]:
            img = got["images"][f"rgb_{fr['offset']:02d}_{cam['name']}.png"]
            intr = cam["intrinsics"]
            assert img.shape == (intr["height"], intr["width"], 3) and img.dtype == np.uint8
            full = rig.camera(cam["name"])
            assert intr["width"] == max(1, round(full.width * CFG.image_scale))
            d = got["frames"][f"depth_{fr['offset']:02d}_{cam['name']}"]
            s = got["frames"][f"semantic_{fr['offset']:02d}_{cam['name']}"]
            assert d.shape == s.shape == img.shape[:2] and d.dtype == np.float16 and s.dtype == np.uint8
    for name, img in fast_sample["images"].items():
        np.testing.assert_array_equal(got["images"][name], img)
    assert got["frames"].keys() == fast_sample["frames"].keys()
    for k, v in fast_sample["frames"].items():
        np.testing.assert_array_equal(got["frames"][k], v)
    # voxels: both levels, documented dtypes
    for level in ("fine", "coarse"):
        assert got["voxels"][f"{level}_ijk"].dtype == np.int16 and got["voxels"][f"{level}_ijk"].shape[1] == 3
        assert got["voxels"][f"{level}_labels"].dtype == np.uint8
        assert got["voxels"][f"{level}_visible"].dtype == bool
        n = got["meta"]["voxels"][level]
        assert len(got["voxels"][f"{level}_labels"]) == len(got["voxels"][f"{level}_ijk"]) == n
    assert float(got["voxels"]["fine_voxel_size"]) == CFG.fine_voxel_m
    assert float(got["voxels"]["coarse_voxel_size"]) == pytest.approx(CFG.fine_voxel_m * CFG.coarse_factor)
    for k, v in fast_sample["voxels"].items():
        np.testing.assert_array_equal(got["voxels"][k], v)
    # LiDAR: the documented point record
    assert got["lidar"].dtype == POINT_DTYPE and len(got["lidar"]) > 1000
    np.testing.assert_array_equal(got["lidar"], fast_sample["lidar"])
    assert np.all(got["lidar"]["range"] > 0) and np.all(got["lidar"]["ring"] < 16)
    # meta
    meta = got["meta"]
    for key in ("format", "version", "split", "index", "world", "world_version", "layout", "chunk_to_world",
                "sun_dir", "frames", "lidar", "voxels"):
        assert key in meta, key
    assert (meta["split"], meta["index"]) == ("train", FAST)
    assert [f["offset"] for f in meta["frames"]] == CFG.frame_offsets
    for fr in meta["frames"]:
        assert fr["time"] == pytest.approx(fr["offset"] / CFG.frame_rate_hz)
        for cam in fr["cameras"]:
            assert cam["timestamp"] == pytest.approx(fr["time"] + rig.camera(cam["name"]).time_offset_s)
            assert np.asarray(cam["cam_to_world"]).shape == (4, 4)
        for b in fr["boxes"]:
            assert set(b) == {"instance", "label", "center", "size", "yaw"}
    assert meta["lidar"]["sensor"] == "vlp16"
    np.testing.assert_allclose(meta["chunk_to_world"], meta["frames"][0]["ego_pose"])


def test_load_sample_rejects_incomplete_and_foreign_folders(tmp_path, dataset_dir):
    with pytest.raises(FileNotFoundError, match="meta.json"):
        load_sample(tmp_path)
    f = tmp_path / "x"
    shutil.copytree(dataset_dir / "train" / "000001", f)
    meta = json.loads((f / "meta.json").read_text())
    meta["version"] = 999
    (f / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="meta.json"):
        load_sample(f)


def test_dataset_header(dataset_dir):
    head = json.loads((dataset_dir / "dataset.json").read_text())
    assert head["format"] == "scube_sim.worlds"
    assert DatasetConfig.model_validate(head["config"]) == CFG
    assert head["labels"] == list(LABEL_NAMES)
    assert head["rig"]["name"] == CFG.rig
    assert [r["name"] for r in head["rigs"]] == CFG.rigs
    assert ensure_dataset_config(dataset_dir, None) == CFG
    assert ensure_dataset_config(dataset_dir, CFG.model_copy()) == CFG


# --- resuming ----------------------------------------------------------------------------------------


def test_rerun_writes_only_the_missing_sample_and_clears_stale_temporaries(dataset_dir, tmp_path):
    out = tmp_path / "ds"
    shutil.copytree(dataset_dir, out)
    keep = out / "train" / "000000"
    before = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in keep.iterdir()}
    old = load_sample(out / "train" / "000001")
    shutil.rmtree(out / "train" / "000001")
    for stale in (".tmp-000001", ".tmp-000007"):  # left by an interrupted run
        (out / "train" / stale).mkdir()
        (out / "train" / stale / "meta.json").write_text("{partial")
    res = generate_dataset(out, "train", 2, CFG, progress=False)
    assert res["written"] == 1 and res["skipped"] == 1 and res["seconds_per_sample"] > 0
    assert sorted(p.name for p in (out / "train").iterdir()) == ["000000", "000001"]
    # the complete sample was not touched
    assert {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in keep.iterdir()} == before
    new = load_sample(out / "train" / "000001")
    for k in old["voxels"]:
        np.testing.assert_array_equal(new["voxels"][k], old["voxels"][k])
    # everything done: a third run writes nothing
    res = generate_dataset(out, "train", 2, CFG, progress=False)
    assert (res["written"], res["skipped"], res["seconds_per_sample"]) == (0, 2, 0.0)


def test_a_sample_cut_off_mid_write_is_not_listed_and_is_redone(dataset_dir, tmp_path):
    """A worker killed while writing leaves a folder under a "running" manifest with some files and
    no meta.json: the adapter does not list it, and the next run writes it whole. A sample written
    before run manifests existed (meta.json, no manifest.json) counts as complete."""
    from scube_sim.datasets import open_dataset

    out = tmp_path / "ds"
    shutil.copytree(dataset_dir, out)
    cut = out / "train" / f"{FAST:06d}"
    whole = files_of(cut)
    (cut / "meta.json").unlink()
    (cut / "voxels.npz").unlink()
    manifest = json.loads((cut / "manifest.json").read_text())
    (cut / "manifest.json").write_text(json.dumps({**manifest, "status": "running", "outputs": {}}))
    legacy = out / "train" / "000000"
    (legacy / "manifest.json").unlink()
    legacy_files = files_of(legacy)
    assert [d.name for d in open_dataset("worlds", out, split="train").sample_dirs] == ["000000"]
    res = generate_dataset(out, "train", 2, CFG, progress=False)
    assert (res["written"], res["skipped"]) == (1, 1)
    digest = lambda files: {k: hashlib.sha256(v).hexdigest() for k, v in files.items()}  # noqa: E731
    assert digest(files_of(cut)) == digest(whole) and digest(files_of(legacy)) == digest(legacy_files)
    assert len(open_dataset("worlds", out, split="train")) == 2


def test_folder_made_with_other_settings_is_refused(dataset_dir):
    other = CFG.model_copy(update={"image_scale": 0.05})
    with pytest.raises(ValueError, match="dataset.json"):
        ensure_dataset_config(dataset_dir, other)
    with pytest.raises(ValueError, match="dataset.json"):
        generate_dataset(dataset_dir, "train", 1, other, progress=False)


def test_folder_of_another_format_is_refused(tmp_path):
    (tmp_path / "dataset.json").write_text(json.dumps({"format": "something-else", "version": 1}))
    with pytest.raises(ValueError, match="dataset.json"):
        ensure_dataset_config(tmp_path, CFG)


# --- splits ------------------------------------------------------------------------------------------


def test_splits_have_disjoint_seeds_and_different_worlds():
    train = {sample_world_config("train", i, CFG).seed for i in range(2000)}
    test = {sample_world_config("test", i, CFG).seed for i in range(2000)}
    val = {sample_world_config("val", i, CFG).seed for i in range(2000)}
    assert len(train) == len(test) == len(val) == 2000
    assert not (train & test) and not (train & val) and not (val & test)
    a, b = sample_world_config("train", FAST, CFG), sample_world_config("test", FAST, CFG)
    assert a.style == b.style and a.seed != b.seed
    wa, wb = generate_world(a), generate_world(b)
    assert not (wa.static.vertices.shape == wb.static.vertices.shape
                and np.array_equal(wa.static.vertices, wb.static.vertices))
    # styles cycle through the configured list; durations cover the last frame
    assert [sample_world_config("train", i, CFG).style for i in range(4)] == CFG.styles[:4]
    assert a.duration_s >= max(CFG.frame_offsets) / CFG.frame_rate_hz
    with pytest.raises(ValueError, match="split"):
        sample_world_config("holdout", 0, CFG)


def test_samples_cycle_through_the_rigs():
    """With two rigs, each full round of styles takes the next rig, and a sample's cameras are
    its rig's (names, resolution scaled as configured, poses from the rig's mounts)."""
    cfg = CFG.model_copy(update={"rigs": ["waymo-5", "nuscenes-6"], "styles": ["suburban"]})
    assert [ds_mod.sample_rig(i, cfg) for i in range(4)] == ["waymo-5", "nuscenes-6", "waymo-5", "nuscenes-6"]
    two = CFG.model_copy(update={"rigs": ["waymo-5", "nuscenes-6"]})
    assert [ds_mod.sample_rig(i, two) for i in range(9)] == ["waymo-5"] * 4 + ["nuscenes-6"] * 4 + ["waymo-5"]
    s = make_sample("train", 1, cfg)
    rig = load_rig("nuscenes-6")
    assert s["meta"]["rig"] == "nuscenes-6"
    cams = s["meta"]["frames"][0]["cameras"]
    assert [c["name"] for c in cams] == [c.name for c in rig.cameras]
    for c, rc in zip(cams, rig.cameras):
        assert c["intrinsics"]["width"] == rc.intrinsics().scaled(cfg.image_scale).width


# --- CLI -----------------------------------------------------------------------------------------


def test_cli_worlds_generate(tmp_path):
    out = tmp_path / "cli"
    ensure_dataset_config(out, CFG)  # a tiny configuration; the CLI resumes into the folder with its settings
    runner = CliRunner()
    r = runner.invoke(app, ["worlds", "generate", "-o", str(out), "--split", "val", "--count", "1",
                            "--start", str(FAST)])
    assert r.exit_code == 0, r.output
    m = re.search(r"val: wrote 1, skipped 0 complete; (\d+\.\d+) s per sample", r.output)
    assert m and float(m.group(1)) > 0, r.output
    s = load_sample(out / "val" / f"{FAST:06d}")
    assert s["meta"]["split"] == "val" and s["meta"]["world"]["seed"] == 1_000_000 + FAST
    r = runner.invoke(app, ["worlds", "generate", "-o", str(out), "--split", "val", "--count", "1",
                            "--start", str(FAST)])
    assert r.exit_code == 0 and "wrote 0, skipped 1 complete" in r.output
    # other settings for an existing folder: one line naming dataset.json, exit code 2
    r = runner.invoke(app, ["worlds", "generate", "-o", str(out), "--image-scale", "0.05", "--count", "1"])
    assert r.exit_code == 2 and "dataset.json" in r.output
    r = runner.invoke(app, ["worlds", "generate", "-o", str(out), "--jobs", "0"])
    assert r.exit_code == 2 and "error:" in r.output
    # --frame-offsets: stored instants of a new folder, from T on
    fresh = tmp_path / "offsets"
    r = runner.invoke(app, ["worlds", "generate", "-o", str(fresh), "--count", "0", "--frame-offsets", "0,2,7"])
    assert r.exit_code == 0, r.output
    assert json.loads((fresh / "dataset.json").read_text())["config"]["frame_offsets"] == [0, 2, 7]
    for bad, why in (("2,7", "include 0"), ("0,7,2", "strictly increasing"), ("0,x", "integers")):
        r = runner.invoke(app, ["worlds", "generate", "-o", str(tmp_path / "bad"), "--count", "0",
                                "--frame-offsets", bad])
        assert r.exit_code == 2 and why in r.output, r.output
    # --fine-voxel / --coarse-factor: the ground-truth grids of a new folder
    grids = tmp_path / "grids"
    r = runner.invoke(app, ["worlds", "generate", "-o", str(grids), "--count", "0", "--fine-voxel", "0.2",
                            "--coarse-factor", "4"])
    assert r.exit_code == 0, r.output
    cfg = json.loads((grids / "dataset.json").read_text())["config"]
    assert (cfg["fine_voxel_m"], cfg["coarse_factor"]) == (0.2, 4)
    for opt, bad in (("--fine-voxel", "0"), ("--coarse-factor", "0")):
        r = runner.invoke(app, ["worlds", "generate", "-o", str(tmp_path / "bad"), "--count", "0", opt, bad])
        assert r.exit_code == 2 and "error:" in r.output, r.output


# --- ground truth in a sample ----------------------------------------------------------------------


def _voxel_table(sample: dict, level: str) -> dict[tuple, tuple[int, bool]]:
    v = sample["voxels"]
    return {tuple(k): (int(lab), bool(vis)) for k, lab, vis in
            zip(v[f"{level}_ijk"].tolist(), v[f"{level}_labels"], v[f"{level}_visible"])}


@pytest.mark.parametrize("index", [0, 1])
def test_road_under_the_ego_is_in_the_voxels(dataset_dir, index):
    s = load_sample(dataset_dir / "train" / f"{index:06d}")
    for level, size in (("fine", CFG.fine_voxel_m), ("coarse", CFG.fine_voxel_m * CFG.coarse_factor)):
        table = _voxel_table(s, level)
        for x in (5.0, 15.0):
            # the road plane z = 0 lies on a voxel boundary (0 - (-3.2) = 8 voxels of 0.4 m): the
            # voxel above or below it may hold the road
            i, j = (np.floor((np.array([x, 0.0]) - CHUNK_CORNER[:2]) / size)).astype(int)
            k = int(round((0.0 - CHUNK_CORNER[2]) / size))
            cands = [table.get((i, j, kk)) for kk in (k - 1, k)]
            labels = {c[0] for c in cands if c is not None}
            assert labels & {ROAD, LANE}, f"{level}: no road voxel under chunk ({x}, 0, 0): {cands}"
        # and nothing sits in the ego's own space: the ego's box above the road is empty
        ijk = s["voxels"][f"{level}_ijk"].astype(np.int64)
        lo = np.floor((np.array([-1.0, -0.8, 0.9]) - CHUNK_CORNER) / size).astype(int)  # clear of the road layer
        hi = np.floor((np.array([3.5, 0.8, 1.5]) - CHUNK_CORNER) / size).astype(int)
        assert not np.any(np.all((ijk >= lo) & (ijk <= hi), axis=1))


def _front_points(s: dict):
    """FRONT depth of frame 0 back-projected into the chunk frame. The depth is stored as float16:
    each point comes with its neighbours 0.6 ulp of float16 nearer and farther along its ray (the
    rounding can move a point across a voxel face, and float16 holds no better)."""
    meta = s["meta"]
    cam = next(c for c in meta["frames"][0]["cameras"] if c["name"] == "FRONT")
    d = cam["intrinsics"]
    intr = Intrinsics(d["width"], d["height"], d["fx"], d["fy"], d["cx"], d["cy"], d["model"], tuple(d["dist"]))
    depth16 = s["frames"]["depth_00_FRONT"]
    to_chunk = invert_pose(np.asarray(meta["chunk_to_world"])) @ np.asarray(cam["cam_to_world"])
    depth = depth16.astype(np.float64)
    fin = np.isfinite(depth.reshape(-1))
    ulp = np.spacing(np.where(np.isfinite(depth16), np.abs(depth16), 0)).astype(np.float64)
    variants = []
    for f in (0.0, -0.6, 0.6):
        pts = depth_to_points(depth + f * ulp, intr, to_chunk)  # straight into the chunk frame
        variants.append(pts)
    sem = s["frames"]["semantic_00_FRONT"].reshape(-1)[fin]
    return variants, sem


def _lookup(s: dict, variants):
    """Per point: the occupied fine voxel holding it (the exact point first, then its float16
    neighbours), or None."""
    v = CFG.fine_voxel_m
    table = _voxel_table(s, "fine")
    keys = [list(map(tuple, np.floor((p - CHUNK_CORNER) / v).astype(np.int64).tolist())) for p in variants]
    out = []
    for n in range(len(variants[0])):
        out.append(next((k[n] for k in keys if k[n] in table), None))
    return out, table


@pytest.mark.parametrize("index", [0, 1])
def test_front_depth_lands_in_occupied_fine_voxels(dataset_dir, index):
    s = load_sample(dataset_dir / "train" / f"{index:06d}")
    variants, sem = _front_points(s)
    p = variants[0]
    inside = np.all((p >= CHUNK_CORNER) & (p < CHUNK_CORNER + CHUNK_SIZE), axis=1)
    assert inside.sum() > 0.5 * len(p) > 100
    found, table = _lookup(s, [q[inside] for q in variants])
    ok = np.array([k is not None for k in found])
    assert ok.mean() >= 0.99, f"{ok.mean():.4f} of the FRONT depth points lie in occupied voxels"
    # the voxel labels agree with the semantic map where the depth lands
    agree = np.mean([table[k][0] == c for k, c in zip(found, sem[inside]) if k is not None])
    assert agree > 0.85, agree
    # off the ground, the voxels holding seen points are marked visible
    vis = np.array([table[k][1] for k, c in zip(found, sem[inside]) if k is not None and c not in (ROAD, LANE)])
    assert len(vis) > 100 and vis.mean() > 0.98


def test_voxels_holding_seen_road_points_are_marked_visible(dataset_dir):
    """Every seen road point lies in a voxel marked visible: the voxel of the point itself or, as
    float16 depth can move it across a voxel face, of one of its float16 neighbours."""
    s = load_sample(dataset_dir / "train" / f"{FAST:06d}")
    variants, sem = _front_points(s)  # this sample's visibility renders are the same pixels (scale 0.04)
    p = variants[0]
    inside = np.all((p >= CHUNK_CORNER) & (p < CHUNK_CORNER + CHUNK_SIZE), axis=1)
    table = _voxel_table(s, "fine")
    v = CFG.fine_voxel_m
    keys = [list(map(tuple, np.floor((q[inside] - CHUNK_CORNER) / v).astype(np.int64).tolist())) for q in variants]
    road = [n for n, c in enumerate(sem[inside]) if c in (ROAD, LANE)]
    assert len(road) > 100
    unseen = [n for n in road if not any(k[n] in table and table[k[n]][1] for k in keys)]
    assert not unseen, f"{len(unseen)} of {len(road)} seen road points lie in voxels not marked visible"

def test_sample_frames_are_the_converters_input(dataset_dir):
    """`sample_frames` gives the shared camera input type: per image its pixels, intrinsics,
    own pose and own timestamp (the rig's firing offsets), and the set's ego pose."""
    from scube_sim.camera.rig import load_rig
    from scube_sim.worlds.dataset import sample_frames

    s = load_sample(dataset_dir / "train" / f"{FAST:06d}")
    rig = load_rig(CFG.rig)
    for f, offset in enumerate(CFG.frame_offsets):
        frames = sample_frames(s, f)
        assert frames.names == [c.name for c in rig.cameras]
        t_ref = offset / CFG.frame_rate_hz
        assert frames.timestamp == pytest.approx(t_ref)
        for im, cam in zip(frames.images, rig.cameras):
            assert im.timestamp == pytest.approx(t_ref + cam.time_offset_s)
            assert im.image.shape[:2] == (im.intrinsics.height, im.intrinsics.width)
            np.testing.assert_array_equal(im.sky, ~np.isfinite(im.depth))
