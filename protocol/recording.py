"""Recordings of the mesh as MCAP files: what `archery record` writes and `archery replay` reads.

The format, chosen so that a replay is exact and the Foxglove app and the `mcap` CLI read it:

- One MCAP channel per Zenoh key (the topic is the key, e.g. `icubSim/cam/target:o`), chunked
  (zstd or lz4), with message and chunk indexes, statistics and summary offsets.
- Every message is JSON (message encoding `json`) with a JSON schema (schema encoding
  `jsonschema`). msgspec writes floats in their shortest round-trip form and bytes as base64, so
  decoding the JSON into the message type and encoding it as msgpack gives back the very bytes
  that were published (`tests/test_record.py` checks this): no float or field is lost.
- Camera frames use Foxglove's well-known schemas, `foxglove.RawImage` (rgb8, bgr8, mono8) or
  `foxglove.CompressedImage` (jpeg, png), so Foxglove's Image panel shows them; the fields of
  `Image` Foxglove has no place for (schema, seq, stamp, sim_time, frame) ride along in an extra
  `archery` object, which Foxglove ignores and the replay reads back. Protobuf (the
  `foxglove-schemas-protobuf` package) would save the base64 third but has no room for those
  fields, so a replayed frame would lose its sim time, which the detector's `measure` relies on.
- Every other message uses its own type's schema (`msgspec.json.schema`), named `archery.TYPE`.
- The header's profile is `archery`; a metadata record `archery` holds the message schema
  version, the robot, the key patterns and the start time. A replay refuses another version.
- A message's log time is when the recorder received it, its publish time the sender's stamp,
  its sequence the sender's seq.

Crash safety: the recorder closes a chunk at least every `flush_interval` s and whenever it
holds `chunk_size` bytes, and hands each closed chunk to the OS at once; a recorder killed with
SIGKILL leaves a file without a summary whose complete chunks all read back
(`read_messages(..., recover=True)`): at most the chunk in progress is lost.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgspec
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Channel, Schema
from mcap.records import Message as McapMessage
from mcap.writer import CompressionType, Writer

from protocol.codec import decode
from protocol.errors import ConfigError, DecodeError
from protocol.messages import MESSAGE_TYPES, SCHEMA_VERSION, Image
from protocol.messages import Message as ArcheryMessage
from protocol.patterns import stream_type

__all__ = [
    "COMPRESSIONS",
    "PROFILE",
    "RecordStats",
    "Recorder",
    "Recording",
    "from_record",
    "open_recording",
    "to_record",
]

log = logging.getLogger("archery.recording")

PROFILE = "archery"
COMPRESSIONS = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}
_MAGIC = b"\x89MCAP0\r\n"
_RAW = "foxglove.RawImage"
_COMPRESSED = "foxglove.CompressedImage"


class _Time(msgspec.Struct, frozen=True):
    sec: int
    nsec: int


class _ImageMeta(msgspec.Struct, frozen=True):
    """The fields of `Image` that Foxglove's image schemas have no place for."""

    schema: int
    seq: int
    stamp: float
    sim_time: float | None
    frame: int
    width: int = 0  # compressed images only: their size
    height: int = 0
    encoding: str = ""


class _RawImage(msgspec.Struct, frozen=True):
    timestamp: _Time
    frame_id: str
    width: int
    height: int
    encoding: str
    step: int
    data: bytes
    archery: _ImageMeta


class _CompressedImage(msgspec.Struct, frozen=True):
    timestamp: _Time
    frame_id: str
    data: bytes
    format: str
    archery: _ImageMeta


_TIME_SCHEMA = {
    "type": "object",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
}


def _image_schema(name: str) -> bytes:
    """A Foxglove image schema as JSON schema, plus the `archery` object."""
    struct = _RawImage if name == _RAW else _CompressedImage
    properties: dict[str, Any] = {
        "timestamp": _TIME_SCHEMA,
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "archery": msgspec.json.schema(_ImageMeta),
    }
    if struct is _RawImage:
        properties |= {
            "width": {"type": "integer", "minimum": 0},
            "height": {"type": "integer", "minimum": 0},
            "encoding": {"type": "string"},
            "step": {"type": "integer", "minimum": 0},
        }
    else:
        properties["format"] = {"type": "string"}
    return json.dumps({"title": name, "type": "object", "properties": properties}).encode()


