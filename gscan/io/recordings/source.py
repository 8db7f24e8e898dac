"""Message sources: one interface over ROS 1 bags, rosbag2 (sqlite3 `.db3`, bag folders) and MCAP files.

A source lists its topics and yields raw messages (topic, log time, serialised bytes) in log-time order,
optionally from a start time (the formats are indexed by time, so a restart does not read the file from
its beginning). Small messages (CameraInfo, transforms, options) are deserialised through the
format's own library; images are parsed by `gscan.io.recordings.messages`, without a copy.

- `.bag` and rosbag2 `.db3` files or folders (metadata.yaml): the `rosbags` package (`AnyReader`),
  with the message definitions stored in the bag, or ROS 2 Humble's when a rosbag2 stores none.
  A message compressed on its own with zstd (librealsense 2.58 writes every message so, in a `.db3` with
  no metadata.yaml to say it) is recognised by the zstd frame magic, which no CDR message starts with,
  and decompressed when it is decoded or parsed (`unwrap`): a corrupt one spoils that message alone.
- `.mcap` (a file, or a rosbag2 folder of one uncompressed `.mcap`): the `mcap` package's reader (the format's
  reference implementation), messages decoded with `mcap-ros2-support` from the schemas stored in the file.

Damaged records: `counts()` is what the file's own index lists (a ROS 1 bag's chunk infos, a bag folder's
metadata.yaml, the metadata a `.db3` stores, an MCAP's statistics), so that the messages read can be compared
with it; `damaged()` locates what was lost where the format tells: a ROS 1 bag's chunks and records that cannot
be read (`gscan.io.recordings.bag1`, read around them) and the rows missing from a `.db3`'s id sequence
(`gscan.io.recordings.db3`).

Every library error becomes an InputError naming the file.
"""
from __future__ import annotations

import contextlib
import logging
import sqlite3
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Protocol

from gscan.errors import InputError

log = logging.getLogger(__name__)

Raw = tuple[str, int, bytes | memoryview]  # (topic, log time ns, serialised message)

ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"  # a zstd frame's first four bytes; a CDR message starts with 00 0x 00 00
MAX_MESSAGE_BYTES = 1 << 30  # a decompressed message larger than this is refused (a corrupt size field)
MAX_TOPICS_LISTED = 4  # a damaged record's line names the topics with the most lost messages, and sums the others
MAX_ROW_GAPS = 20  # runs of missing row ids reported one by one; the ones after are reported together


def zstd_decompress(data: bytes | memoryview) -> bytes:
    """The bytes of a zstd frame; ValueError when they do not decompress (truncated, corrupt) or would decompress
    to more than MAX_MESSAGE_BYTES (refused from the frame header's size before anything is allocated)."""
    import zstandard

    raw = bytes(data)
    try:
        size = zstandard.get_frame_parameters(raw).content_size
        if size != zstandard.CONTENTSIZE_UNKNOWN and size > MAX_MESSAGE_BYTES:
            raise ValueError(f"zstd frame claims {size} bytes, more than {MAX_MESSAGE_BYTES}")
        return zstandard.ZstdDecompressor().decompress(raw, max_output_size=MAX_MESSAGE_BYTES)
    except zstandard.ZstdError as e:
        raise ValueError(f"zstd data does not decompress ({e})") from None


def unwrap(data: bytes | memoryview) -> bytes | memoryview:
    """A serialised message as it is, or decompressed when it is a zstd frame (a message compressed alone)."""
    return zstd_decompress(data) if bytes(data[:4]) == ZSTD_MAGIC else data


