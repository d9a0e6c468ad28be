"""Clouds merged from several LiDARs: per-point origins in `LidarSweep` and the folder format, the
build and fidelity traced from each point's own sensor, and the refusal when a cloud lacks them.

The synthetic scene is exact (planes and boxes scanned by two noiseless presets), so the truth is
the scene itself: a build from the merged cloud, traced again from the same poses, must return
the real ranges. The real sweeps in ../shared/data give the single-sensor side of the check.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from scube_sim.datasets import DatasetError, LidarSpec, LidarSweep, Sample, open_dataset
from scube_sim.datasets.base import merge_sweeps
from scube_sim.datasets.folder import FolderDataset, write_folder_dataset
from scube_sim.datasets.origins import MergedCloudError, check_origin
from scube_sim.lidar.config import load_lidar_config
from scube_sim.lidar.model import Lidar
from scube_sim.mesh import TriangleMesh
from scube_sim.raytrace.tracer import Tracer
from scube_sim.realdata.build import BuildOptions, accumulate, build_from_dataset
from scube_sim.realdata.fidelity import FidelityOptions, run_fidelity
from scube_sim.transforms import pose_from_xyz_rpy, transform_points
from scube_sim.worlds import primitives as pr
from tests.conftest import require

EGO = pose_from_xyz_rpy([100.0, -50.0, 0.0], [0.0, 0.0, 25.0])  # ego frame at ground level, world z up
MOUNTS = {"top": pose_from_xyz_rpy([0.0, 0.0, 1.9], [0, 0, 0]),          # roof, T_ego_sensor
          "front": pose_from_xyz_rpy([2.2, 0.0, 0.6], [0.0, 10.0, 0.0])}  # bumper, pitched 10 degrees down


def quiet(name):
    cfg = load_lidar_config(name)
    return cfg.model_copy(update={
        "noise": cfg.noise.model_copy(update={"range_sigma_m": 0.0, "quantization_m": 0.0}),
        "drop": cfg.drop.model_copy(update={"max_incidence_deg": 90.0}), "ego_body": None})


CONFIGS = {"top": quiet("HDL-32E"), "front": quiet("VLP-16")}


def world_scene() -> TriangleMesh:
    """Ground at z = 0, two car-sized boxes, a pillar and a wall, around the ego (world frame)."""
    local = TriangleMesh.concatenate([
        pr.quad([[-30, -30, 0], [30, -30, 0], [30, 30, 0], [-30, 30, 0]]),
        pr.box([8.0, 3.0, 0.75], [4.0, 1.8, 1.5]), pr.box([-7.0, -4.0, 0.75], [4.0, 1.8, 1.5]),
        pr.box([3.0, -6.0, 1.5], [1.0, 1.0, 3.0]),
        pr.quad([[20, -30, 0], [20, 30, 0], [20, 30, 6], [20, -30, 6]])])
    return TriangleMesh(transform_points(EGO, local.vertices), local.faces)


@pytest.fixture(scope="module")
def two_sweeps():
    scene = world_scene()
    out = []
    for name in ("top", "front"):
        pose = EGO @ MOUNTS[name]
        pts = Lidar(CONFIGS[name]).scan(Tracer(scene), pose).points
        xyz = np.stack([pts["x"], pts["y"], pts["z"]], 1).astype(np.float64)
        out.append(LidarSweep(name, xyz, pose, 0.0, pts["intensity"].astype(np.float32), 1.0,
                              pts["ring"].astype(np.int16)))
    return out


def without_origins(sw: LidarSweep) -> LidarSweep:
    return dataclasses.replace(sw, origin_id=None, origins=None, origin_names=None)


class OneSample:
    """A minimal dataset adapter: one sample holding `sweep`, with both sensors' models and mounts."""

    name, root, poses_from_icp = "synthetic", "memory", False

    def __init__(self, sweep):
        self.sweep = sweep

    def __len__(self):
        return 1

    def __getitem__(self, i):
        lidars = {n: LidarSpec(n, CONFIGS[n], MOUNTS[n]) for n in CONFIGS}
        lidars["merged"] = LidarSpec("merged", CONFIGS["top"], np.eye(4))
        return Sample("s0", 0.0, EGO, sweeps=[self.sweep], lidars=lidars)


