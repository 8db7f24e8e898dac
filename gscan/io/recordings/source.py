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
- `.mcap`: the `mcap` package's reader (the format's reference implementation), messages decoded
  with `mcap-ros2-support` from the schemas stored in the file.

Every library error becomes an InputError naming the file.
"""
from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO, Protocol

from gscan.errors import InputError

log = logging.getLogger(__name__)

Raw = tuple[str, int, bytes | memoryview]  # (topic, log time ns, serialised message)

ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"  # a zstd frame's first four bytes; a CDR message starts with 00 0x 00 00
MAX_MESSAGE_BYTES = 1 << 30  # a decompressed message larger than this is refused (a corrupt size field)


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


class MessageSource(Protocol):
    """What the recording readers need from a file format."""

    path: Path
    wire: str  # "ros1" | "cdr": how messages are serialised

    def topics(self) -> dict[str, str]:
        """topic -> message type, normalised to "pkg/msg/Type"."""

    def counts(self) -> dict[str, int]:
        """topic -> number of messages."""

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

        self.path = path
        self.wire = "ros1" if path.suffix.lower() == ".bag" and path.is_file() else "cdr"
        try:
            self._reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            self._reader.open()
        except Exception as e:  # noqa: BLE001 - rosbags raises its own errors, sqlite3's, OSError, KeyError, ...
            raise InputError(path, f"cannot open the recording: {self._reason(e)}") from None
        self._conns: dict[str, list[Any]] = {}
        for c in self._reader.connections:
            self._conns.setdefault(c.topic, []).append(c)

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
        return {t: sum(int(c.msgcount) for c in cs) for t, cs in self._conns.items()}

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
    return RosbagsSource(path)