@dataclass(frozen=True)
class DamagedRecords:
    """Messages a recording holds record of but that cannot be read, located: `where` (a chunk's byte offset, a run
    of missing row ids), `why`, how many (`count`), on which topics (`topics`: topic -> count; empty when the file
    does not tell) and the log times (ns) they lie between, inclusive (`first_ns` / `last_ns`; None: the
    recording's start / end)."""

    where: str
    why: str
    count: int
    topics: dict[str, int]
    first_ns: int | None
    last_ns: int | None

    def covers(self, t_ns: int, margin_ns: float = 0.0) -> bool:
        """Whether log time t_ns lies in the records' window (widened by margin_ns)."""
        return (self.first_ns is None or t_ns >= self.first_ns - margin_ns) and \
            (self.last_ns is None or t_ns <= self.last_ns + margin_ns)

    def describe(self, start_ns: int | None, attributed: str = "") -> str:
        """One line: where, why, the messages lost (by topic, or `attributed` when the file does not tell) and,
        given the recording's start, their times from it."""
        def at(t: int) -> str:
            return f"{(t - (start_ns or 0)) * 1e-9:.3f} s"

        on = ", ".join(f"{n} on {t}" for t, n in self.topics.items()) if self.topics else \
            (attributed or "on topics the file does not tell")
        if len(self.topics) > MAX_TOPICS_LISTED:  # the topics with the most lost messages named, the others summed
            top = sorted(self.topics.items(), key=lambda tn: (-tn[1], tn[0]))
            rest = top[MAX_TOPICS_LISTED:]
            on = ", ".join(f"{n} on {t}" for t, n in top[:MAX_TOPICS_LISTED]) + \
                f", {sum(n for _, n in rest)} on {len(rest)} other topics"
        lo, hi = self.first_ns, self.last_ns
        if start_ns is None or (lo is None and hi is None):
            when = ""
        elif lo is None:
            when = f", logged before {at(hi)}" if hi is not None else ""
        elif hi is None:
            when = f", logged after {at(lo)}"
        else:
            when = f", logged at {at(lo)}" if lo == hi else f", logged between {at(lo)} and {at(hi)}"
        rel = " (from the recording's start)" if when else ""
        return f"{self.where}: {self.why}; {self.count} message{'s' * (self.count != 1)} lost ({on}){when}{rel}"


class MessageSource(Protocol):
    """What the recording readers need from a file format."""

    path: Path
    wire: str  # "ros1" | "cdr": how messages are serialised

    def topics(self) -> dict[str, str]:
        """topic -> message type, normalised to "pkg/msg/Type"."""

    def counts(self) -> dict[str, int]:
        """topic -> number of messages the file's index lists."""

    def damaged(self) -> list[DamagedRecords]:
        """The damaged records located so far (on opening, and while messages were read)."""

    def messages(self, topics: list[str], start_ns: int | None = None) -> Iterator[Raw]:
        """Messages of `topics` with log time >= start_ns, in log-time order."""

    def decode(self, topic: str, data: bytes | memoryview) -> Any:
        """A message of `topic` deserialised (attribute access, field names as in its definition)."""

    def close(self) -> None: ...


def normalise_type(msgtype: str) -> str:
    """'sensor_msgs/Image' (ROS 1) and 'sensor_msgs/msg/Image' (ROS 2) -> 'sensor_msgs/msg/Image'."""
    parts = msgtype.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else msgtype


def _why(e: BaseException) -> str:
    text = " ".join(str(e).split()) or e.__class__.__name__
    return text if len(text) <= 200 else text[:197] + "..."