def test_merge_and_split_give_back_each_sensor(two_sweeps):
    m = merge_sweeps(two_sweeps, EGO)
    assert m.merged and m.origin_names == ("top", "front") and len(m) == sum(len(s) for s in two_sweeps)
    np.testing.assert_allclose(m.origins, [MOUNTS["top"], MOUNTS["front"]], atol=1e-12)
    # Each point's origin is its sensor's position in the ego frame.
    np.testing.assert_allclose(m.point_origins()[m.origin_id == 1], np.tile([2.2, 0.0, 0.6], ((m.origin_id == 1).sum(), 1)),
                               atol=1e-12)
    for part, sw in zip(m.by_origin(), two_sweeps):
        assert part.sensor == sw.sensor and not part.merged
        np.testing.assert_allclose(part.points, sw.points, atol=1e-9)
        np.testing.assert_allclose(part.sensor_to_world, sw.sensor_to_world, atol=1e-12)
        np.testing.assert_array_equal(part.ring, sw.ring)
    np.testing.assert_allclose(m.world_points(), np.concatenate([s.world_points() for s in two_sweeps]), atol=1e-9)


def test_bad_origins_are_named():
    with pytest.raises(ValueError, match=r"sweep 'm': origin_id holds 0\.\.2, expected 0\.\.1"):
        LidarSweep("m", np.zeros((3, 3)), np.eye(4), 0.0, origin_id=np.array([0, 1, 2]),
                   origins=np.stack([np.eye(4)] * 2))
    with pytest.raises(ValueError, match="give origin_id and origins together"):
        LidarSweep("m", np.zeros((3, 3)), np.eye(4), 0.0, origin_id=np.array([0, 0, 0]))


def test_build_and_fidelity_trace_each_return_from_its_own_sensor(two_sweeps):
    merged = merge_sweeps(two_sweeps, EGO)  # stored as logs do: the ego frame at ground level
    ds = OneSample(merged)
    vs, rep, acc = build_from_dataset(ds, BuildOptions(samples=[0], color=False, reflectance=False))
    # Every point remembers where it was seen from: the two mounts (local frame of acc.origin).
    ids = merged.origin_id
    for k, name in enumerate(("top", "front")):
        seen_from = acc.sensor[acc.sweep == k] + acc.origin
        np.testing.assert_allclose(seen_from, np.broadcast_to((EGO @ MOUNTS[name])[:3, 3], seen_from.shape), atol=1e-9)
    assert np.bincount(acc.sweep).tolist() == np.bincount(ids).tolist()
    # Each part meshed in its own range image: most returns are in a triangle (the bumper sensor,
    # 0.6 m up, sees the ground beyond ~17 m at over the mesh's 88 degree incidence limit) ...
    def in_triangles(a):
        used = np.zeros(len(a), bool)
        used[a.faces.ravel()] = True
        return used

    used, ground = in_triangles(acc), (acc.points + acc.origin)[:, 2] < 0.01
    assert used[acc.sweep == 0].mean() > 0.9 and used[acc.sweep == 1].mean() > 0.6 and used[ground].mean() > 0.7
    # ... where one range image from the stated origin (ground level) sees the ground edge-on.
    bare_acc = accumulate([Sample("s0", 0.0, EGO, sweeps=[without_origins(merged)])],
                          BuildOptions(samples=[0], assume_single_origin=True))
    assert in_triangles(bare_acc)[(bare_acc.points + bare_acc.origin)[:, 2] < 0.01].mean() < 0.05
    res = run_fidelity(ds, vs, 0, FidelityOptions(baselines=False))
    m = res.rows["voxsplat"]
    assert m["hit_agreement"] > 0.99 and m["median_abs_m"] < 0.01 and m["p90_abs_m"] < 0.05
    assert m["chamfer_m"] < 0.02
    assert any("merged sweep: 2 LiDARs (top, front)" in n for n in res.notes)
    # The same cloud without its origins is refused by both, naming the sweep and the fix ...
    bare = OneSample(without_origins(merged))
    with pytest.raises(MergedCloudError, match=r"sample 's0': sweep 'merged' looks merged .*sensor_id.*"
                                               r"assume-single-origin"):
        build_from_dataset(bare, BuildOptions(samples=[0], color=False, reflectance=False))
    with pytest.raises(MergedCloudError, match=r"synthetic: sample 0: sweep 'merged' .*above the ground"):
        run_fidelity(bare, vs, 0, FidelityOptions(baselines=False))
    # ... and forcing it through shows why: traced from ground level the ranges are metres off.
    forced = run_fidelity(bare, vs, 0, FidelityOptions(baselines=False, assume_single_origin=True))
    assert forced.rows["voxsplat"]["median_abs_m"] > 0.3


