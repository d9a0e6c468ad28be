"""Frames over time: the instants around a reference in the same log, never across a log or scene
boundary and never past the log's ends; the converter records what it was given."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from scube_sim.camera.frames import CameraImage, Frames
from scube_sim.camera.model import Intrinsics
from scube_sim.datasets import open_dataset
from scube_sim.datasets.base import Sample, frames_with_context
from scube_sim.datasets.folder import write_folder_dataset
from scube_sim.datasets.nuscenes import scene_logs
from scube_sim.errors import InputError


def _image(name="FRONT", t=0.0) -> CameraImage:
    return CameraImage(name, np.zeros((4, 6, 3), np.uint8), Intrinsics(fx=5, fy=5, cx=3, cy=2, width=6, height=4),
                       np.eye(4), t)


def _pose(x: float) -> np.ndarray:
    p = np.eye(4)
    p[0, 3] = x
    return p


@dataclass
class _Log:
    """A dataset of logs ['a'] * 3 + ['b'] * 2 (samples 1 m and 0.1 s apart), counting loads."""

    logs: list = field(default_factory=lambda: ["a", "a", "a", "b", "b"])
    loads: list = field(default_factory=list)
    name: str = "toy"
    root: Path = Path("toy")

    def __len__(self):
        return len(self.logs)

    def __getitem__(self, i):
        self.loads.append(i)
        t = 0.1 * i
        frames = Frames([_image(t=t)], _pose(float(i)), t)
        return Sample(f"s{i}", t, _pose(float(i)), frames=frames, log=self.logs[i])


def test_frames_with_context_carry_offsets_poses_and_the_log():
    ds = _Log()
    f = frames_with_context(ds, 2, 2)
    assert [c.offset for c in f.context] == [-2, -1] and f.offset == 0 and f.log == "a"
    assert [c.log for c in f.context] == ["a", "a"]
    np.testing.assert_array_equal([c.ego_pose[0, 3] for c in f.context], [0.0, 1.0])
    assert [i.offset for i in f.instants()] == [-2, -1, 0]
    assert 4 not in ds.loads  # the walk stops at the first sample of another log
    f = frames_with_context(_Log(), 3, 3)
    assert [c.offset for c in f.context] == [1]  # the end of the set, and log "a" before it
    assert [c.offset for c in frames_with_context(_Log(), 0, 3).context] == [1, 2]  # the start of the set
    assert frames_with_context(_Log(), 1, 0).context == []
    with pytest.raises(InputError, match="context"):
        frames_with_context(_Log(), 1, -1)


def test_a_context_frame_from_another_log_is_refused():
    other = Frames([_image()], _pose(1.0), 0.1, log="drive-2", offset=1)
    with pytest.raises(InputError, match="from log 'drive-2', not the reference's 'drive-1'"):
        Frames([_image()], np.eye(4), 0.0, log="drive-1", context=[other])
    same = Frames([_image()], _pose(1.0), 0.1, log="drive-1", offset=0)
    with pytest.raises(InputError, match="non-zero and distinct"):
        Frames([_image()], np.eye(4), 0.0, log="drive-1", context=[same])


@dataclass
class _Entry:
    index: int
    token: str
    timestamp: float
    ego2global: np.ndarray


def test_nuscenes_scenes_split_where_keyframes_jump_in_time_or_space():
    e = [_Entry(0, "a", 0.0, _pose(0)), _Entry(1, "b", 0.5, _pose(4)), _Entry(2, "c", 20.0, _pose(8)),
         _Entry(3, "d", 20.5, _pose(500)), _Entry(4, "e", 21.0, _pose(504))]
    assert scene_logs(e, [None] * 5) == ["scene@a", "scene@a", "scene@c", "scene@d", "scene@d"]
    # an info file that names its scenes is taken at its word
    assert scene_logs(e, ["s1", "s2", "s2", "s2", None]) == ["scene-token:s1", "scene-token:s2", "scene-token:s2",
                                                              "scene-token:s2", "scene@e"]


def test_the_folder_format_keeps_the_log(tmp_path):
    ds = _Log()
    write_folder_dataset([ds[i] for i in range(len(ds))], tmp_path / "f", name="toy")
    back = open_dataset("folder", tmp_path / "f")
    assert [back[i].log for i in range(len(back))] == ds.logs
    f = frames_with_context(back, 1, 5)
    assert [c.offset for c in f.context] == [-1, 1]


def test_a_conversion_with_context_is_the_same_scene_and_records_the_instants(tiny_converter):
    from scube_sim.converter.frames import open_frames
    from scube_sim.converter.pipeline import Converter

    conv = Converter(tiny_converter["profile"])
    plain = conv.convert(open_frames(tiny_converter["sample"]), sky=False).scene
    frames = open_frames(tiny_converter["sample"])
    neighbour = Frames(frames.images, frames.ego_pose, frames.timestamp + 0.1, log=frames.log, offset=1)
    frames.context = [neighbour]
    with_context = conv.convert(frames, sky=False).scene
    np.testing.assert_array_equal(with_context.params, plain.params)
    np.testing.assert_array_equal(with_context.ijk, plain.ijk)
    assert "instants" not in plain.metadata  # one instant: the metadata of before
    assert [i["offset"] for i in with_context.metadata["instants"]] == [0, 1]
    assert with_context.metadata["instants"][1]["cameras"] == frames.names


def test_convert_context_on_a_real_drive_records_its_neighbours(tiny_converter, shared_data, tmp_path):
    """KITTI raw (3 consecutive frames, poses by ICP): --context 1 at the middle frame gives the
    converter the frames before and after it; the scene is that of --context 0."""
    from typer.testing import CliRunner

    from scube_sim.cli import app
    from scube_sim.voxsplat import VoxSplat

    from ..conftest import require

    drive = require(shared_data / "kitti-raw-2011_09_26-udacity")
    out = {}
    for k in (0, 1):
        r = CliRunner().invoke(app, ["convert", str(drive), "--dataset", "kitti_raw", "--sample", "1", "--context",
                                     str(k), "--profile", str(tiny_converter["profile"]), "--no-sky",
                                     "-o", str(tmp_path / f"c{k}.npz")])
        assert r.exit_code == 0, r.output
        out[k] = VoxSplat.load(tmp_path / f"c{k}.npz")
    assert "(+2 context instant(s))" in r.output
    inst = out[1].metadata["instants"]
    assert [i["offset"] for i in inst] == [-1, 0, 1]
    assert np.all(np.diff([i["timestamp"] for i in inst]) > 0.05)  # 10 Hz
    np.testing.assert_array_equal(out[1].params, out[0].params)
    r = CliRunner().invoke(app, ["convert", str(drive), "--dataset", "kitti_raw", "--context", "-1",
                                 "--profile", str(tiny_converter["profile"]), "-o", str(tmp_path / "x.npz")])
    assert r.exit_code == 2 and "--context" in r.output
