"""Numbers without bounds where they enter (issue 46): every numeric option of every command and
every numeric key of the converter profiles, LiDAR sensors, scenarios and batch settings has its
valid range; a value outside it (NaN and infinity too) is one line naming the option or key and
the range, exit code 2, and nothing is written. Sizes that imply memory are checked against the
memory the machine has before anything is allocated."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from scube_sim import memory
from scube_sim.cli import app
from scube_sim.converter.profile import PROFILE_DIR
from scube_sim.errors import InputError
from tests.conftest import one_line_error as one_line

runner = CliRunner()
SEED_RANGE = "an integer from 0 to 4294967295"


def _files(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def _refused(tmp_path, argv, expected: str, inputs=()):
    """Run argv in-process: exit 2, one line equal to `error: EXPECTED` (or containing it), and no
    file appears under tmp_path besides the inputs."""
    before = _files(tmp_path)
    line = one_line(runner.invoke(app, argv))
    assert line.startswith("error: ") and expected in line, line
    assert _files(tmp_path) == before, f"stray output: {_files(tmp_path) - before}"
    return line


# --- command-line options: (command line before the option, option, value, the expected range) ---

def _cli_cases():
    conv = ["convert", "{t}/sample", "-o", "{t}/out.npz"]
    lidar = ["lidar", "{t}/s.npz", "--sensor", "vlp16", "-o", "{t}/out.pcd"]
    export = ["export", "{t}/s.ply", "--to", "npz", "-o", "{t}/out.npz"]
    render = ["render", "{t}/s.npz", "--rig", "waymo-5", "-o", "{t}/out.png"]
    gen = ["worlds", "generate", "-o", "{t}/ds"]
    prev = ["worlds", "preview", "-o", "{t}/pv"]
    demo = ["demo", "-o", "{t}/demo", "--no-convert"]
    replay = ["replay", "{t}/sc.yaml", "-o", "{t}/run"]
    batch = ["batch", "convert", "-i", "{t}/sample", "-o", "{t}/batch"]
    build = ["build", "{t}/data", "-d", "folder", "-o", "{t}/out.npz"]
    fid = ["fidelity", "{t}/data", "-d", "folder", "--scene", "{t}/s.npz", "-o", "{t}/fid"]
    train = ["train", "geometry", "--data", "{t}/data", "-c", "x.yaml", "-o", "{t}/run"]
    ev = ["eval", "sensor-to-sensor", "--data", "{t}/data", "-o", "{t}/m.json"]
    return [
        (conv, "--sample", "-1", "an integer >= 0"),
        (conv, "--steps", "0", "an integer from 1 to 1000"),
        (conv, "--steps", "-5", "an integer from 1 to 1000"),
        (conv, "--steps", "1001", "an integer from 1 to 1000"),
        (conv, "--seed", "-1", SEED_RANGE),
        (conv, "--seed", str(2**32), SEED_RANGE),
        (conv, "--confidence", "65", "an integer from 0 to 64"),
        (conv, "--confidence", "-1", "an integer from 0 to 64"),
        (conv, "--max-range", "0", "a finite number > 0 and <= 10000 (metres)"),
        (conv, "--max-range", "nan", "a finite number > 0 and <= 10000 (metres)"),
        (conv, "--max-range", "inf", "a finite number > 0 and <= 10000 (metres)"),
        (conv, "--context", "101", "an integer from 0 to 100"),
        (conv, "--context", "-1", "an integer from 0 to 100"),
        (conv, "--fit-steps", "-1", "an integer from 0 to 10000"),
        (conv, "--fit-steps", "1000000", "an integer from 0 to 10000"),
        (lidar, "--threads", "-1", "an integer from 0 to 1024"),
        (lidar, "--k", "0", "a finite number > 0 and <= 10"),
        (lidar, "--k", "nan", "a finite number > 0 and <= 10"),
        (lidar, "--soft-alpha-min", "1", "a finite number >= 0 and < 1"),
        (lidar, "--seed", "-1", SEED_RANGE),
        (export, "--voxel-size", "0", "a finite number >= 0.001 and <= 100 (metres)"),
        (export, "--voxel-size", "-0.5", "a finite number >= 0.001 and <= 100 (metres)"),
        (export, "--voxel-size", "nan", "a finite number >= 0.001 and <= 100 (metres)"),
        (export, "--max-gaussians", "0", "an integer >= 1"),
        (render, "--scale", "0", "a finite number > 0 and <= 1"),
        (render, "--scale", "inf", "a finite number > 0 and <= 1"),
        (gen, "--count", "-1", "an integer from 0 to 1000000"),
        (gen, "--start", "-1", "an integer from 0 to 999999"),
        (gen, "--jobs", "0", "an integer from 1 to 1024"),
        (gen, "--image-scale", "0", "a finite number > 0 and <= 1"),
        (gen, "--fine-voxel", "nan", "a finite number >= 0.05 and <= 1.6 (metres)"),
        (gen, "--coarse-factor", "0", "an integer from 1 to 16"),
        (prev, "--seed", "-3", SEED_RANGE),
        (demo, "--voxel-size", "0", "a finite number > 0.01 and <= 5 (metres)"),
        (demo, "--seed", "-1", SEED_RANGE),
        (replay, "--duration", "0", "a finite number > 0 and <= 86400 (seconds)"),
        (replay, "--duration", "inf", "a finite number > 0 and <= 86400 (seconds)"),
        (replay, "--seed", "-1", SEED_RANGE),
        (batch, "--workers", "0", "an integer from 1 to 1024"),
        (batch, "--retries", "-1", "an integer from 0 to 100"),
        (batch, "--threads", "0", "an integer from 1 to 1024"),
        (build, "--voxel-size", "0", "a finite number >= 0.001 and <= 100 (metres)"),
        (build, "--gaussians-per-voxel", "0", "an integer from 1 to 16"),
        (build, "--patch-scale", "0", "a finite number > 0 and <= 10"),
        (build, "--max-patch-sigma", "nan", "a finite number > 0 and <= 10 (metres)"),
        (build, "--max-normal-scale", "-1", "a finite number > 0 and <= 10 (metres)"),
        (build, "--mesh-max-edge-rel", "inf", "a finite number > 0 and <= 10"),
        (fid, "--sample", "-1", "an integer >= 0"),
        (train, "--ranks", "0", "an integer from 1 to 256"),
        (ev, "--context", "-1", "an integer from 0 to 100"),
        (ev, "--limit", "0", "an integer >= 1"),
        (ev, "--gt-voxel", "0", "a finite number >= 0.05 and <= 1.6 (metres)"),
        (ev, "--seed", "-1", SEED_RANGE),
    ]


@pytest.mark.parametrize("argv, option, value, expected", _cli_cases(),
                         ids=[f"{c[0][0]}{c[1]}={c[2]}" for c in _cli_cases()])
def test_numeric_options_name_the_option_and_range(tmp_path, argv, option, value, expected):
    argv = [a.format(t=tmp_path) for a in argv] + [option, value]
    line = _refused(tmp_path, argv, "")
    got = {"nan": "nan", "inf": "inf"}.get(value)
    shown = got if got is not None else (repr(float(value)) if "." in value or option in _FLOAT_OPTIONS else value)
    assert line == f"error: {option}: expected {expected}, got {shown}"


_FLOAT_OPTIONS = {"--max-range", "--k", "--soft-alpha-min", "--voxel-size", "--scale", "--image-scale", "--fine-voxel",
                  "--duration", "--patch-scale", "--max-patch-sigma", "--max-normal-scale", "--mesh-max-edge-rel",
                  "--gt-voxel"}


def test_every_numeric_option_has_its_range():
    """Each int or float option of every command (sub-apps too) is bounded: its help says its range."""
    import inspect
    import typing

    unbounded, checked = [], []

    def walk(typer_app, prefix):
        for info in typer_app.registered_commands:
            fn = inspect.unwrap(info.callback)
            hints = typing.get_type_hints(fn)
            for name, param in inspect.signature(fn).parameters.items():
                tp = hints[name]
                args = [a for a in typing.get_args(tp) if a is not type(None)]
                if tp in (int, float) or (args and args[0] in (int, float) and len(args) == 1):
                    checked.append(name)
                    if "(valid:" not in (getattr(param.default, "help", None) or ""):
                        unbounded.append(f"{' '.join(prefix + [info.name or fn.__name__])} {name}")
        for group in typer_app.registered_groups:
            walk(group.typer_instance, prefix + [group.name])

    walk(app, [])
    assert len(checked) >= 40 and not unbounded, (len(checked), unbounded)


def test_sample_index_lists_are_non_negative(tmp_path):
    for opt in ("--samples", "--carve-with"):
        line = _refused(tmp_path, ["build", str(tmp_path / "data"), "-d", "folder", "-o", str(tmp_path / "o.npz"),
                                   opt, "0,-1"], "")
        assert line == f"error: {opt}: expected comma-separated sample indices >= 0, got '0,-1'"


# --- converter profiles ---------------------------------------------------------------------

def _profile(tmp_path, name="cpu", **edits) -> Path:
    data = yaml.safe_load((PROFILE_DIR / f"{name}.yaml").read_text())
    for key, value in edits.items():
        node = data
        *parents, leaf = key.split(".")
        for k in parents:
            node = node.setdefault(k, {})
        node[leaf] = value
    path = tmp_path / "bad-profile.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


PROFILE_CASES = [
    ("cpu", "appearance.sky_size", [0, 0], "appearance.sky_size[0]: expected an integer from 8 to 8192, got 0"),
    ("cpu", "appearance.sky_size", [100000, 200000],
     "appearance.sky_size[0]: expected an integer from 8 to 8192, got 100000"),
    ("cpu", "appearance.fit_steps", 10001, "appearance.fit_steps: expected an integer from 0 to 10000, got 10001"),
    ("cpu", "appearance.focal_px", math.inf, "appearance.focal_px: expected a finite number > 0 and <= 100000, got inf"),
    ("cpu", "appearance.max_scale_voxels", math.nan, ("appearance.max_scale_voxels: expected a finite number > 0 and "
                                                     "<= 100, got nan")),
    ("cpu", "appearance.gaussians_per_voxel", 0, "appearance.gaussians_per_voxel: expected an integer from 1 to 64"),
    ("cpu", "geometry.sample_steps", 0, "geometry.sample_steps: expected an integer from 1 to 1000, got 0"),
    ("cpu", "geometry.max_side", 100000, "geometry.max_side: expected an integer from 16 to 8192, got 100000"),
    ("cpu", "context", 101, "context: expected an integer from 0 to 100, got 101"),
    ("cpu", "confidence_samples", 1000, "confidence_samples: expected an integer from 2 to 64, got 1000"),
    ("evidence", "evidence.fusion.voxel_size", 0, ("evidence.fusion.voxel_size: expected a finite number >= 0.01 and "
                                                   "<= 10, got 0")),
    ("evidence", "evidence.stereo.hypotheses", 10**6, "evidence.stereo.hypotheses: expected an integer from 3 to 4096"),
    ("evidence", "evidence.ground_band_m", math.inf, "evidence.ground_band_m: expected a finite number > 0, got inf"),
    ("evidence", "evidence.gaussians_per_voxel", 100, "evidence.gaussians_per_voxel: expected an integer from 1 to 16"),
]


@pytest.mark.parametrize("base, key, value, expected", PROFILE_CASES, ids=[f"{c[1]}={c[2]}" for c in PROFILE_CASES])
def test_profile_numbers_name_the_file_key_and_range(tmp_path, base, key, value, expected):
    path = _profile(tmp_path, base, **{key: value})
    line = _refused(tmp_path, ["convert", str(tmp_path / "sample"), "-o", str(tmp_path / "out.npz"),
                               "--profile", str(path)], f"{path}: {expected}")
    assert "Traceback" not in line


def test_a_sky_panorama_larger_than_memory_is_refused_before_allocating(tmp_path, monkeypatch):
    monkeypatch.setattr(memory, "available_bytes", lambda: 1 << 30)  # a machine with 1 GB free
    path = _profile(tmp_path, **{"appearance.sky_size": [4096, 8192]})
    line = _refused(tmp_path, ["convert", str(tmp_path / "sample"), "-o", str(tmp_path / "out.npz"),
                               "--profile", str(path)], "")
    assert line == (f"error: {path}: appearance: sky_size [4096, 8192] = 33,554,432 panorama pixels (~384 bytes each "
                    f"while decoded) needs about 12.0 GB of memory; 1.0 GB is available")


# --- LiDAR sensors --------------------------------------------------------------------------

SENSOR = {"name": "s", "pattern": {"type": "spinning", "columns": 360, "rotation_hz": 10,
                                   "channels": {"elevation_deg": [-1.0, 0.0, 1.0]}}}

SENSOR_CASES = [
    ("pattern.start_azimuth_deg", math.inf, ("pattern.start_azimuth_deg: expected a finite number >= -360 and <= 360, "
                                            "got inf")),
    ("pattern.start_azimuth_deg", 720, "pattern.start_azimuth_deg: expected a finite number >= -360 and <= 360"),
    ("pattern.rotation_hz", math.nan, "pattern.rotation_hz: expected a finite number > 0 and <= 100, got nan"),
    ("pattern.columns", 0, "pattern.columns: expected an integer > 0 and <= 100000, got 0"),
    ("range.max_m", math.inf, "range.max_m: expected a finite number > 0 and <= 10000, got inf"),
    ("noise.range_sigma_m", math.nan, "noise.range_sigma_m: expected a finite number >= 0 and <= 10, got nan"),
    ("beam.samples", 65, "beam.samples: expected an integer from 1 to 64, got 65"),
    ("beam.divergence_mrad", math.inf, "beam.divergence_mrad: expected a finite number >= 0 and <= 100, got inf"),
    ("mount.xyz", [0.0, 0.0, math.inf], "mount.xyz[2]: expected a finite number, got inf"),
    ("intensity.reference_range_m", -1.0, "intensity.reference_range_m: expected a finite number > 0, got -1.0"),
]


def _sensor(tmp_path, key, value) -> Path:
    data = yaml.safe_load(yaml.safe_dump(SENSOR))
    node = data
    *parents, leaf = key.split(".")
    for k in parents:
        node = node.setdefault(k, {})
    node[leaf] = value
    path = tmp_path / "bad-sensor.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("key, value, expected", SENSOR_CASES, ids=[f"{c[0]}={c[1]}" for c in SENSOR_CASES])
def test_sensor_numbers_name_the_file_key_and_range(tmp_path, key, value, expected):
    path = _sensor(tmp_path, key, value)
    _refused(tmp_path, ["lidar", str(tmp_path / "s.npz"), "--sensor", str(path), "-o", str(tmp_path / "out.pcd")],
             f"error: {path}: {expected}")


def test_a_sweep_larger_than_memory_is_refused_before_tracing(tmp_path, monkeypatch):
    monkeypatch.setattr(memory, "available_bytes", lambda: 1 << 20)  # 1 MB free: 360 x 64 x 64 B is 1.4 MB
    path = _sensor(tmp_path, "pattern.channels.elevation_deg", [float(e) for e in range(-32, 32)])
    line = _refused(tmp_path, ["lidar", str(tmp_path / "s.npz"), "--sensor", str(path), "-o",
                               str(tmp_path / "out.pcd")], "")
    assert line == (f"error: {path}: (top level): pattern.columns 360 x 64 channels x beam.samples 1 = 23,040 traced rays per "
                    f"sweep needs about 1.4 MB of memory; 1.0 MB is available")


# --- scenarios and batch settings -----------------------------------------------------------

SCENARIO = {"name": "t", "scene": {"world": {"style": "urban", "seed": 1}}, "sensors": [{"preset": "vlp16"}]}

SCENARIO_CASES = [
    ("seed", -1, f"seed: expected {SEED_RANGE}, got -1"),
    ("seed", 2**40, f"seed: expected {SEED_RANGE}, got {2**40}"),
    ("duration_s", math.inf, "duration_s: expected a finite number > 0 and <= 86400, got inf"),
    ("tick_hz", math.nan, "tick_hz: expected a finite number > 0 and <= 1000, got nan"),
    ("scene.voxel_size", 0, "scene.voxel_size: expected a finite number > 0.01 and <= 5, got 0"),
    ("scene.world.seed", -1, f"scene.world.seed: expected {SEED_RANGE}, got -1"),
    ("scene.world.length_m", math.inf, "scene.world.length_m: expected a finite number > 20 and <= 5000, got inf"),
    ("trajectory.rate_hz", 1e9, "trajectory.rate_hz: expected a finite number > 0 and <= 1000, got 1000000000.0"),
    ("sensors", [{"preset": "vlp16", "rate_hz": 0}], "sensors[0].rate_hz: expected a finite number > 0 and <= 1000"),
    ("sensors", [{"preset": "vlp16", "phase_s": math.nan}], "sensors[0].phase_s: expected a finite number, got nan"),
]


@pytest.mark.parametrize("key, value, expected", SCENARIO_CASES, ids=[f"{c[0]}={c[1]}" for c in SCENARIO_CASES])
def test_scenario_numbers_name_the_file_key_and_range(tmp_path, key, value, expected):
    data = yaml.safe_load(yaml.safe_dump(SCENARIO))
    node = data
    *parents, leaf = key.split(".")
    for k in parents:
        node = node.setdefault(k, {})
    node[leaf] = value
    path = tmp_path / "sc.yaml"
    path.write_text(yaml.safe_dump(data))
    _refused(tmp_path, ["replay", str(path), "-o", str(tmp_path / "run")], f"error: {path}: {expected}")


BATCH_CASES = [
    ("convert", ["steps=0"], "batch convert settings: steps: expected an integer from 1 to 1000, got 0"),
    ("convert", ["seed=-1"], f"batch convert settings: seed: expected {SEED_RANGE}, got -1"),
    ("convert", ["confidence=100"], "batch convert settings: confidence: expected an integer from 0 to 64, got 100"),
    ("convert", ["max_range=.nan"], ("batch convert settings: max_range: expected a finite number > 0 and <= 10000, "
                                    "got nan")),
    ("convert", ["samples=[0, -2]"], "batch convert settings: samples.1: expected an integer >= 0, got -2"),
    ("replay", ["seeds=[1, -1]"], f"batch replay settings: seeds.1: expected {SEED_RANGE}, got -1"),
    ("replay", ["duration_s=.inf"], ("batch replay settings: duration_s: expected a finite number > 0 and <= 86400, "
                                    "got inf")),
    ("build", ["dataset=folder", "options={voxel_size: 0}"],
     "batch build settings: options.voxel_size: expected a finite number >= 0.001 and <= 100 (metres), got 0"),
    ("build", ["dataset=folder", "options={gaussians_per_voxel: 99}"],
     "batch build settings: options.gaussians_per_voxel: expected an integer from 1 to 16, got 99"),
    ("build", ["dataset=folder", "options={samples: [-1]}"],
     "batch build settings: options.samples[0]: expected an integer >= 0, got -1"),
]


@pytest.mark.parametrize("job, sets, expected", BATCH_CASES, ids=[f"{c[0]}:{c[1][-1]}" for c in BATCH_CASES])
def test_batch_settings_name_the_key_and_range(tmp_path, job, sets, expected):
    argv = ["batch", job, "-i", str(tmp_path / "in"), "-o", str(tmp_path / "batch")]
    for s in sets:
        argv += ["--set", s]
    line = _refused(tmp_path, argv, "")
    assert line == f"error: {expected}"


# --- the API behind the options -------------------------------------------------------------

def test_export_voxel_size_zero_is_an_error_not_automatic():
    import numpy as np

    from scube_sim.scene_file import as_voxsplat
    from scube_sim.voxsplat import Gaussians

    g = Gaussians(means=np.zeros((2, 3)), scales=np.full((2, 3), 0.1), quats=np.tile([1.0, 0, 0, 0], (2, 1)),
                  opacities=np.full(2, 0.5), sh_dc=np.zeros((2, 3), np.float32))
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(InputError, match=r"voxel_size: expected a finite number >= 0\.001 and <= 100"):
            as_voxsplat(g, bad)
    assert as_voxsplat(g, None).voxel_size > 0


def test_build_options_check_their_ranges():
    from scube_sim.realdata.build import BuildOptions

    with pytest.raises(InputError, match=r"^mesh_max_angle_deg: expected a finite number > 0 and <= 90 \(degrees\), "
                                         r"got 0$"):
        BuildOptions(samples=[0], mesh_max_angle_deg=0)
    assert BuildOptions(samples=[0]).voxel_size == 0.1
