"""Inputs whose errors used to name neither the file nor the key (a traceback, or a message from
deep inside a library): non-UTF-8 YAML, an image renamed .ply, a negative PLY element count,
trajectory poses of shape (T, 3, 4), a negative seed. Each now gives one line naming where it
came from and what was expected, with exit code 2 from the CLI."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from scube_sim.cli import app
from scube_sim.config import ConfigError, load_yaml
from scube_sim.errors import InputError
from scube_sim.io.ply3dgs import read_3dgs_ply
from scube_sim.sim.sources import TrajectorySource
from scube_sim.voxsplat import VoxSplat
from tests.conftest import one_line_error as one_line

runner = CliRunner()


@pytest.fixture
def scene(tmp_path):
    return VoxSplat(ijk=np.zeros((1, 3)), params=np.zeros((1, 1, 14)), voxel_size=0.1).save(tmp_path / "s.npz")


def test_non_utf8_yaml(tmp_path, scene):
    bad = tmp_path / "latin1.yaml"
    bad.write_bytes("name: caf\xe9\n".encode("latin-1"))
    with pytest.raises(ConfigError, match=r"latin1\.yaml: not UTF-8 text \(byte 0xe9 at offset 9\)"):
        load_yaml(bad)
    line = one_line(runner.invoke(app, ["lidar", str(scene), "--sensor", str(bad), "-o", str(tmp_path / "x.pcd")]))
    assert "latin1.yaml: not UTF-8" in line


def test_an_image_renamed_ply(tmp_path, scene):
    fake = tmp_path / "photo.ply"
    Image.new("RGB", (8, 8), (200, 10, 10)).save(fake, format="JPEG")
    with pytest.raises(InputError, match=r"photo\.ply: not a PLY file \(no 'ply' magic line\)"):
        read_3dgs_ply(fake)
    line = one_line(runner.invoke(app, ["lidar", str(fake), "--sensor", "vlp16", "-o", str(tmp_path / "x.pcd")]))
    assert "photo.ply: not a PLY file" in line


def test_a_negative_vertex_count(tmp_path):
    bad = tmp_path / "neg.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex -5\nproperty float x\nend_header\n")
    with pytest.raises(InputError, match=r"neg\.ply: malformed PLY header"):
        read_3dgs_ply(bad)


@pytest.mark.parametrize("shape", [(4, 3, 4), (3, 16), (2, 4, 4, 1)])
def test_trajectory_poses_of_the_wrong_shape(tmp_path, shape):
    """(4, 3, 4) holds 48 numbers, which a reshape would have turned into 3 wrong (4, 4) poses."""
    path = tmp_path / "traj.npz"
    np.savez(path, times=np.arange(shape[0], dtype=float), poses=np.zeros(shape))
    with pytest.raises(InputError, match=rf"traj\.npz: poses: expected shape \(T, 4, 4\), got \({shape[0]}, "):
        TrajectorySource.from_file(path)


def test_a_negative_seed(tmp_path, scene):
    line = one_line(runner.invoke(app, ["lidar", str(scene), "--sensor", "vlp16", "-o", str(tmp_path / "x.pcd"),
                                        "--seed", "-1"]))
    assert line == "error: --seed: expected an integer from 0 to 4294967295, got -1"
    assert not (tmp_path / "x.pcd").exists()
    scen = tmp_path / "s.yaml"
    scen.write_text("name: s\nseed: -2\nscene: {world: {style: suburban}}\nsensors: [{preset: vlp16}]\n")
    line = one_line(runner.invoke(app, ["replay", str(scen), "-o", str(tmp_path / "r")]))
    assert "s.yaml: seed: expected an integer from 0 to 4294967295, got -2" in line


def test_a_folder_where_a_file_is_expected(tmp_path, scene):
    """A folder given as the scenario said 'no such file'; a folder given as -o failed naming the
    temporary file beside it."""
    line = one_line(runner.invoke(app, ["replay", str(tmp_path), "-o", str(tmp_path / "r")]))
    assert line == f"error: {tmp_path}: is a folder; expected a YAML file"
    (tmp_path / "dir.npz").mkdir()
    line = one_line(runner.invoke(app, ["export", str(scene), "--to", "npz", "-o", str(tmp_path / "dir.npz")]))
    assert line == f"error: {tmp_path / 'dir.npz'}: is a folder; expected a file path"
    assert [p.name for p in (tmp_path / "dir.npz").iterdir()] == []
