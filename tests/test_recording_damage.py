"""Damaged ROS recordings: what is lost is reported as damage where the file locates it, and the rest is read.

- a ROS 1 bag's damaged chunk (data that does not decompress, a record header that cannot be read, with or without
  its index records, index records that cannot be read) or damaged record (a length that runs past its chunk):
  reported with the chunk's byte offset, the messages its index lists (per topic) and their log times; the
  frames of the other chunks read as written;
- a rosbag2 `.db3` whose rows were deleted: the gaps in its message ids reported (which ids, between which times),
  attributed to a topic by the counts its metadata (metadata.yaml, or the copy in the file) lists, or else by
  the image streams' own periods; rows lost at the end are told by those counts only;
- a recording whose damage leaves no frame: one line naming the file and its damage, exit code 2.

The damaged files are written here by `gscan.synth.recordings` and then damaged byte by byte (or row by row).
"""
from __future__ import annotations

import sqlite3
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Reader

from gscan.errors import InputError
from gscan.io import open_sequence
from gscan.io.camera import Intrinsics
from gscan.synth.recordings import RecordingFrame, write_realsense_bag, write_rosbag2

ROOT = Path(__file__).resolve().parents[1]
T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 33_333_333
K = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)
N = 24
COLOR, DEPTH = "/device_0/sensor_1/Color_0/image/data", "/device_0/sensor_0/Depth_0/image/data"
ROS2_COLOR = "/camera/camera/color/image_raw"
ROS2_DEPTH = "/camera/camera/aligned_depth_to_color/image_raw"


def _frames(n: int = N) -> list[RecordingFrame]:
    """n frames of distinct random colour and a flat depth (0.5 m + 1 mm per frame)."""
    rng = np.random.default_rng(7)
    return [RecordingFrame(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8),
                           np.full((48, 64), 500 + i, np.uint16), T0_NS + i * PERIOD_NS) for i in range(n)]


def _index(bag: Path) -> tuple[list[int], dict[int, dict[str, list[int]]], dict[int, int]]:
    """A bag as its index lists it (rosbags' reader, on the intact file): chunk positions, {chunk: {topic: [log
    times]}} and {chunk: its data's file position}."""
    with Reader(bag) as r:
        topic = {c.id: c.topic for c in r.connections}
        chunks: dict[int, dict[str, list[int]]] = {ci.pos: {} for ci in r.chunk_infos}
        for cid, entries in r.indexes.items():
            for e in entries:
                chunks[e.chunk_pos].setdefault(topic[cid], []).append(e.time)
        return sorted(chunks), chunks, {pos: r.chunks[pos].datapos for pos in chunks}


def _spoil_header(data: bytearray, pos: int) -> None:
    """The chunk record at pos says it is a message record (op 2, not 5)."""
    k = data.index(b"op=\x05", pos)
    data[k + 3] = 2


def _damage_bag(bag: Path, case: str, pos: int, datapos: int, chunk: dict[str, list[int]]) -> dict[str, list[int]]:
    """Damage the chunk at `pos` of `bag` as `case` says; the log times it loses, per topic."""
    data = bytearray(bag.read_bytes())
    if case == "bad-compression":  # the LZ4 frame's magic number: its data does not decompress
        data[datapos:datapos + 4] = b"\0\0\0\0"
        lost = chunk
    elif case in ("wrong-header", "wrong-header-and-index", "damaged-index"):
        if case != "damaged-index":
            _spoil_header(data, pos)
        if case != "wrong-header":  # its first index record (IDXDATA, op 4)
            k = data.index(b"op=\x04", pos)
            data[k + 3] = 9
        lost = chunk
    else:  # truncated-record: the chunk's second depth record declares 2^31 bytes of data
        with Reader(bag) as r:
            cid = next(c.id for c in r.connections if c.topic == DEPTH)
            entry = [e for e in r.indexes[cid] if e.chunk_pos == pos][1]
        i = datapos + entry.offset
        struct.pack_into("<I", data, i + 4 + struct.unpack_from("<I", data, i)[0], 2**31)
        lost = {DEPTH: [entry.time]}
    bag.write_bytes(bytes(data))
    return lost


def _which(color: np.ndarray, frames: list[RecordingFrame]) -> int:
    return next(i for i, f in enumerate(frames) if np.array_equal(f.color, color))


