"""A ROS 2 bag survives a real SIGKILL of the process writing it: the rosbags reader opens what a
killed `RosbagSink` left, directly (a kill between commits) or after one `scube-sim bag-reindex`
(a kill inside a commit's writes), and reads back exactly the messages of the frames committed,
byte for byte, as an uninterrupted run wrote them."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("rosbags")
pytest.importorskip("mcap_ros2")
from rosbags.rosbag2 import Reader  # noqa: E402
from typer.testing import CliRunner  # noqa: E402

from scube_sim.cli import app  # noqa: E402
from scube_sim.sim.sinks.rosbag import RosbagSink  # noqa: E402
from tests.sim.test_rosbag import make_frames, run_info  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SEED, N_FRAMES = 7, 24

# The writer: a sink fed the same frames as the reference, one line after each frame's write
# returned; it then sleeps until killed. With a 5th argument k, the commit of frame k+1 stops
# (and says so) after the chunk's write and before the summary's.
DRIVER = f"""
import sys, time
sys.path.insert(0, {str(ROOT)!r})
import numpy as np
from tests.sim.test_rosbag import make_frames, run_info
from scube_sim.sim.sinks.rosbag import RosbagSink
frames = make_frames(np.random.default_rng({SEED}), n_ticks={N_FRAMES})
sink = RosbagSink(sys.argv[1], compression=sys.argv[3])
sink.open(run_info())
print("opened", flush=True)
if len(sys.argv) > 4:
    def stuck(close_chunk=sink._close_chunk):
        close_chunk()
        if sink._data_end is not None and done == int(sys.argv[4]):
            print("flushed mid-commit", flush=True)
            time.sleep(120)
    sink._close_chunk = stuck
for i, f in enumerate(frames[:int(sys.argv[2])]):
    done = i
    sink.write(f)
    print("flushed", i + 1, flush=True)