def _schema_of(message_type: type[ArcheryMessage], encoding: str = "") -> tuple[str, bytes]:
    """(schema name, JSON schema) of a message type's channel."""
    if message_type is Image:
        name = _COMPRESSED if encoding in ("jpeg", "png") else _RAW
        return name, _image_schema(name)
    return f"archery.{message_type.__name__}", json.dumps(
        msgspec.json.schema(message_type)
    ).encode()


def _time(stamp: float) -> _Time:
    sec = max(0, int(stamp))
    return _Time(sec, min(999_999_999, max(0, round((stamp - sec) * 1e9))))


_json = msgspec.json.Encoder()


def to_record(message: ArcheryMessage) -> tuple[str, bytes]:
    """(schema name, JSON bytes) of one message as the recording stores it."""
    if isinstance(message, Image):
        meta = _ImageMeta(
            schema=message.schema,
            seq=message.seq,
            stamp=message.stamp,
            sim_time=message.sim_time,
            frame=message.frame,
        )
        if message.encoding in ("jpeg", "png"):
            meta = msgspec.structs.replace(
                meta, width=message.width, height=message.height, encoding=message.encoding
            )
            record: Any = _CompressedImage(
                _time(message.stamp), "target_camera", message.data, message.encoding, meta
            )
            return _COMPRESSED, _json.encode(record)
        channels = len(message.data) // (message.width * message.height)
        record = _RawImage(
            _time(message.stamp),
            "target_camera",
            message.width,
            message.height,
            message.encoding,
            message.width * channels,
            message.data,
            meta,
        )
        return _RAW, _json.encode(record)
    return f"archery.{type(message).__name__}", _json.encode(message)


_decoders: dict[str, msgspec.json.Decoder[Any]] = {
    _RAW: msgspec.json.Decoder(_RawImage),
    _COMPRESSED: msgspec.json.Decoder(_CompressedImage),
} | {f"archery.{name}": msgspec.json.Decoder(cls) for name, cls in MESSAGE_TYPES.items()}


def from_record(schema_name: str, data: bytes) -> ArcheryMessage:
    """The message a record holds (validated, as on the wire).

    Raises:
        DecodeError: an unknown schema, or data that does not fit it.
    """
    decoder = _decoders.get(schema_name)
    if decoder is None:
        raise DecodeError(f"unknown schema {schema_name!r} in the recording")
    try:
        record = decoder.decode(data)
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        raise DecodeError(f"invalid {schema_name} record: {exc}") from None
    if isinstance(record, ArcheryMessage):
        return record
    meta = record.archery
    common = {"schema": meta.schema, "seq": meta.seq, "stamp": meta.stamp, "frame": meta.frame}
    if isinstance(record, _RawImage):
        width, height, encoding = record.width, record.height, record.encoding
    else:
        width, height, encoding = meta.width, meta.height, record.format
    try:
        return Image(
            width=width,
            height=height,
            encoding=encoding,
            data=record.data,
            sim_time=meta.sim_time,
            **common,
        )
    except ValueError as exc:
        raise DecodeError(f"invalid {schema_name} record: {exc}") from None


# -- writing --------------------------------------------------------------------------------------


@dataclass
class RecordStats:
    """What a recorder has seen: per key, messages and bytes written; malformed payloads."""

    written: dict[str, int] = field(default_factory=dict)
    bytes: dict[str, int] = field(default_factory=dict)
    malformed: int = 0
    chunks: int = 0
    missing: int = 0  # messages never seen: gaps in a key's sequence numbers
    overflow: int = 0  # messages dropped because the writer fell `max_pending` bytes behind

    @property
    def total(self) -> int:
        """Messages written."""
        return sum(self.written.values())