@pytest.mark.parametrize("case", ["bad-compression", "wrong-header", "wrong-header-and-index", "damaged-index",
                                  "truncated-record"])
def test_a_damaged_bag_chunk_is_reported_and_the_other_chunks_are_read(tmp_path, case):
    frames = _frames()
    bag = write_realsense_bag(tmp_path / "d.bag", frames, K, compress=case == "bad-compression", chunk_bytes=30_000)
    order, chunks, datapos = _index(bag)
    assert len(order) >= 4
    pos = order[2]
    lost = _damage_bag(bag, case, pos, datapos[pos], chunks[pos])
    with open_sequence(bag) as seq:
        assert len(seq.damage) == 1, seq.damage
        line = seq.damage[0]
        where = "records in the chunk" if case == "truncated-record" else "the chunk"
        assert line.startswith(f"{bag}: damaged records: {where} at byte {pos}: "), line
        n = sum(len(t) for t in lost.values())
        assert f"; {n} message{'s' * (n != 1)} lost (" in line, line
        for topic in (COLOR, DEPTH):
            if lost.get(topic):
                assert f"{len(lost[topic])} on {topic}" in line, line
        start = min(t for c in chunks.values() for topic in (COLOR, DEPTH) for t in c.get(topic, []))
        times = sorted(t for ts in lost.values() for t in ts)
        at = [f"{(t - start) * 1e-9:.3f} s" for t in (times[0], times[-1])]
        assert (f"logged between {at[0]} and {at[1]}" if len(times) > 1 else f"logged at {at[0]}") in line, line
        # the frames of the other chunks read as written; those whose depth was lost are said to be lost to it
        read = {name: _which(seq[name].color, frames) for name in seq.names}
        for name, i in read.items():
            assert np.all(np.rint(seq[name].depth * 1000) == 500 + i), name  # depth in mm: the frame's own
        lost_colour = {int(round((t - 1_000_000) / PERIOD_NS)) for t in lost.get(COLOR, [])}
        lost_depth = {int(round((t - 1_000_000) / PERIOD_NS)) for t in lost.get(DEPTH, [])}
        assert set(read.values()) == set(range(N)) - lost_colour - lost_depth
        assert len(seq.problems) == len(lost_depth - lost_colour), seq.problems
        assert all("among the recording's damaged records (the chunk" in why or
                   "among the recording's damaged records (records in the chunk" in why
                   for why in seq.problems.values()), seq.problems


def _delete_rows(db3: Path, topic: str, which: list[int]) -> list[tuple[int, int]]:
    """Delete the messages of `topic` at the positions `which` (negative from the end); their (id, log time)."""
    with sqlite3.connect(db3) as con:
        (tid,) = con.execute("SELECT id FROM topics WHERE name = ?", (topic,)).fetchone()
        rows = con.execute("SELECT id, timestamp FROM messages WHERE topic_id = ? ORDER BY id", (tid,)).fetchall()
        gone = [rows[k] for k in which]
        con.executemany("DELETE FROM messages WHERE id = ?", [(i,) for i, _ in gone])
    return gone