time.sleep(120)
"""


def one_line(res) -> str:
    lines = [x for x in res.output.splitlines() if x.strip()]
    assert len(lines) == 1, res.output
    return lines[0]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """Per compression: the uninterrupted bag's messages per topic [(time ns, raw bytes)], the
    per-topic counts after each frame's write (from the metadata.yaml each commit writes), and the
    MCAP and metadata.yaml as each commit left them with where its data ended."""
    out = {}
    for compression in ("none", "zstd"):
        folder = tmp_path_factory.mktemp("ref") / "bag"
        frames = make_frames(np.random.default_rng(SEED), n_ticks=N_FRAMES)
        sink = RosbagSink(folder, compression=compression)
        sink.open(run_info())
        mcap, meta = folder / "bag.mcap", folder / "metadata.yaml"
        counts, states = [topic_counts(folder)], [(mcap.read_bytes(), meta.read_text(), sink._data_end)]
        for f in frames:
            sink.write(f)
            counts.append(topic_counts(folder))
            states.append((mcap.read_bytes(), meta.read_text(), sink._data_end))
        sink.close()
        out[compression] = (read(folder), counts, states)
    return out


def topic_counts(folder: Path) -> dict[str, int]:
    info = yaml.safe_load((folder / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    return {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]}


def read(folder: Path) -> dict[str, list[tuple[int, bytes]]]:
    """topic -> [(time ns, raw bytes)] through the rosbags reader, which must agree with its own
    metadata (message count per topic and in all)."""
    out: dict[str, list] = {}
    with Reader(folder) as reader:
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t, bytes(raw)))
        assert sum(map(len, out.values())) == reader.message_count
        assert {c.topic: c.msgcount for c in reader.connections if c.msgcount} == {k: len(v) for k, v in out.items()}
    return out


def check_frames(got: dict, ref: dict, counts: list[dict]) -> int:
    """The number m of frames whose messages `got` holds: exactly those of an uninterrupted run's
    first m frames, in order, byte for byte."""
    have = {k: len(v) for k, v in got.items()}
    m = next((m for m, c in enumerate(counts) if {k: v for k, v in c.items() if v} == have), None)
    assert m is not None, f"not the messages of a whole number of frames: {have}"
    for topic, msgs in got.items():
        assert msgs == ref[topic][: len(msgs)], topic
    return m


def kill_after(folder: Path, flushed: int | str, write: int, compression: str, *extra: str) -> None:
    """Run the writer in a subprocess, SIGKILL it as soon as it reports `flushed` frames written
    (it goes on writing up to `write` frames meanwhile)."""
    proc = subprocess.Popen([sys.executable, "-c", DRIVER, str(folder), str(write), compression, *extra],
                            stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        for line in proc.stdout:
            if line.split() == ["flushed", str(flushed)]:
                break
        else:
            pytest.fail("the writer ended before it wrote the frames asked")
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(timeout=30)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_a_bag_killed_between_frames_opens_as_it_is(tmp_path, reference, compression):
    ref, counts, _ = reference[compression]
    folder = tmp_path / "bag"
    kill_after(folder, 5, 5, compression)  # killed while it waits after its 5th frame
    got = read(folder)  # no recovery step
    assert check_frames(got, ref, counts) == 5
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    res = CliRunner().invoke(app, ["bag-reindex", str(folder)])
    assert res.exit_code == 0 and one_line(res) == (f"{folder}: reads as it is ({sum(counts[5].values())} messages "
                                                    "in 6 chunks); nothing to do")
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before  # not a byte changed
    assert sorted(before) == ["bag.mcap", "metadata.yaml"]  # no temporary file left either


@pytest.mark.parametrize("flushed", [2, 9, 17])
def test_a_bag_killed_mid_run_opens_directly_or_after_one_reindex(tmp_path, reference, flushed):
    ref, counts, _ = reference["none"]
    folder = tmp_path / "bag"
    kill_after(folder, flushed, N_FRAMES, "none")  # killed while it goes on writing
    try:
        got = read(folder)
    except Exception:  # noqa: BLE001 - killed inside a commit: the documented recovery
        res = CliRunner().invoke(app, ["bag-reindex", str(folder)])
        assert res.exit_code == 0, res.output
        assert "summary and metadata.yaml rewritten" in one_line(res)
        got = read(folder)
    assert check_frames(got, ref, counts) >= flushed
    assert not [p.name for p in folder.iterdir() if p.name not in ("bag.mcap", "metadata.yaml")]


def test_a_bag_killed_inside_a_commit_reads_after_one_reindex(tmp_path, reference):
    ref, counts, _ = reference["none"]
    folder = tmp_path / "bag"
    kill_after(folder, "mid-commit", N_FRAMES, "none", "8")  # frame 9's chunk written, no summary yet
    with pytest.raises(Exception, match="magic"):
        Reader(folder).open()
    res = CliRunner().invoke(app, ["bag-reindex", str(folder)])
    assert res.exit_code == 0 and one_line(res).endswith("summary and metadata.yaml rewritten")
    assert check_frames(read(folder), ref, counts) in (8, 9)  # 9 where the chunk reached the file whole


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_reindex_recovers_every_moment_a_commit_can_be_cut_at(tmp_path, reference, compression):
    """A kill inside commit k+1 leaves commit k's data (its metadata.yaml too, written atomically)
    followed by any prefix of what commit k+1 writes: its chunk, message indexes, summary and
    footer. bag-reindex gives the k frames, or k+1 once their chunk and indexes are whole."""
    ref, counts, states = reference[compression]
    k = 6
    (old, old_meta, old_end), (new, _, new_end) = states[k], states[k + 1]
    assert new[:old_end] == old[:old_end]
    n = len(new) - old_end
    cuts = sorted({0, 1, 8, 9, 20, new_end - old_end - 40, new_end - old_end - 1, new_end - old_end,
                   new_end - old_end + 1, new_end - old_end + 9, (new_end - old_end + n) // 2, n - 8, n - 1, n})
    cuts += [int(c) for c in np.random.default_rng(1).integers(0, n, 4)]
    for cut in cuts:
        folder = tmp_path / f"cut{cut}"
        folder.mkdir()
        (folder / f"cut{cut}.mcap").write_bytes(new[: old_end + cut])
        info = yaml.safe_load(old_meta)
        info["rosbag2_bagfile_information"]["relative_file_paths"] = [f"cut{cut}.mcap"]
        (folder / "metadata.yaml").write_text(yaml.safe_dump(info))
        if cut < n:
            with pytest.raises(Exception, match="magic|[Ff]ooter|summary"):
                Reader(folder).open()  # as the kill left it: unreadable
        else:  # killed between the MCAP's commit and metadata.yaml's: they disagree
            with pytest.raises(AssertionError):
                read(folder)
        res = CliRunner().invoke(app, ["bag-reindex", str(folder)])
        assert res.exit_code == 0, res.output
        whole = cut >= new_end - old_end
        cut_bytes = cut - (new_end - old_end if whole else 0)
        assert one_line(res) == (f"{folder}: {sum(counts[k + whole].values())} messages in {k + 2 + whole - 1} "
                                 f"chunks" + (f"; cut {cut_bytes} bytes of an unfinished write" if cut_bytes else "")
                                 + "; summary and metadata.yaml rewritten")
        assert check_frames(read(folder), ref, counts) == k + whole
        if cut in (0, n):
            again = CliRunner().invoke(app, ["bag-reindex", str(folder)])
            assert "reads as it is" in one_line(again)
        shutil.rmtree(folder)


def test_reindex_keeps_the_topics_qos_hashes_and_custom_data(tmp_path, reference):
    _, _, states = reference["none"]
    data, meta, end = states[4]
    folder = tmp_path / "bag"
    folder.mkdir()
    (folder / "bag.mcap").write_bytes(data[: end + 5])
    (folder / "metadata.yaml").write_text(meta)
    assert CliRunner().invoke(app, ["bag-reindex", str(folder)]).exit_code == 0
    assert yaml.safe_load((folder / "metadata.yaml").read_text()) == yaml.safe_load(meta)
    (folder / "metadata.yaml").unlink()  # torn or lost: rebuilt from the MCAP alone (hashes from the typestore)
    (folder / "bag.mcap").write_bytes(data[: end + 5])
    assert CliRunner().invoke(app, ["bag-reindex", str(folder)]).exit_code == 0
    rebuilt = yaml.safe_load((folder / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    want = yaml.safe_load(meta)["rosbag2_bagfile_information"]
    assert rebuilt["topics_with_message_count"] == want["topics_with_message_count"]
    assert rebuilt["custom_data"] is None and rebuilt["message_count"] == want["message_count"]


def test_reindex_refuses_what_it_does_not_rebuild_and_changes_nothing(tmp_path):
    from mcap.writer import Writer

    runner = CliRunner()
    res = runner.invoke(app, ["bag-reindex", str(tmp_path / "none")])
    assert res.exit_code == 2 and one_line(res) == (f"error: {tmp_path / 'none'}: no such bag folder (a rosbag2 "
                                                    "folder: metadata.yaml and an .mcap)")
    (tmp_path / "empty").mkdir()
    res = runner.invoke(app, ["bag-reindex", str(tmp_path / "empty")])
    assert res.exit_code == 2 and one_line(res) == f"error: {tmp_path / 'empty'}: expected one .mcap file in the " \
                                                   "bag folder, found 0"
    (tmp_path / "text").mkdir()
    (tmp_path / "text" / "text.mcap").write_text("not a bag")
    res = runner.invoke(app, ["bag-reindex", str(tmp_path / "text")])
    assert res.exit_code == 2 and one_line(res) == (f"error: {tmp_path / 'text' / 'text.mcap'}: not an MCAP file "
                                                    "(it does not start with the MCAP magic)")
    # another writer's MCAP, unchunked: messages before the summary, refused rather than cut
    (tmp_path / "other").mkdir()
    path = tmp_path / "other" / "other.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh, use_chunking=False)
        w.start(profile="ros2", library="test")
        sid = w.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
        cid = w.register_channel("/chatter", "cdr", sid)
        w.add_message(cid, log_time=1, data=b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00", publish_time=1)
    before = path.read_bytes()  # as a kill leaves it: not finished, no footer
    res = runner.invoke(app, ["bag-reindex", str(tmp_path / "other")])
    assert res.exit_code == 2 and one_line(res).startswith(f"error: {path}: byte ") and one_line(res).endswith(
        "is not a chunk before the summary; bag-reindex rebuilds bags written by scube-sim (RosbagSink) only, "
        "and leaves this one as it is")
    assert path.read_bytes() == before and sorted(p.name for p in path.parent.iterdir()) == ["other.mcap"]