class Recorder:
    """Writes messages arriving on any thread (`put`) into an MCAP file from its own thread.

    Args:
        path: the file to write (replaced if it exists).
        robot: the robot recorded (metadata).
        patterns: the key patterns recorded (metadata).
        compression: "zstd", "lz4" or "none".
        chunk_size: close a chunk once it holds this many bytes.
        flush_interval: close the chunk in progress at least this often (s), so a crash loses at
            most that much.
        max_pending: bytes queued for the writer at most; a message beyond is dropped and
            counted in `stats.overflow` (never blocks the receiving thread).

    Losses are counted, never guessed: `stats.missing` counts the gaps in each key's sequence
    numbers (messages dropped before they reached the recorder, or by the full queue).
    """

    def __init__(
        self,
        path: Path,
        robot: str,
        patterns: list[str],
        *,
        compression: str = "zstd",
        chunk_size: int = 4 * 1024 * 1024,
        flush_interval: float = 1.0,
        max_pending: int = 1 << 30,
    ) -> None:
        self.path = Path(path)
        try:
            self._file: IO[bytes] = open(self.path, "wb")  # noqa: SIM115 (closed by close())
        except OSError as exc:
            raise ConfigError(f"--out {str(path)!r}: {exc.strerror}") from None
        self._writer = Writer(
            self._file, chunk_size=chunk_size, compression=COMPRESSIONS[compression]
        )
        self._writer.start(profile=PROFILE, library=f"archery (mcap {_mcap_version()})")
        self._writer.add_metadata(
            PROFILE,
            {
                "schema_version": str(SCHEMA_VERSION),
                "robot": robot,
                "patterns": " ".join(patterns),
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            },
        )
        self._writer.flush()
        self.stats = RecordStats()
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._queue: queue.SimpleQueue[tuple[str, bytes, int] | None] = queue.SimpleQueue()
        self._pending_bytes = 0
        self._max_pending = max_pending
        self._lock = threading.Lock()
        self._seqs: dict[str, int] = {}
        self._flush_interval = flush_interval
        self._dirty = False
        self._closed = False
        self._thread = threading.Thread(target=self._work, name="recorder", daemon=True)
        self._thread.start()

    def put(self, key: str, payload: bytes, received_ns: int | None = None) -> None:
        """Queue one payload received on `key` (any thread; never blocks)."""
        with self._lock:
            if self._pending_bytes + len(payload) > self._max_pending:
                self.stats.overflow += 1
                return
            self._pending_bytes += len(payload)
        self._queue.put((key, payload, received_ns if received_ns is not None else time.time_ns()))

    def pending(self) -> int:
        """Payloads queued, not written yet."""
        return self._queue.qsize()

    def _channel(self, key: str, schema_name: str, message: ArcheryMessage) -> int:
        channel = self._channels.get((key, schema_name))
        if channel is None:
            schema_id = self._schemas.get(schema_name)
            if schema_id is None:
                encoding = message.encoding if isinstance(message, Image) else ""
                schema = _schema_of(type(message), encoding)[1]
                schema_id = self._writer.register_schema(schema_name, "jsonschema", schema)
                self._schemas[schema_name] = schema_id
            channel = self._writer.register_channel(key, "json", schema_id)
            self._channels[(key, schema_name)] = channel
        return channel

    def _write(self, key: str, payload: bytes, received_ns: int) -> None:
        with self._lock:
            self._pending_bytes -= len(payload)
        message_type = stream_type(key)
        if message_type is None:
            self.stats.malformed += 1
            return
        try:
            message = decode(payload, message_type)
        except DecodeError as exc:
            self.stats.malformed += 1
            if self.stats.malformed <= 10:
                log.warning("skipped a malformed message on %s: %s", key, exc)
            return
        last = self._seqs.get(key)
        if last is not None and message.seq > last + 1:
            self.stats.missing += message.seq - last - 1
        self._seqs[key] = message.seq  # a lower seq: its sender restarted
        schema_name, data = to_record(message)
        channel = self._channel(key, schema_name, message)
        self._writer.add_message(
            channel,
            log_time=received_ns,
            data=data,
            publish_time=int(message.stamp * 1e9),
            sequence=message.seq & 0xFFFFFFFF,
        )
        self._dirty = True
        self.stats.written[key] = self.stats.written.get(key, 0) + 1
        self.stats.bytes[key] = self.stats.bytes.get(key, 0) + len(payload)

    def _work(self) -> None:
        last_flush = time.monotonic()
        while True:
            timeout = max(0.0, last_flush + self._flush_interval - time.monotonic())
            try:
                item = self._queue.get(timeout=timeout)
            except queue.Empty:
                item = ()  # type: ignore[assignment]
            if item is None:
                return
            if item:
                try:
                    self._write(*item)
                except Exception:
                    log.exception("could not write a message on %s", item[0])
            if self._dirty and time.monotonic() - last_flush >= self._flush_interval:
                self._writer.flush()
                self.stats.chunks += 1
                self._dirty = False
                last_flush = time.monotonic()

    def close(self) -> RecordStats:
        """Write what is queued, the summary and the footer; close the file (idempotent)."""
        if not self._closed:
            self._closed = True
            self._queue.put(None)
            self._thread.join()
            self._writer.finish()
            self._file.close()
        return self.stats