def test_check_flags_the_merged_cloud_not_its_parts(two_sweeps):
    for sw in two_sweeps:
        c = check_origin(sw)
        assert c.single_origin and c.seen_through < 0.01
        np.testing.assert_allclose(c.origin_height_m, MOUNTS[sw.sensor][2, 3], atol=0.02)
    c = check_origin(without_origins(merge_sweeps(two_sweeps, EGO)))
    assert not c.single_origin and len(c.reasons) == 2
    assert abs(c.origin_height_m) < 0.02 and c.seen_through > 0.3
    # A cloud stated in the roof sensor's frame: the bumper's returns are all in view from the roof
    # in this scene, so tracing from there is right, and the check lets it pass.
    assert check_origin(without_origins(merge_sweeps(two_sweeps, EGO @ MOUNTS["top"]))).single_origin
    # A merged sweep that carries its origins passes part by part.
    assert check_origin(merge_sweeps(two_sweeps, EGO)).single_origin


def test_folder_round_trip_of_a_merged_sweep(two_sweeps, tmp_path):
    merged = merge_sweeps(two_sweeps, EGO)
    sample = Sample("s0", 0.0, EGO, sweeps=[merged, two_sweeps[0]],
                    lidars={n: LidarSpec(n, CONFIGS[n], MOUNTS[n]) for n in CONFIGS})
    out = write_folder_dataset([sample], tmp_path / "f")
    top = yaml.safe_load((out / "dataset.yaml").read_text())
    assert top["version"] == 2
    doc = yaml.safe_load((out / "samples" / "000000" / "sample.yaml").read_text())
    assert [o["sensor"] for o in doc["sweeps"]["merged"]["origins"]] == ["top", "front"]
    assert "origins" not in doc["sweeps"]["top"]
    pts = np.load(out / "samples" / "000000" / "merged.npz", allow_pickle=False)["points"]
    np.testing.assert_array_equal(pts["sensor_id"], merged.origin_id)
    got = FolderDataset(out)[0].sweep("merged")
    np.testing.assert_array_equal(got.origin_id, merged.origin_id)
    np.testing.assert_array_equal(got.origins, merged.origins)
    assert got.origin_names == ("top", "front") and got.source.endswith("merged.npz")
    for part, sw in zip(got.by_origin(), two_sweeps):
        np.testing.assert_allclose(part.points, sw.points, atol=1e-9)
    assert FolderDataset(out)[0].sweep("top").origins is None
    with pytest.raises(ValueError, match="KITTI .bin cannot store its sensor_id"):
        write_folder_dataset([sample], tmp_path / "b", points_format="bin")


