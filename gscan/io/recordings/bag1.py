"""A ROS 1 bag reader that reads around damaged chunks instead of refusing the whole recording.

rosbags' `rosbag1.Reader` stops at the first chunk it cannot read: a chunk record whose header is damaged fails
`open()`, and a chunk whose data does not decompress, or a record that runs past its chunk's end, ends
`messages()` with an error. `TolerantBag1Reader` keeps rosbags' parsing of the bag header, connections and chunk
infos (the index at the file's end, which must be intact: without it nothing tells where the chunks are), and
reads each chunk on its own:

- a chunk whose record header cannot be read: its index records (IDXDATA) are found from their end (they fill
  the bytes before the next chunk or the index, and their sizes follow from the chunk info's counts); when they
  do not parse either, the chunk info's per-connection counts and time range describe what was lost;
- a chunk whose index records cannot be read: nothing tells where its messages lie; the chunk info describes
  what was lost;
- a chunk whose data does not decompress: every message its index records list is lost;
- a record that cannot be read, or is not the message its index lists: that message is lost.

Everything lost is kept in `lost` (chunk position -> `LostChunk`), whichever call found it.
"""
from __future__ import annotations

import heapq
import os
import struct
from collections import defaultdict
from collections.abc import Collection, Generator
from contextlib import suppress
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import BinaryIO

from rosbags.interfaces import Connection
from rosbags.rosbag1 import Reader, ReaderError
from rosbags.rosbag1.reader import Chunk, ChunkInfo, Header, IndexData, RecordType, read_bytes, read_uint32

# errors a damaged record raises in rosbags' parsing (short reads, bad fields, unknown compression, bad data)
DAMAGE_ERRORS = (ReaderError, AssertionError, struct.error, KeyError, ValueError, EOFError, OSError, RuntimeError)
IDXDATA_FIXED = 4 + 47 + 4  # an IDXDATA record: header length, its 47 header bytes (ver, conn, count, op), data length
IDXDATA_ENTRY = 12  # one index entry: time (sec, nsec) and offset in the chunk


@dataclass
class LostChunk:
    """What of the chunk at byte `pos` could not be read: `why` (the first error), `whole` (the chunk itself, not
    single records), `entries` {(connection id, log time ns, offset in the chunk)} the lost messages its index
    records list, and, when those records are unreadable too, the chunk info's `counts` {connection id: messages}
    and time range (ns)."""

    pos: int
    why: str
    whole: bool
    entries: set[tuple[int, int, int]] = field(default_factory=set)
    counts: dict[int, int] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int | None = None


def _why(e: BaseException) -> str:
    text = " ".join(str(e).split()) or e.__class__.__name__
    return text if len(text) <= 160 else text[:157] + "..."