def _mcap_version() -> str:
    import importlib.metadata

    try:
        return importlib.metadata.version("mcap")
    except importlib.metadata.PackageNotFoundError:
        return "?"


# -- reading --------------------------------------------------------------------------------------


@dataclass
class Recording:
    """An MCAP file checked for being a recording this version of the mesh can replay.

    Attributes:
        path: the file.
        complete: it has its summary and footer (False: cut short, e.g. a killed recorder).
        metadata: the `archery` metadata record.
        message_count: messages in it (complete files only; else None).
    """

    path: Path
    complete: bool
    metadata: dict[str, str]
    message_count: int | None

    def messages(self, *, recover: bool = False) -> Iterator[tuple[str, ArcheryMessage, int]]:
        """(key, message, log time ns) in file order (the order they were received).

        Args:
            recover: for a file cut short: yield what its complete records hold, then stop.

        Raises:
            ConfigError: the file is cut short and `recover` is not set, or a record is
                corrupt.
        """
        with open(self.path, "rb") as stream:
            reader = NonSeekingReader(stream, validate_crcs=True, record_size_limit=None)
            it = reader.iter_messages(log_time_order=False)
            while True:
                try:
                    item: tuple[Schema | None, Channel, McapMessage] = next(it)
                except StopIteration:
                    return
                except (McapError, EOFError, ValueError, OSError) as exc:
                    if recover:
                        return
                    raise ConfigError(f"{self.path}: unreadable record ({exc})") from None
                schema, channel, record = item
                if schema is None:
                    raise ConfigError(f"{self.path}: channel {channel.topic} has no schema")
                yield channel.topic, from_record(schema.name, record.data), record.log_time


def open_recording(path: str | Path) -> Recording:
    """Check that `path` is an MCAP recording of this schema version.

    Raises:
        ConfigError: no such file, not MCAP, not an archery recording, or another schema
            version; one line saying which.
    """
    path = Path(path)
    try:
        with open(path, "rb") as stream:
            head = stream.read(len(_MAGIC))
            if head != _MAGIC:
                raise ConfigError(f"{str(path)!r} is not an MCAP file (no MCAP magic at its start)")
            stream.seek(0)
            metadata, profile = _head_metadata(stream, path)
            stream.seek(0)
            complete, count = _summary(stream)
    except OSError as exc:
        raise ConfigError(f"{str(path)!r}: {exc.strerror}") from None
    if profile != PROFILE or metadata is None:
        raise ConfigError(
            f"{str(path)!r} is an MCAP file but not an archery recording (profile {profile!r})"
        )
    version = metadata.get("schema_version", "?")
    if version != str(SCHEMA_VERSION):
        raise ConfigError(
            f"{str(path)!r} was recorded with message schema version {version}; this version of "
            f"archery replays version {SCHEMA_VERSION} only"
        )
    return Recording(path, complete, metadata, count)


def _head_metadata(stream: IO[bytes], path: Path) -> tuple[dict[str, str] | None, str]:
    """The `archery` metadata record and the header's profile, read from the file's start (the
    recorder writes them before any message)."""
    from mcap.records import Header, Metadata
    from mcap.stream_reader import StreamReader

    profile = ""
    try:
        for record in StreamReader(stream, skip_magic=False, record_size_limit=None).records:
            if isinstance(record, Header):
                profile = record.profile
            elif isinstance(record, Metadata):
                if record.name == PROFILE:
                    return dict(record.metadata), profile
            else:
                break
    except (McapError, EOFError, ValueError) as exc:
        raise ConfigError(f"{str(path)!r}: a corrupt MCAP header ({exc})") from None
    return None, profile


def _summary(stream: IO[bytes]) -> tuple[bool, int | None]:
    """(has a readable summary and footer, its message count)."""
    try:
        summary = make_reader(stream).get_summary()
    except (McapError, EOFError, ValueError, AssertionError, OSError):
        return False, None
    if summary is None or summary.statistics is None:
        return False, None
    return True, summary.statistics.message_count
