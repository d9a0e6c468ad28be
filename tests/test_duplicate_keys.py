"""Silent last-wins (issue 46): a mapping that holds one key twice, and a list that names one thing
twice, are refused wherever the project reads them, naming the file, the line and key path (or
the list and both places); from the CLI as one `error:` line, exit code 2, and no output file.

The YAML check is one loader (`scube_sim.config.UniqueKeyLoader`, behind `load_yaml`), the JSON
check one `object_pairs_hook` (`scube_sim.config.json_loads`), the list check one helper
(`scube_sim.config.listed_twice` / `unique_names`); these tests plant one duplicate in each place
that reads a file, a setting or an option."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from scube_sim.cli import app
from scube_sim.config import ConfigError, json_loads, load_yaml, parse_key_values, validate_model
from scube_sim.errors import InputError, ScubeSimError
from tests.conftest import one_line_error as one_line

runner = CliRunner()
REPO = Path(__file__).resolve().parents[1]


def files_under(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


@pytest.fixture
def scene(tmp_path):
    from scube_sim.voxsplat import VoxSplat

    return VoxSplat(ijk=np.zeros((1, 3)), params=np.zeros((1, 1, 14)), voxel_size=0.1).save(tmp_path / "s.npz")


def dup_sensor_yaml(folder: Path) -> Path:
    """vlp16 with `pattern.columns` twice (the issue's example: 1800, then 90) at lines 5 and 7."""
    bad = folder / "sensor.yaml"
    bad.write_text("name: dup\npattern:\n  type: spinning\n  rotation_hz: 10.0\n  columns: 1800\n"
                   "  direction: cw\n  columns: 90\n"
                   "  channels: {elevation_deg: [-15.0, 1.0]}\n")
    return bad


# --- the loader -------------------------------------------------------------------------------


def test_the_loader_names_line_and_key_path(tmp_path):
    p = tmp_path / "s.yaml"
    p.write_text("name: x\nsensors:\n- preset: vlp16\n  mount: {xyz: [0, 0, 1]}\n- preset: hdl32e\n"
                 "  mount:\n    xyz: [0, 0, 1]\n    rpy_deg: [0, 0, 0]\n    xyz: [1, 1, 1]\n")
    with pytest.raises(ConfigError) as e:
        load_yaml(p)
    assert str(e.value) == f"{p}: line 9: sensors[1].mount.xyz: duplicate key (first at line 7)"


def test_the_earliest_duplicate_is_named_and_keys_compare_as_values(tmp_path):
    p = tmp_path / "k.yaml"
    p.write_text("a:\n  b: 1\n  b: 2\nc: 1\nc: 2\n")  # c's second at line 5, b's at line 3
    with pytest.raises(ConfigError, match=r"k\.yaml: line 3: a\.b: duplicate key \(first at line 2\)$"):
        load_yaml(p)
    p.write_text("table:\n  1: a\n  0x1: b\n")  # one integer key
    with pytest.raises(ConfigError, match=r"line 3: table\.0x1: duplicate key \(first at line 2\)"):
        load_yaml(p)


def test_what_yaml_allows_still_loads(tmp_path):
    """Merge keys may be overridden (YAML's own rule), an alias repeats a node, and `1` and '1' are
    two keys."""
    p = tmp_path / "ok.yaml"
    p.write_text("base: &b {x: 1, y: 2}\nm:\n  <<: *b\n  x: 3\nn: *b\nt: {1: int, '1': str}\n")
    assert load_yaml(p) == {"base": {"x": 1, "y": 2}, "m": {"x": 3, "y": 2}, "n": {"x": 1, "y": 2},
                            "t": {1: "int", "1": "str"}}


def _shipped_yamls() -> list[str]:
    out = subprocess.run(["git", "ls-files", "*.yaml", "*.yml"], cwd=REPO, capture_output=True, text=True, check=False)
    listed = out.stdout.split() if out.returncode == 0 else []
    on_disk = [str(p.relative_to(REPO)) for d in ("sensors", "scenarios", "scube_sim", "experiments")
               for p in (REPO / d).rglob("*.y*ml")]
    return sorted({f for f in listed + on_disk if f.split("/")[0] in ("sensors", "scenarios", "scube_sim",
                                                                       "experiments")})


def test_every_shipped_yaml_loads_through_the_loader():
    files = _shipped_yamls()
    assert len(files) >= 40 and any(f.startswith("scube_sim/converter/profiles/") for f in files)
    for f in files:
        assert load_yaml(REPO / f) is not None, f


def test_every_shipped_yaml_validates_where_a_schema_reads_it():
    from scube_sim.camera.rig import load_rig
    from scube_sim.converter.profile import load_profile, shipped_profiles
    from scube_sim.lidar.config import load_config_file
    from scube_sim.runs.scenario import load_scenario

    for p in sorted((REPO / "sensors/lidar").glob("*.yaml")):
        if "." not in p.stem:
            load_config_file(p)
    for p in sorted((REPO / "sensors/rigs").glob("*.yaml")):
        load_rig(p)
    for name in shipped_profiles():
        load_profile(name)
    for p in sorted((REPO / "scenarios").glob("*.yaml")):
        load_scenario(p)


# --- YAML files, from the command line --------------------------------------------------------


def test_a_sensor_yaml_with_a_key_twice(tmp_path, scene):
    bad = dup_sensor_yaml(tmp_path)
    out = tmp_path / "x.pcd"
    line = one_line(runner.invoke(app, ["lidar", str(scene), "--sensor", str(bad), "-o", str(out)]))
    assert line == f"error: {bad}: line 7: pattern.columns: duplicate key (first at line 5)"
    assert not out.exists() and files_under(tmp_path) == {"s.npz", "sensor.yaml"}


def _scenario(tmp_path: Path, body: str) -> Path:
    p = tmp_path / "sc.yaml"
    p.write_text("name: sc\nscene: {world: {style: suburban}}\nsensors: [{preset: vlp16}]\n" + body)
    return p


@pytest.mark.parametrize("body, line, key", [
    ("seed: 1\nseed: 2\n", 5, "seed"),                                     # top level
    ("outputs:\n  usd: a.usdc\n  files: [npz]\n  usd: b.usdc\n", 7, "outputs.usd"),  # nested
])
def test_a_scenario_with_a_key_twice(tmp_path, body, line, key):
    sc = _scenario(tmp_path, body)
    out = tmp_path / "r"
    msg = one_line(runner.invoke(app, ["replay", str(sc), "-o", str(out)]))
    first = line - (1 if key == "seed" else 2)
    assert msg == f"error: {sc}: line {line}: {key}: duplicate key (first at line {first})"
    assert not out.exists()


def test_a_converter_profile_with_a_key_twice(tmp_path):
    """The issue's example: `focal_px` twice in a profile."""
    prof = tmp_path / "p.yaml"
    prof.write_text("route: scube\ngeometry:\n  checkpoint: geometry\n  focal_px: 200\n  focal_px: 400\n"
                    "appearance: {checkpoint: appearance, focal_px: 200}\n")
    out = tmp_path / "c.npz"
    msg = one_line(runner.invoke(app, ["convert", str(tmp_path / "nowhere"), "--profile", str(prof), "-o", str(out)]))
    assert msg == f"error: {prof}: line 5: geometry.focal_px: duplicate key (first at line 4)"
    assert not out.exists()


def test_a_camera_rig_with_a_key_twice(tmp_path, scene):
    rig = tmp_path / "rig.yaml"
    rig.write_text("name: r\ncameras:\n- {name: FRONT, width: 8, height: 8, fx: 4, fy: 4, cx: 4, cy: 4, fx: 5}\n")
    out = tmp_path / "v.png"
    msg = one_line(runner.invoke(app, ["render", str(scene), "--rig", str(rig), "-o", str(out)]))
    assert msg == f"error: {rig}: line 3: cameras[0].fx: duplicate key (first at line 3)"
    assert not out.exists()


def test_batch_settings_with_a_key_twice(tmp_path):
    sc = _scenario(tmp_path, "")
    settings = tmp_path / "sweep.yaml"
    settings.write_text("seeds: [1, 2]\nduration_s: 1\nseeds: [3]\n")
    out = tmp_path / "campaign"
    msg = one_line(runner.invoke(app, ["batch", "replay", "-i", str(sc), "--settings", str(settings), "-o", str(out),
                                       "--no-progress"]))
    assert msg == f"error: {settings}: line 3: seeds: duplicate key (first at line 1)"
    assert not out.exists()


def test_a_set_value_with_a_key_twice(tmp_path):
    """`--set` keeps later-over-earlier between items, but one VALUE's own mapping may not hold a
    key twice."""
    assert parse_key_values(["seeds=[1]", "seeds=[2]"], "--set") == {"seeds": [2]}
    sc = _scenario(tmp_path, "")
    out = tmp_path / "campaign"
    item = "edits={a: {speed_scale: 2}, a: {speed_scale: 3}}"
    msg = one_line(runner.invoke(app, ["batch", "replay", "-i", str(sc), "--set", item, "-o", str(out),
                                       "--no-progress"]))
    assert msg == f"error: --set {item!r}: edits.a: duplicate key in VALUE"
    assert not out.exists()


def _folder_dataset(root: Path, sample_yaml: str, dataset_extra: str = "") -> Path:
    eye = "[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]"
    (root / "samples/000000").mkdir(parents=True)
    (root / "dataset.yaml").write_text(
        "format: scube-sim-folder\nversion: 2\n"
        f"lidars:\n  top: {{preset: vlp16, sensor_to_ego: {eye}}}\n"
        "cameras:\n  FRONT: {width: 8, height: 8, fx: 4.0, fy: 4.0, cx: 4.0, cy: 4.0}\n"
        "  LEFT: {width: 8, height: 8, fx: 4.0, fy: 4.0, cx: 4.0, cy: 4.0}\n" + dataset_extra)
    (root / "samples/000000/sample.yaml").write_text(f"name: s0\ntimestamp: 0.0\nego_pose: {eye}\n" + sample_yaml)
    return root


EYE = "[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]"
IMG = f"{{file: F.png, timestamp: 0.0, cam_to_world: {EYE}}}"


@pytest.mark.parametrize("sample, dataset_extra, where, expect", [
    # the example: a camera listed twice in a sample (its second image silently won)
    (f"images:\n  FRONT: {IMG}\n  FRONT: {IMG}\n", "", "sample", "line 6: images.FRONT: duplicate key (first at line 5)"),
    ("", "cameras:\n  BACK: {width: 8, height: 8, fx: 4.0, fy: 4.0, cx: 4.0, cy: 4.0}\n", "dataset",
     "line 8: cameras: duplicate key (first at line 5)"),
])
def test_a_folder_dataset_with_a_key_twice(tmp_path, sample, dataset_extra, where, expect):
    root = _folder_dataset(tmp_path / "ds", sample, dataset_extra)
    out = tmp_path / "scene.npz"
    msg = one_line(runner.invoke(app, ["build", str(root), "--dataset", "folder", "-o", str(out)]))
    file = root / "dataset.yaml" if where == "dataset" else root / "samples/000000/sample.yaml"
    assert msg == f"error: {file}: {expect}"
    assert not out.exists()


# --- YAML files, through the API (every other reader) -----------------------------------------


def _write(tmp_path, name, text) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize("reader, name, text, where", [
    ("world", "w.yaml", "world:\n  style: suburban\n  seed: 1\n  seed: 2\n", "line 4: world.seed"),
    ("drop", "d.drop.yaml", ("format: scube_sim.drop_model\nversion: 1\nintercept: 0\n"
                             "coefficients: {log_range: 1.0, log_range: 2.0}\n"), "line 4: coefficients.log_range"),
    ("velodyne", "v.yaml", "lasers:\n- {laser_id: 0, vert_correction: 0.1, rot_correction: 0.0, vert_correction: 0.2}\n",
     "line 2: lasers[0].vert_correction"),
    ("run_config", "run.yaml", "stage: geometry\nstage: appearance\n", "line 2: stage"),
    ("lidar_class_reflectivity", "l.yaml", None, "intensity.class_reflectivity.car"),
    ("folder_lidar_config", "lidars/top.yaml", None, "line 7: pattern.columns"),
])
def test_every_yaml_reader_refuses_a_key_twice(tmp_path, reader, name, text, where):
    from scube_sim.datasets import open_dataset
    from scube_sim.lidar.config import load_lidar_config
    from scube_sim.lidar.drop import DropModel
    from scube_sim.lidar.importers import from_velodyne_yaml
    from scube_sim.model.config import load_config
    from scube_sim.worlds.generator import WorldConfig

    if reader == "lidar_class_reflectivity":
        text = (REPO / "sensors/lidar/vlp16.yaml").read_text().replace(
            "  class_reflectivity: {}\n", "  class_reflectivity:\n    car: 0.3\n    road: 0.1\n    car: 0.9\n")
        assert "car: 0.9" in text
    if reader == "folder_lidar_config":
        root = _folder_dataset(tmp_path / "ds", "")
        (root / "lidars").mkdir()
        bad = dup_sensor_yaml(root / "lidars")
        (root / "dataset.yaml").write_text((root / "dataset.yaml").read_text().replace(
            "{preset: vlp16,", "{config: lidars/sensor.yaml,"))
        with pytest.raises(ScubeSimError) as e:
            open_dataset("folder", root)
        assert f"{bad}: line 7: pattern.columns: duplicate key (first at line 5)" in str(e.value)
        return
    p = _write(tmp_path, name, text)
    call = {"world": lambda: WorldConfig.from_yaml(p), "drop": lambda: DropModel.load(p),
            "velodyne": lambda: from_velodyne_yaml(p, columns=100, rotation_hz=10.0),
            "run_config": lambda: load_config(p), "lidar_class_reflectivity": lambda: load_lidar_config(str(p))}[reader]
    with pytest.raises(ScubeSimError) as e:
        call()
    assert str(e.value).startswith(f"{p}: line ") and f"{where}: duplicate key (first at line " in str(e.value)


# --- JSON files --------------------------------------------------------------------------------


def test_json_loads_names_the_key_path():
    with pytest.raises(ConfigError) as e:
        json_loads('{"a": {"b": [1, {"c": 1, "c": 2}]}, "a2": 1}', "f.json")
    assert str(e.value) == "f.json: a.b[1].c: duplicate key"
    assert json_loads('{"a": {"c": 1}, "b": {"c": 2}}', "f.json") == {"a": {"c": 1}, "b": {"c": 2}}
    with pytest.raises(json.JSONDecodeError):  # not JSON: each caller words it, as before
        json_loads("{", "f.json")


def test_an_ouster_metadata_json_with_a_key_twice(tmp_path):
    from scube_sim.lidar.importers import from_ouster_json

    p = _write(tmp_path, "os.json", '{"beam_altitude_angles": [1, 2], "beam_azimuth_angles": [0, 0],'
                                    ' "lidar_mode": "1024x10", "beam_altitude_angles": [3, 4]}')
    with pytest.raises(ConfigError, match=rf"^{p}: beam_altitude_angles: duplicate key$"):
        from_ouster_json(p)


def _waymo_meta(lasers=None, cameras=None, images=None, dup_key=False) -> str:
    eye = np.eye(4).tolist()
    laser = {"name": "TOP", "beam_inclinations_rad": [-0.1, 0.0, 0.1], "extrinsic_laser_to_vehicle_4x4": eye}
    cam = {"name": "FRONT", "width": 8, "height": 8, "intrinsic_fu_fv_cu_cv_k1_k2_p1_p2_k3": [4, 4, 4, 4, 0, 0, 0, 0, 0],
           "extrinsic_camera_to_vehicle_4x4": eye}
    meta = {"context_name": "c", "timestamp_micros": 0, "pose_vehicle_to_global_4x4": eye,
            "laser_calibrations": lasers or [laser], "camera_calibrations": cameras or [cam],
            "images": images or [], "laser_labels": []}
    text = json.dumps(meta)
    return text.replace('"context_name": "c"', '"context_name": "c", "context_name": "d"') if dup_key else text


@pytest.mark.parametrize("case, expect", [
    ("key", "context_name: duplicate key"),
    ("laser", "laser_calibrations: name 'TOP' is listed twice (at [0] and [1])"),
    ("camera", "camera_calibrations: name 'FRONT' is listed twice (at [0] and [1])"),
    ("image", "images: name 'FRONT' is listed twice (at [0] and [1])"),
])
def test_a_waymo_frame_with_a_key_or_a_name_twice(tmp_path, case, expect):
    from scube_sim.datasets.base import DatasetError
    from scube_sim.datasets.waymo import WaymoFrameDataset
    from scube_sim.lidar.importers import from_waymo_frame

    eye = np.eye(4).tolist()
    laser = {"name": "TOP", "beam_inclinations_rad": [-0.1, 0.0, 0.1], "extrinsic_laser_to_vehicle_4x4": eye}
    cam = {"name": "FRONT", "width": 8, "height": 8, "intrinsic_fu_fv_cu_cv_k1_k2_p1_p2_k3": [4, 4, 4, 4, 0, 0, 0, 0, 0],
           "extrinsic_camera_to_vehicle_4x4": eye}
    img = {"name": "FRONT", "file": "front.jpg", "pose_vehicle_to_global_4x4_at_image": eye, "pose_timestamp_s": 0.0}
    text = {"key": lambda: _waymo_meta(dup_key=True), "laser": lambda: _waymo_meta(lasers=[laser, laser]),
            "camera": lambda: _waymo_meta(cameras=[cam, cam]), "image": lambda: _waymo_meta(images=[img, img])}[case]()
    p = _write(tmp_path, "frame_metadata.json", text)
    with pytest.raises(DatasetError) as e:
        ds = WaymoFrameDataset(p)
        ds._lidars() if case == "laser" else ds._frames(np.eye(4), 0.0)
    assert str(e.value) == f"{p}: {expect}"
    if case == "laser":  # the importer on its own: it took the first of the two
        with pytest.raises(ConfigError, match=r"laser_calibrations: name 'TOP' is listed twice"):
            from_waymo_frame(p, "TOP")


def test_a_worlds_dataset_header_and_a_run_manifest_with_a_key_twice(tmp_path, scene):
    from scube_sim.datasets import open_dataset
    from scube_sim.run_manifest import read_manifest

    (tmp_path / "w").mkdir()
    head = _write(tmp_path / "w", "dataset.json", '{"format": "scube_sim.worlds", "version": 4, "version": 2}')
    with pytest.raises(ScubeSimError, match=rf"^{head}: version: duplicate key$"):
        open_dataset("worlds", tmp_path / "w", split="test")
    (tmp_path / "r").mkdir()
    man = _write(tmp_path / "r", "manifest.json", '{"format": "x", "status": "complete", "status": "failed"}')
    with pytest.raises(InputError, match=rf"^{man}: status: duplicate key$"):
        read_manifest(tmp_path / "r")


def test_a_voxsplat_whose_metadata_json_has_a_key_twice(tmp_path, scene):
    z = dict(np.load(scene, allow_pickle=False))
    z["metadata"] = np.array('{"trace_mode": "entry", "trace_mode": "soft"}')
    bad = tmp_path / "meta2.npz"
    np.savez(bad, **z)
    out = tmp_path / "x.pcd"
    msg = one_line(runner.invoke(app, ["lidar", str(bad), "--sensor", "vlp16", "-o", str(out)]))
    assert msg == f"error: {bad}: key 'metadata': trace_mode: duplicate key"
    assert not out.exists()


# --- lists that name one thing twice ----------------------------------------------------------


@pytest.mark.parametrize("sensors, outputs, expect", [
    ("[{preset: vlp16, name: roof}, {preset: hdl32e, name: roof}]", "",
     "sensors: 'roof' is listed twice (at [0] and [1]); give each sensor its own name"),
    ("[{preset: vlp16}, {preset: VLP-16}]", "",  # both named by the preset's id
     "sensors: 'vlp16' is listed twice (at [0] and [1]); give each sensor its own name"),
    ("[{preset: vlp16}]", "outputs: {files: [npz, pcd, npz]}\n", "outputs.files: 'npz' is listed twice (at [0] and [2])"),
    ("[{preset: vlp16}]", "outputs: {rosbag: {boxes: [markers, markers]}}\n",
     "outputs.rosbag.boxes: 'markers' is listed twice (at [0] and [1])"),
])
def test_a_scenario_naming_a_sensor_or_output_twice(tmp_path, sensors, outputs, expect):
    sc = tmp_path / "sc.yaml"
    sc.write_text(f"name: sc\nscene: {{world: {{style: suburban}}}}\nsensors: {sensors}\n{outputs}")
    out = tmp_path / "r"
    msg = one_line(runner.invoke(app, ["replay", str(sc), "-o", str(out)]))
    assert msg == f"error: {sc}: {expect}"
    assert not out.exists()


def test_a_rig_naming_a_camera_twice(tmp_path, scene):
    rig = tmp_path / "rig.yaml"
    cam = "{name: FRONT, width: 8, height: 8, fx: 4, fy: 4, cx: 4, cy: 4}"
    rig.write_text(f"name: r\ncameras:\n- {cam}\n- {cam.replace('FRONT', 'LEFT')}\n- {cam}\n")
    out = tmp_path / "v.png"
    msg = one_line(runner.invoke(app, ["render", str(scene), "--rig", str(rig), "-o", str(out)]))
    assert msg == f"error: {rig}: cameras: camera names must be unique: 'FRONT' is listed twice (at [0] and [2])"
    assert not out.exists()


@pytest.mark.parametrize("sample, expect", [
    (f"images:\n  FRONT: {IMG}\n  LEFT: {IMG}\n", "images: file 'F.png' is listed twice (FRONT.file and LEFT.file)"),
    ((f"sweeps:\n  a: {{file: p.npz, timestamp: 0.0, sensor_to_world: {EYE}}}\n"
      f"  b: {{file: p.npz, timestamp: 0.0, sensor_to_world: {EYE}}}\n"),
     "sweeps: file 'p.npz' is listed twice (a.file and b.file)"),
    ((f"sweeps:\n  m: {{file: m.npz, timestamp: 0.0, sensor_to_world: {EYE}, origins: [{{sensor: top}}, "
      f"{{sensor: top, pose: {EYE}}}]}}\n"), "sweeps.m.origins: sensor 'top' is listed twice (at [0] and [1])"),
])
def test_a_folder_sample_naming_a_file_or_sensor_twice(tmp_path, sample, expect):
    root = _folder_dataset(tmp_path / "ds", sample)
    out = tmp_path / "scene.npz"
    msg = one_line(runner.invoke(app, ["build", str(root), "--dataset", "folder", "-o", str(out)]))
    assert msg == f"error: {root / 'samples/000000/sample.yaml'}: {expect}"
    assert not out.exists()


@pytest.mark.parametrize("args, expect", [
    (["--samples", "0,1,0"], "--samples: 0 is listed twice (at [0] and [2])"),
    (["--carve-with", "1,1"], "--carve-with: 1 is listed twice (at [0] and [1])"),
    (["--sensors", "top,top"], "--sensors: 'top' is listed twice (at [0] and [1])"),
])
def test_build_options_naming_a_sample_or_sensor_twice(tmp_path, args, expect):
    root = _folder_dataset(tmp_path / "ds", "")
    out = tmp_path / "scene.npz"
    msg = one_line(runner.invoke(app, ["build", str(root), "--dataset", "folder", "-o", str(out), *args]))
    assert msg == f"error: {expect}"
    assert not out.exists()


def test_worlds_generate_naming_a_rig_twice(tmp_path):
    out = tmp_path / "w"
    msg = one_line(runner.invoke(app, ["worlds", "generate", "-o", str(out), "--count", "1",
                                       "--rig", "waymo-5,nuscenes-6,Waymo5"]))
    assert msg == "error: worlds generate options: rigs: 'Waymo5' is listed twice (at [0] and [2])"
    assert not out.exists()


@pytest.mark.parametrize("job, setting, expect", [
    ("replay", "seeds=[1, 2, 1]", "batch replay settings: seeds: "),
    ("convert", "samples=[0, 0]", "batch convert settings: samples: "),
    ("build", "options={samples: [3, 3]}", "batch build settings: options.samples: 3 is listed twice (at [0] and [1])"),
])
def test_batch_settings_naming_a_seed_or_sample_twice(tmp_path, job, setting, expect):
    sc = _scenario(tmp_path, "")
    inp = str(sc) if job != "build" else str(_folder_dataset(tmp_path / "ds", ""))
    extra = ["--set", "dataset=folder"] if job in ("build", "convert") else []
    out = tmp_path / "campaign"
    msg = one_line(runner.invoke(app, ["batch", job, "-i", inp, "--set", setting, *extra, "-o", str(out),
                                       "--no-progress"]))
    assert msg.startswith(f"error: {expect}") and "is listed twice (at [0] and [" in msg
    assert not out.exists()


def test_schemas_refuse_a_list_naming_one_thing_twice():
    from scube_sim.reconstruct.config import EvidenceConfig
    from scube_sim.worlds.dataset import DatasetConfig

    with pytest.raises(ConfigError, match=r"^d: styles: 'urban' is listed twice \(at \[0\] and \[1\]\)$"):
        validate_model(DatasetConfig, {"styles": ["urban", "urban"]}, "d")
    with pytest.raises(ConfigError, match=r"^p: references: 0 is listed twice \(at \[0\] and \[2\]\)$"):
        validate_model(EvidenceConfig, {"references": [0, -3, 0]}, "p")


def test_a_profile_naming_a_stereo_reference_twice(tmp_path):
    prof = _write(tmp_path, "p.yaml", "route: evidence\nevidence: {references: [0, -3, 0]}\n")
    out = tmp_path / "c.npz"
    msg = one_line(runner.invoke(app, ["convert", str(tmp_path / "nowhere"), "--profile", str(prof), "-o", str(out)]))
    assert msg.startswith(f"error: {prof}") and "evidence.references" in msg and "0 is listed twice" in msg
    assert not out.exists()


@pytest.mark.parametrize("kind", ["emitter", "hesai_angles", "hesai_fire_times"])
def test_sensor_tables_naming_a_column_or_channel_twice(tmp_path, kind):
    from scube_sim.lidar.importers import from_hesai_csv
    from scube_sim.lidar.pattern import read_emitter_table

    if kind == "emitter":
        p = _write(tmp_path, "e.csv", "azimuth_deg,elevation_deg,azimuth_deg\n0,1,2\n")
        with pytest.raises(ConfigError, match=rf"^{p}: header: column 'azimuth_deg' is listed twice"):
            read_emitter_table(p)
    elif kind == "hesai_angles":
        p = _write(tmp_path, "a.csv", "Channel,Elevation,Azimuth,Elevation\n1,1,0,2\n2,-1,0,3\n")
        with pytest.raises(ConfigError, match=rf"^{p}: header: column 'Elevation' is listed twice"):
            from_hesai_csv(p, columns=100, rotation_hz=10.0)
    else:
        a = _write(tmp_path, "a.csv", "Channel,Elevation,Azimuth\n1,1,0\n2,-1,0\n")
        f = _write(tmp_path, "f.csv", "EEFF,x,x\nOperation Mode,2,2\nAngle State,0,0\n1,100,100\n1,200,200\n")
        with pytest.raises(ConfigError, match=rf"^{f}: row 5: channel 1 listed twice"):
            from_hesai_csv(a, f, columns=100, rotation_hz=10.0)