class TolerantBag1Reader(Reader):
    """rosbags' ROS 1 reader, reading around damaged chunks and records (see the module docstring)."""

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        self.lost: dict[int, LostChunk] = {}
        self._chunk_entries: dict[int, list[tuple[int, int, int]]] = {}  # chunk pos -> [(connection, time, offset)]

    def open(self) -> None:
        """Read the bag header, the index at the file's end and each chunk's index records (a damaged chunk is
        recorded in `lost`, the others read as rosbags reads them)."""
        if self.bio is not None:
            raise ReaderError("Reader is already open.")
        self.bio = self.path.open("rb")
        try:
            magic = self.bio.readline().decode(errors="replace")
            if not magic:
                raise ReaderError(f"File {str(self.path)!r} seems to be empty.")
            if magic != "#ROSBAG V2.0\n":
                raise ReaderError("File magic is invalid." if not magic.startswith("#ROSBAG V")
                                  else f"Bag version {magic.strip()[8:]!r} is not supported.")
            header = Header.read(self.bio, RecordType.BAGHEADER)
            index_pos = header.get_uint64("index_pos")
            conn_count, chunk_count = header.get_uint32("conn_count"), header.get_uint32("chunk_count")
            if "encryptor" in header and header.get_string("encryptor"):
                raise ReaderError(f"Bag encryption {header.get_string('encryptor')!r} is not supported.")
            if index_pos == 0:
                raise ReaderError("Bag is not indexed, reindex before reading.")
            if chunk_count == 0:
                return
            self.bio.seek(index_pos)
            try:
                self.connections = [self.read_connection() for _ in range(conn_count)]
                self.chunk_infos = [self.read_chunk_info() for _ in range(chunk_count)]
            except DAMAGE_ERRORS as err:
                raise ReaderError(f"Bag index looks damaged: {err.args}") from None
            ends = sorted({ci.pos for ci in self.chunk_infos} | {index_pos})
            indexes: dict[int, list[IndexData]] = defaultdict(list)
            for ci in self.chunk_infos:
                end = next(p for p in ends if p > ci.pos) if ci.pos < index_pos else index_pos
                self._open_chunk(ci, end, indexes)
            self.indexes = {c.id: sorted(indexes[c.id]) for c in self.connections}
            listed: dict[int, int] = defaultdict(int)  # the index's counts: every chunk info's, damaged ones too
            for ci in self.chunk_infos:
                for cid, n in ci.connection_counts.items():
                    listed[cid] += n
            self.connections = [Connection(*c[0:5], listed[c.id], *c[6:]) for c in self.connections]
        except BaseException:
            with suppress(Exception):
                self.close()
            raise

    def _open_chunk(self, ci: ChunkInfo, end: int, indexes: dict[int, list[IndexData]]) -> None:
        """The chunk record at ci.pos and its index records (which end at `end`), or its damage in `lost`."""
        assert self.bio is not None
        entries: list[tuple[int, IndexData]] = []
        stage = "its record header"
        try:
            self.bio.seek(ci.pos)
            chunk = self.read_chunk()
            stage = "its index records"
            for _ in range(len(ci.connection_counts)):
                entries += self._index_record(ci)
            self.chunks[ci.pos] = chunk
        except DAMAGE_ERRORS as e:
            why = f"{stage} cannot be read ({_why(e).rstrip('.')})"
            entries = self._index_from_end(ci, end) if stage == "its record header" else []
            lost = LostChunk(ci.pos, why, True)
            if entries:
                lost.entries = {(cid, ix.time, ix.offset) for cid, ix in entries}
            else:
                lost.counts = dict(ci.connection_counts)
                lost.start_ns, lost.end_ns = ci.start_time, ci.end_time - 1
            self.lost[ci.pos] = lost
        for cid, ix in entries:
            indexes[cid].append(ix)
        self._chunk_entries[ci.pos] = [(cid, ix.time, ix.offset) for cid, ix in entries]

    def _index_record(self, ci: ChunkInfo) -> list[tuple[int, IndexData]]:
        """One IDXDATA record at the file position, checked against the chunk info: [(connection id, entry)]."""
        assert self.bio is not None
        header = Header.read(self.bio, RecordType.IDXDATA)
        if header.get_uint32("ver") != 1:
            raise ReaderError(f"IDXDATA version {header.get_uint32('ver')} is not supported.")
        cid, count = header.get_uint32("conn"), header.get_uint32("count")
        if ci.connection_counts.get(cid) != count:
            raise ReaderError(f"index record of connection {cid} lists {count} messages, the chunk info "
                              f"{ci.connection_counts.get(cid, 0)}")
        size = read_uint32(self.bio)
        if size != count * 12:
            raise ReaderError(f"index record data is {size} bytes for {count} messages")
        buf = read_bytes(self.bio, size)
        out = []
        for k in range(count):
            sec, nsec, offset = struct.unpack_from("<LLL", buf, k * 12)
            out.append((cid, IndexData(sec * 10**9 + nsec, ci.pos, offset)))
        return out

    def _index_from_end(self, ci: ChunkInfo, end: int) -> list[tuple[int, IndexData]]:
        """The index records of a chunk whose record header is damaged, read back from where they end (`end`: the
        next chunk or the index): their sizes follow from the chunk info's counts. [] when they do not parse."""
        assert self.bio is not None
        size = sum(IDXDATA_FIXED + IDXDATA_ENTRY * n for n in ci.connection_counts.values())
        if end - size <= ci.pos:
            return []
        try:
            self.bio.seek(end - size)
            entries = []
            for _ in range(len(ci.connection_counts)):
                entries += self._index_record(ci)
        except DAMAGE_ERRORS:
            return []
        return entries

    def messages(self, connections: Collection[Connection] = (), start: int | None = None,
                 stop: int | None = None) -> Generator[tuple[Connection, int, bytes], None, None]:
        """The messages of `connections` (all when empty) with start <= log time < stop, in log-time order; the
        messages of a damaged chunk or record are left out and recorded in `lost`."""
        self._check_open()
        assert self.bio is not None
        connmap = {c.id: c for c in self.connections}
        wanted = list(connections) or self.connections
        tagged = [[(ix, c.id) for ix in self.indexes[c.id]] for c in wanted]
        for entry, cid in heapq.merge(*tagged, key=lambda e: e[0].time):
            if start is not None and entry.time < start:
                continue
            if stop is not None and entry.time >= stop:
                return
            if entry.chunk_pos in self.lost and self.lost[entry.chunk_pos].whole:
                continue
            chunk = self._chunk_data(entry.chunk_pos)
            if chunk is None:
                continue
            try:
                chunk.seek(entry.offset)
                while True:
                    header = Header.read(chunk)
                    op = header.get_uint8("op")
                    if op != RecordType.CONNECTION:
                        break
                    chunk.seek(read_uint32(chunk), os.SEEK_CUR)
                if op != RecordType.MSGDATA or header.get_uint32("conn") != cid or \
                        header.get_time("time") != entry.time:
                    raise ReaderError("the record there is not the message the chunk's index lists")
                data = read_bytes(chunk, read_uint32(chunk))
            except DAMAGE_ERRORS as e:
                lost = self.lost.setdefault(entry.chunk_pos, LostChunk(
                    entry.chunk_pos, f"a record cannot be read ({_why(e).rstrip('.')})", False))
                lost.entries.add((cid, entry.time, entry.offset))
                continue
            yield connmap[cid], entry.time, data

    def _chunk_data(self, pos: int) -> BinaryIO | None:
        """The decompressed data of the chunk at `pos` (kept while its messages are read), None when it does not
        decompress (then the whole chunk is lost)."""
        assert self.bio is not None
        if self.current_chunk[0] == pos:
            return self.current_chunk[1]
        self.current_chunk[1].close()
        self.current_chunk = (-1, BytesIO())
        chunk: Chunk = self.chunks[pos]
        try:
            self.bio.seek(chunk.datapos)
            raw = chunk.decompressor(read_bytes(self.bio, chunk.datasize))
        except Exception as e:  # noqa: BLE001 - lz4 / bz2 raise their own errors on corrupt data
            self.lost[pos] = LostChunk(pos, f"its data does not decompress ({_why(e).rstrip('.')})", True,
                                       set(self._chunk_entries.get(pos, [])))
            return None
        self.current_chunk = (pos, BytesIO(raw))
        return self.current_chunk[1]

    def lost_topics(self, lost: LostChunk) -> dict[str, int]:
        """topic -> lost messages of a `LostChunk` (its index entries, else the chunk info's counts)."""
        topic_of = {c.id: c.topic for c in self.connections}
        out: dict[str, int] = defaultdict(int)
        if lost.entries:
            for cid, _, _ in lost.entries:
                out[topic_of.get(cid, f"connection {cid}")] += 1
        else:
            for cid, n in lost.counts.items():
                out[topic_of.get(cid, f"connection {cid}")] += n
        return dict(sorted(out.items()))