def test_hand_written_origins_by_sensor_name_use_the_mounts(two_sweeps, tmp_path):
    merged = merge_sweeps(two_sweeps, EGO)
    out = write_folder_dataset([Sample("s0", 0.0, EGO, sweeps=[merged],
                                       lidars={n: LidarSpec(n, CONFIGS[n], MOUNTS[n]) for n in CONFIGS})],
                               tmp_path / "f")
    path = out / "samples" / "000000" / "sample.yaml"
    doc = yaml.safe_load(path.read_text())
    doc["sweeps"]["merged"]["origins"] = [{"sensor": "top"}, {"sensor": "front"}]  # mounts from dataset.yaml
    path.write_text(yaml.safe_dump(doc))
    got = FolderDataset(out)[0].sweep("merged")
    # sensor_to_world is the ego pose, so each origin is the sensor's mount exactly.
    np.testing.assert_allclose(got.origins, [MOUNTS["top"], MOUNTS["front"]], atol=1e-9)
    doc["sweeps"]["merged"]["origins"] = [{"sensor": "top"}, {"sensor": "rear"}]
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(DatasetError, match=r"sample.yaml: sweeps\.merged\.origins\[1\]\.sensor: 'rear' is not a LiDAR"):
        FolderDataset(out)[0]
    del doc["sweeps"]["merged"]["origins"]
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(DatasetError, match=r"merged\.npz: has a 'sensor_id' field but .*sample\.yaml: sweeps\.merged "
                                           r"has no 'origins'"):
        FolderDataset(out)[0]
    doc["sweeps"]["merged"]["origins"] = [{"sensor": "top"}, {"sensor": "front"}]
    path.write_text(yaml.safe_dump(doc))
    top = yaml.safe_load((out / "dataset.yaml").read_text())
    top["version"] = 1
    (out / "dataset.yaml").write_text(yaml.safe_dump(top))
    with pytest.raises(DatasetError, match=r"sweeps\.merged\.origins: merged sweeps need version 2"):
        FolderDataset(out)[0]


def test_real_single_sensor_sweeps_pass_the_check(shared_data):
    nus = open_dataset("nuscenes", require(shared_data / "nuscenes-mmdet3d-demo"))[0].sweep()
    kitti = open_dataset("kitti_raw", require(shared_data / "kitti-raw-2011_09_26-udacity"))[0].sweep()
    for sw, height in ((nus, 1.58), (kitti, 1.76)):  # roof sensors: the check measures their height
        c = check_origin(sw)
        assert c.single_origin, c.reasons
        assert c.seen_through < 0.05 and abs(c.origin_height_m - height) < 0.1


def test_argoverse2_table_in_its_ego_frame_is_refused_and_split_by_laser_number(shared_data):
    """AV2 stores both VLP-32C in one table in the ego frame (origin at ground level): as stored it
    is refused; with laser_number // 32 as sensor id and the calibrated mounts, its parts are the
    two sensors' own sweeps."""
    from scube_sim.datasets.argoverse2 import Argoverse2Dataset, read_lidar_feather

    ds = Argoverse2Dataset(require(shared_data / "argoverse2-sensor-log-7fab2350"))
    s = ds[0]
    cols = read_lidar_feather(ds.sweep_files[0])
    xyz = np.stack([cols["x"], cols["y"], cols["z"]], 1).astype(np.float64)
    table = LidarSweep("lidar", xyz, s.ego_pose, s.timestamp, source=str(ds.sweep_files[0]))
    c = check_origin(table)
    assert not c.single_origin and c.seen_through > 0.15 and c.origin_height_m < 0.3
    with pytest.raises(MergedCloudError, match=r"sweep 'lidar' \(.*\.feather\) looks merged"):
        accumulate([Sample("t", s.timestamp, s.ego_pose, sweeps=[table])], BuildOptions(samples=[0], mesh=False))
    merged = dataclasses.replace(table, origin_id=(cols["laser_number"] // 32).astype(np.int16),
                                 origins=np.stack([s.lidars[n].sensor_to_ego for n in ("up_lidar", "down_lidar")]),
                                 origin_names=("up_lidar", "down_lidar"))
    for part, sw in zip(merged.by_origin(), s.sweeps):
        assert part.sensor == sw.sensor
        np.testing.assert_allclose(part.points, sw.points, atol=1e-9)
        np.testing.assert_allclose(part.sensor_to_world, sw.sensor_to_world, atol=1e-9)
        assert check_origin(part).single_origin


def test_unnamed_origins_round_trip_twice(two_sweeps, tmp_path):
    merged = dataclasses.replace(merge_sweeps(two_sweeps, EGO), origin_names=None)
    first = FolderDataset(write_folder_dataset([Sample("s0", 0.0, EGO, sweeps=[merged])], tmp_path / "a"))[0]
    got = first.sweep("merged")
    assert got.origin_names == ("merged#0", "merged#1")  # read back with made-up names ...
    second = FolderDataset(write_folder_dataset([first], tmp_path / "b"))[0].sweep("merged")  # ... not written
    np.testing.assert_array_equal(second.origins, merged.origins)
    np.testing.assert_array_equal(second.origin_id, merged.origin_id)