class RosbagsSource:
    """A ROS 1 bag or a rosbag2 (.db3 file or bag folder) read with `rosbags`."""

    def __init__(self, path: Path):
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        from gscan.io.recordings.bag1 import TolerantBag1Reader

        self.path = path
        self.wire = "ros1" if path.suffix.lower() == ".bag" and path.is_file() else "cdr"
        self._bag1: TolerantBag1Reader | None = None
        try:
            self._reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            if self.wire == "ros1":  # read around damaged chunks (AnyReader opens and merges its readers)
                self._bag1 = TolerantBag1Reader(path)
                self._reader.readers = [self._bag1]
            self._reader.open()
        except Exception as e:  # noqa: BLE001 - rosbags raises its own errors, sqlite3's, OSError, KeyError, ...
            raise InputError(path, f"cannot open the recording: {self._reason(e)}") from None
        self._conns: dict[str, list[Any]] = {}
        for c in self._reader.connections:
            self._conns.setdefault(c.topic, []).append(c)
        self._counts = {t: sum(int(c.msgcount) for c in cs) for t, cs in self._conns.items()}
        self._row_damage: list[DamagedRecords] = [] if self.wire == "ros1" else self._missing_rows()

    def _missing_rows(self) -> list[DamagedRecords]:
        """The rows missing from the `.db3` files' id sequences (`gscan.io.recordings.db3`), each attributed to a
        topic when only one topic holds fewer messages than the recording's metadata lists. A bare `.db3`'s counts
        become the ones its stored metadata lists (rosbags counts its rows)."""
        from gscan.io.recordings.db3 import db3_files, db3_rows

        gaps, rows = [], dict.fromkeys(self._counts, 0)
        for f in db3_files(self.path):
            try:
                found = db3_rows(f)
            except sqlite3.Error as e:
                log.warning("%s: its message ids cannot be checked (%s)", f, _why(e))
                return []
            gaps += found.gaps
            for t, n in found.rows.items():
                rows[t] = rows.get(t, 0) + n
            if self.path.is_file() and found.listed is not None:
                self._counts.update({t: n for t, n in found.listed.items() if t in self._counts})
        short = {t: self._counts[t] - n for t, n in rows.items() if self._counts.get(t, 0) > n}
        total = sum(g.count for g in gaps)
        only = next(iter(short)) if len(short) == 1 and total <= next(iter(short.values())) else None
        why = "missing from its messages table, whose ids the recorder assigns in sequence"
        if short and only is None:
            why += " (the recording's metadata lists more messages than it holds on " + \
                ", ".join(f"{t} ({n})" for t, n in sorted(short.items())) + ")"
        out = []
        runs = [[g] for g in gaps[:MAX_ROW_GAPS - 1]] + ([gaps[MAX_ROW_GAPS - 1:]] if len(gaps) >= MAX_ROW_GAPS else [])
        for run in runs:
            g, n = run[0], sum(x.count for x in run)
            ids = f"message id {g.first}" if g.count == 1 else f"message ids {g.first}-{g.last}"
            if len(run) > 1:
                ids = f"{len(run)} more runs of missing message ids (from {g.first} to {run[-1].last})"
            times = [t for x in run for t in (x.before_ns, x.after_ns) if t is not None]
            lo = None if any(x.before_ns is None for x in run) else min(times)
            files = ", ".join(sorted({x.file.name for x in run}))
            out.append(DamagedRecords(f"{ids} of {files}", why, n, {only: n} if only else {}, lo, max(times)))
        return out

    def _reason(self, e: BaseException) -> str:
        text = _why(e)
        if "not indexed" in text or "reindex" in text or "index looks damaged" in text:
            return ("truncated or damaged: its index cannot be read (`rosbag reindex` repairs a bag whose "
                    "recording was cut off)")
        if "magic" in text.lower():
            return f"not a ROS bag ({text})"
        if "malformed" in text or "not a database" in text:
            return f"truncated or corrupt ({text})"
        return text

    def topics(self) -> dict[str, str]:
        return {t: normalise_type(cs[0].msgtype) for t, cs in self._conns.items()}

    def counts(self) -> dict[str, int]:
        return dict(self._counts)

    def damaged(self) -> list[DamagedRecords]:
        if self._bag1 is None:
            return list(self._row_damage)
        out = []
        for pos, lost in sorted(self._bag1.lost.items()):
            times = sorted(t for _, t, _ in lost.entries)
            first, last = (times[0], times[-1]) if times else (lost.start_ns, lost.end_ns)
            topics = self._bag1.lost_topics(lost)
            where = f"the chunk at byte {pos}" if lost.whole else f"records in the chunk at byte {pos}"
            out.append(DamagedRecords(where, lost.why, sum(topics.values()), topics, first, last))
        return out

    def messages(self, topics: list[str], start_ns: int | None = None) -> Iterator[Raw]:
        conns = [c for t in topics for c in self._conns.get(t, [])]
        if not conns:
            return
        try:
            for c, t, data in self._reader.messages(connections=conns, start=start_ns):
                yield c.topic, int(t), data
        except InputError:
            raise
        except Exception as e:  # noqa: BLE001 - a corrupt chunk / page surfaces here
            raise InputError(self.path, f"truncated or corrupt recording ({self._reason(e)})") from None

    def decode(self, topic: str, data: bytes | memoryview) -> Any:
        try:
            return self._reader.deserialize(bytes(unwrap(data)), self._conns[topic][0].msgtype)
        except Exception as e:  # noqa: BLE001
            raise InputError(self.path, f"topic {topic}: message does not deserialise ({_why(e)})") from None

    def close(self) -> None:
        with contextlib.suppress(Exception):  # closing twice, or after a failed open
            self._reader.close()