@pytest.mark.parametrize("kind", ["db3", "folder", "db3-without-metadata"])
def test_missing_db3_rows_are_reported_as_damage(tmp_path, kind):
    """The depth rows of frames 3 and 7 deleted: each gap in the ids is reported (which id, between which times);
    with the recording's metadata (the file's own copy, or the folder's metadata.yaml) they are depth's, the only
    topic it holds fewer messages of; without it, the depth stream's period tells."""
    n = 12
    db3 = write_rosbag2(tmp_path / "r", _frames(n), K, topics=("color", "aligned"))
    gone = _delete_rows(db3, ROS2_DEPTH, [3, 7])
    if kind == "db3-without-metadata":
        with sqlite3.connect(db3) as con:
            con.execute("DELETE FROM metadata")
    path = db3.parent if kind == "folder" else db3
    with sqlite3.connect(db3) as con:
        ids = dict(con.execute("SELECT id, timestamp FROM messages").fetchall())
    with open_sequence(path) as seq:
        assert len(seq.damage) == 2, seq.damage
        for line, (i, _) in zip(seq.damage, gone, strict=True):
            assert line.startswith(f"{path}: damaged records: message id {i} of r.db3: missing from its messages "
                                   "table, whose ids the recorder assigns in sequence; 1 message lost ("), line
            lo, hi = sorted((ids[i - 1], ids[i + 1]))
            when = (f"logged between {(lo - T0_NS) * 1e-9:.3f} s and {(hi - T0_NS) * 1e-9:.3f} s" if lo != hi
                    else f"logged at {(lo - T0_NS) * 1e-9:.3f} s")
            assert when in line, line
            if kind == "db3-without-metadata":
                assert f"(on topics the file does not tell; by the image streams' periods, 1 on {ROS2_DEPTH})" in line
            else:
                assert f"1 message lost (1 on {ROS2_DEPTH})" in line, line
        assert sorted(seq.problems) == ["000003", "000007"], seq.problems
        for name, line in zip(("000003", "000007"), seq.damage, strict=True):
            assert seq.problems[name] == f"its depth message on {ROS2_DEPTH} is among the recording's damaged " \
                f"records ({line.split(': damaged records: ', 1)[1]})", seq.problems[name]
        assert len(seq.names) == n - 2


def test_rows_lost_at_the_end_of_a_db3_are_told_by_its_metadata(tmp_path):
    """The last rows (the last frame's depth and its CameraInfo; that frame has no colour) deleted leave no gap in
    the ids: the counts the file's own metadata lists tell them, without a place (the messages read leave no
    stretch for them). (A `.db3` without metadata cannot tell them: docs/input.md.)"""
    n = 8
    frames = _frames(n)
    frames[-1].color = None
    db3 = write_rosbag2(tmp_path / "r", frames, K, topics=("color", "aligned"))
    with sqlite3.connect(db3) as con:
        last = con.execute("SELECT max(id) FROM messages").fetchone()[0]
        names = [r[0] for r in con.execute("SELECT topics.name FROM messages JOIN topics ON topic_id = topics.id "
                                           "WHERE messages.id > ? ORDER BY messages.id", (last - 2,))]
        assert names == [ROS2_DEPTH, "/camera/camera/aligned_depth_to_color/camera_info"]
        con.execute("DELETE FROM messages WHERE id > ?", (last - 2,))
    with open_sequence(db3) as seq:
        assert seq.damage == [f"{db3}: damaged records: 1 of the {n} messages the file's index lists on "
                              f"{ROS2_DEPTH} could not be read, where, the messages read do not tell (they "
                              "leave no stretch without one: lost at the recording's start or end, or the "
                              "index overcounts)"], seq.damage
        assert len(seq.names) == n - 1 and seq.problems == {}


def _all_chunk_headers_damaged(tmp: Path) -> Path:
    bag = write_realsense_bag(tmp / "x.bag", _frames(8), K, chunk_bytes=30_000)
    order, _, _ = _index(bag)
    data = bytearray(bag.read_bytes())
    for pos in order:
        _spoil_header(data, pos)
    bag.write_bytes(bytes(data))
    return bag


def _all_image_rows_deleted(tmp: Path) -> Path:
    db3 = write_rosbag2(tmp / "x", _frames(8), K, topics=("color", "aligned"))
    with sqlite3.connect(db3) as con:
        con.execute("DELETE FROM messages WHERE topic_id IN (SELECT id FROM topics WHERE name LIKE '%image_raw')")
    return db3


WHOLLY = {
    "bag-every-chunk-damaged": (_all_chunk_headers_damaged, "(the recording has damaged records: the chunk at byte"),
    "db3-every-image-row-deleted": (_all_image_rows_deleted, "(the recording has damaged records: message id"),
}


@pytest.mark.parametrize("case", sorted(WHOLLY))
def test_a_recording_damaged_beyond_use_exits_2_with_one_line_naming_its_damage(tmp_path, case):
    make, needle = WHOLLY[case]
    rec = make(tmp_path)
    with pytest.raises(InputError, match="damaged records"):
        open_sequence(rec)
    keep = tmp_path / "out.gscan"
    r = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(rec), "-o", str(keep)], capture_output=True,
                       text=True, cwd=ROOT, timeout=120, check=False)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert lines[0].startswith(f"error: {rec}: ") and needle in lines[0], lines[0]
    assert not keep.exists()