class McapSource:
    """An MCAP file (ROS 2 messages, CDR) read with the `mcap` package."""

    def __init__(self, path: Path):
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory

        self.path = path
        self.wire = "cdr"
        self._decoders: dict[str, Any] = {}
        self._factory = DecoderFactory()
        self._file: BinaryIO | None = None
        try:
            self._file = open(path, "rb")  # noqa: SIM115 - open while the source lives
            self._reader = make_reader(self._file)
            summary = self._reader.get_summary()
            if summary is None:
                raise ValueError("the file has no summary section")
        except Exception as e:  # noqa: BLE001 - McapError, struct.error, EndOfFile, OSError ...
            self.close()
            raise InputError(path, f"cannot open the recording: truncated or corrupt MCAP ({_why(e)})") from None
        self._summary = summary
        self._channels = {c.topic: c for c in summary.channels.values()}
        for c in summary.channels.values():
            if c.message_encoding != "cdr":
                log.info("%s: topic %s is %s-encoded, not read", path, c.topic, c.message_encoding)

    def topics(self) -> dict[str, str]:
        out = {}
        for t, c in self._channels.items():
            schema = self._summary.schemas.get(c.schema_id)
            if schema is not None and c.message_encoding == "cdr":
                out[t] = normalise_type(schema.name)
        return out

    def counts(self) -> dict[str, int]:
        stats = self._summary.statistics
        by_id = stats.channel_message_counts if stats is not None else {}
        return {t: int(by_id.get(c.id, 0)) for t, c in self._channels.items()}

    def damaged(self) -> list[DamagedRecords]:
        return []  # the MCAP reader does not say where it lost records: the counts tell (`counts`)

    def messages(self, topics: list[str], start_ns: int | None = None) -> Iterator[Raw]:
        if not topics:
            return
        try:
            for _schema, channel, msg in self._reader.iter_messages(topics=topics, starting_at=start_ns,
                                                                      log_time_order=True):
                yield channel.topic, int(msg.log_time), msg.data
        except InputError:
            raise
        except Exception as e:  # noqa: BLE001
            raise InputError(self.path, f"truncated or corrupt MCAP ({_why(e)})") from None

    def decode(self, topic: str, data: bytes | memoryview) -> Any:
        dec = self._decoders.get(topic)
        try:
            if dec is None:
                c = self._channels[topic]
                dec = self._factory.decoder_for(c.message_encoding, self._summary.schemas.get(c.schema_id))
                if dec is None:
                    raise ValueError("no decoder for its schema")
                self._decoders[topic] = dec
            return dec(bytes(data))
        except Exception as e:  # noqa: BLE001
            raise InputError(self.path, f"topic {topic}: message does not deserialise ({_why(e)})") from None

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def open_source(path: Path) -> MessageSource:
    """The source for a `.bag`, `.db3` or `.mcap` file or a rosbag2 folder; InputError when it cannot be read."""
    if not path.exists():
        raise InputError(path, "recording not found")
    try:
        if path.is_file():
            with open(path, "rb") as f:
                head = f.read(16)
            if not head:
                raise InputError(path, "file is empty")
    except PermissionError:
        raise InputError(path, "permission denied") from None
    except OSError as e:
        raise InputError(path, f"cannot read file ({_why(e)})") from None
    if path.is_file() and path.suffix.lower() == ".mcap":
        return McapSource(path)
    if path.is_dir() and (one := _single_mcap(path)) is not None:
        return McapSource(one)
    return RosbagsSource(path)


def _single_mcap(folder: Path) -> Path | None:
    """The MCAP file of a rosbag2 folder that holds one, uncompressed (read by the MCAP reader, which reads past
    damaged records, rather than rosbags'); None for any other folder."""
    import yaml

    try:
        info = yaml.safe_load((folder / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        files = [folder / Path(str(f)).name for f in info["relative_file_paths"]]
        plain = info.get("storage_identifier") == "mcap" and not info.get("compression_format")
    except (OSError, UnicodeDecodeError, yaml.YAMLError, KeyError, TypeError):
        return None
    return files[0] if plain and len(files) == 1 and files[0].suffix == ".mcap" and files[0].is_file() else None
