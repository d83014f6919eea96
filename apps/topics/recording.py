"""Recordings of the mesh as MCAP files: what `archery record` writes and `archery replay` reads.

The format is chosen so that a replay is exact, the Foxglove app and the `mcap` CLI read it, and
writing a camera frame costs a copy of its pixels and little else: one MCAP channel per Zenoh
key, frames as Foxglove's protobuf images, every other message as JSON with its type's JSON
schema (`Recorder` says it field by field; docs/commands.md, under `archery
record`). Reading goes through `Recording` and the bounded reader `apps.topics.mcap_reader`.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Protocol

import msgspec
from mcap.records import Attachment, Channel, Header, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.writer import CompressionType, Writer

from archery.apps.topics.foxglove_records import DERIVED_SCHEMAS, schema_data
from archery.apps.topics.image_records import (
    COMPRESSED,
    RAW,
    image_from_record,
    image_record,
    image_schema,
)
from archery.apps.topics.json_image_records import json_image_from_record
from archery.apps.topics.mcap_reader import MAGIC, BadRecording, CutShort, McapFile, printable
from archery.mesh.patterns import stream_type
from archery.mesh.priority import WRITER_NICE, lower_thread_priority
from archery.protocol.codec import decode
from archery.protocol.errors import ConfigError, DecodeError
from archery.protocol.messages import MESSAGE_TYPES, SCHEMA_VERSION, Image
from archery.protocol.messages import Message as ArcheryMessage

__all__ = [
    "CALIBRATION_ATTACHMENT",
    "CALIBRATION_MEDIA_TYPE",
    "COMPRESSIONS",
    "DESCRIPTION_METADATA",
    "FORMAT",
    "PROFILE",
    "Derived",
    "FrameSource",
    "RecordStats",
    "Recorder",
    "Recording",
    "from_record",
    "message_encoding",
    "open_recording",
    "to_record",
]

log = logging.getLogger("archery.recording")


@dataclass(frozen=True)
class Derived:
    """One record a `FrameSource` derives: its channel's topic, its schema (one of
    `DERIVED_SCHEMAS`, protobuf) and the protobuf bytes."""

    topic: str
    schema: str
    data: bytes


class FrameSource(Protocol):
    """What the recorder needs of `apps.topics.robot_frames.RobotFrames` (which needs MuJoCo,
    so it is passed in, not imported here)."""

    def attachments(self) -> dict[str, tuple[str, bytes]]: ...

    def metadata(self) -> dict[str, str]: ...

    def scene_update(self, ns: int) -> Derived: ...

    def derive(self, key: str, message: ArcheryMessage, ns: int) -> list[Derived]: ...


DESCRIPTION_METADATA = "robot_description"

PROFILE = "archery"
COMPRESSIONS = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}
CALIBRATION_ATTACHMENT = "camera-calibration"  # the camera's `calibration` reply, encoded
CALIBRATION_MEDIA_TYPE = "application/msgpack"
FORMAT = "2"  # recording format: 2 = frames as protobuf; 1 (no `format` metadata) = as JSON
_IMAGES = (RAW, COMPRESSED)


def message_encoding(schema_name: str) -> str:
    """The MCAP message encoding of a schema's channel: protobuf for frames, else json."""
    return "protobuf" if schema_name in _IMAGES else "json"


def _schema_of(schema_name: str, message_type: type[ArcheryMessage]) -> tuple[str, bytes]:
    """(schema encoding, schema data) of a channel's schema."""
    if schema_name in _IMAGES:
        return "protobuf", image_schema(schema_name)
    return "jsonschema", json.dumps(msgspec.json.schema(message_type)).encode()


_json = msgspec.json.Encoder()


def to_record(message: ArcheryMessage) -> tuple[str, bytes]:
    """(schema name, bytes) of one message as the recording stores it: a frame as protobuf,
    anything else as JSON (schema `archery.TYPE`). msgspec writes floats in their shortest
    round-trip form, so decoding the JSON into the message type and encoding it as msgpack
    gives back the very bytes that were published (`tests/test_record.py` checks this, frames
    included): no float or field is lost."""
    if isinstance(message, Image):
        return image_record(message)
    return f"archery.{type(message).__name__}", _json.encode(message)


_decoders: dict[str, msgspec.json.Decoder[Any]] = {
    f"archery.{name}": msgspec.json.Decoder(cls) for name, cls in MESSAGE_TYPES.items()
}


def from_record(schema_name: str, data: bytes, schema_encoding: str = "") -> ArcheryMessage:
    """The message a record holds (validated, as on the wire); `schema_encoding` "jsonschema"
    reads a frame of the first recording format.

    Raises:
        DecodeError: an unknown schema, or data that does not fit it.
    """
    if schema_name in _IMAGES:
        if schema_encoding == "jsonschema":
            return json_image_from_record(schema_name, data)
        return image_from_record(schema_name, data)
    decoder = _decoders.get(schema_name)
    if decoder is None:
        raise DecodeError(f"unknown schema {schema_name!r} in the recording")
    try:
        return decoder.decode(data)
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        raise DecodeError(f"invalid {schema_name} record: {exc}") from None


# -- writing --------------------------------------------------------------------------------------


@dataclass
class RecordStats:
    """What a recorder has seen: per key, messages and bytes written; malformed payloads."""

    written: dict[str, int] = field(default_factory=dict)
    bytes: dict[str, int] = field(default_factory=dict)
    malformed: int = 0
    chunks: int = 0
    derived: int = 0  # records derived from the messages (the robot's transforms, …)
    missing: int = 0  # messages never seen: gaps in a key's sequence numbers
    overflow: int = 0  # messages dropped because the writer fell `max_pending` bytes behind

    @property
    def total(self) -> int:
        """Messages written."""
        return sum(self.written.values())


class Recorder:
    """Writes messages arriving on any thread (`put`) into an MCAP file from its own thread.

    The format:

    - One MCAP channel per Zenoh key (the topic is the key, e.g. `icubSim/cam/target:o`),
      chunked (lz4 by default; zstd or none on request), with message and chunk indexes,
      statistics and summary offsets.
    - Camera frames use Foxglove's well-known schemas as protobuf, `foxglove.RawImage` (rgb8,
      bgr8, mono8) or `foxglove.CompressedImage` (jpeg, png), with the fields of `Image`
      Foxglove has no place for added (`apps.topics.image_records`): the pixels are written
      as raw bytes, and Foxglove's Image panel shows them.
    - Every other message is JSON (message encoding `json`) with its own type's JSON schema
      (`msgspec.json.schema`, schema encoding `jsonschema`), named `archery.TYPE`
      (`to_record`).
    - The header's profile is `archery`; a metadata record `archery` holds the message schema
      version, the recording format (`FORMAT`), the robot, the key patterns and the start
      time. A replay refuses another message schema version (`open_recording`).
    - A message's log time is when the recorder received it, its publish time the sender's
      stamp, its sequence the sender's seq.

    Crash safety: the writer closes a chunk at least every `flush_interval` s and whenever it
    holds `chunk_size` bytes, and hands each closed chunk to the OS at once; a recorder killed
    with SIGKILL leaves a file without a summary whose complete chunks all read back
    (`Recording.messages(recover=True)`): at most the chunk in progress is lost.

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
        attachments: {name: (media type, data)} written as MCAP attachments before any
            message (e.g. `CALIBRATION_ATTACHMENT`, the camera's calibration frame and marks).
        frames: derives the robot's 3D records (`apps.topics.robot_frames.RobotFrames`):
            its description as an attachment and metadata, its scene written first, and the
            records it derives from each message written after that message.
        writer_nice: the writer thread's niceness on top of the process's, in the SCHED_IDLE
            class (`put` runs on the receiving threads, which keep theirs; 0: the writer
            keeps them too): on a busy machine the decoding, compression and writing wait for
            idle CPU, with the queue (`max_pending`) holding what arrived meanwhile, rather
            than slow the session recorded.

    Losses are counted, never guessed: `stats.missing` counts the gaps in each key's sequence
    numbers (messages dropped before they reached the recorder, or by the full queue).
    """

    def __init__(
        self,
        path: Path,
        robot: str,
        patterns: list[str],
        *,
        compression: str = "lz4",
        chunk_size: int = 4 * 1024 * 1024,
        flush_interval: float = 1.0,
        max_pending: int = 1 << 30,
        attachments: dict[str, tuple[str, bytes]] | None = None,
        frames: FrameSource | None = None,
        writer_nice: int = WRITER_NICE,
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
                "format": FORMAT,
                "robot": robot,
                "patterns": " ".join(patterns),
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            },
        )
        now = time.time_ns()
        attachments = dict(attachments or {})
        if frames is not None:
            self._writer.add_metadata(DESCRIPTION_METADATA, frames.metadata())
            attachments |= frames.attachments()
        for name, (media_type, data) in attachments.items():
            self._writer.add_attachment(now, now, name, media_type, data)
        self.stats = RecordStats()
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._frames = frames
        if frames is not None:
            self._add_derived(frames.scene_update(now), now)
        self._writer.flush()
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
        # the writer thread's niceness (None: unchanged, or not Linux)
        self.writer_niceness = (
            lower_thread_priority(writer_nice, self._thread.native_id, idle=True)
            if writer_nice
            else None
        )

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
                encoding, schema = _schema_of(schema_name, type(message))
                schema_id = self._writer.register_schema(schema_name, encoding, schema)
                self._schemas[schema_name] = schema_id
            channel = self._writer.register_channel(key, message_encoding(schema_name), schema_id)
            self._channels[(key, schema_name)] = channel
        return channel

    def _add_derived(self, record: Derived, log_ns: int) -> None:
        channel = self._channels.get((record.topic, record.schema))
        if channel is None:
            schema_id = self._schemas.get(record.schema)
            if schema_id is None:
                data = schema_data(record.schema)
                schema_id = self._writer.register_schema(record.schema, "protobuf", data)
                self._schemas[record.schema] = schema_id
            channel = self._writer.register_channel(record.topic, "protobuf", schema_id)
            self._channels[(record.topic, record.schema)] = channel
        self._writer.add_message(channel, log_time=log_ns, data=record.data, publish_time=log_ns)
        self.stats.derived += 1

    def _malformed(self, key: str, exc: Exception) -> None:
        """Count a message skipped as malformed; log the first ten."""
        self.stats.malformed += 1
        if self.stats.malformed <= 10:
            log.warning("skipped a malformed message on %s: %s", key, exc)

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
            self._malformed(key, exc)
            return
        last = self._seqs.get(key)
        if last is not None and message.seq > last + 1:
            self.stats.missing += message.seq - last - 1
        self._seqs[key] = message.seq  # a lower seq: its sender restarted
        try:
            schema_name, data = to_record(message)
        except ValueError as exc:  # an rgb8_lz4 frame whose block does not decode
            self._malformed(key, exc)
            return
        channel = self._channel(key, schema_name, message)
        self._writer.add_message(
            channel,
            log_time=received_ns,
            data=data,
            publish_time=int(message.stamp * 1e9),
            sequence=message.seq & 0xFFFFFFFF,
        )
        if self._frames is not None:
            for record in self._frames.derive(key, message, int(message.stamp * 1e9)):
                self._add_derived(record, received_ns)
        self._dirty = True
        self.stats.written[key] = self.stats.written.get(key, 0) + 1
        self.stats.bytes[key] = self.stats.bytes.get(key, 0) + len(payload)

    def _work(self) -> None:
        last_flush = time.monotonic()
        while True:
            # nothing unflushed: wait for the next message, not for a flush due (no busy loop)
            timeout = (
                max(0.0, last_flush + self._flush_interval - time.monotonic())
                if self._dirty
                else None
            )
            try:
                item = self._queue.get(timeout=timeout)
            except queue.Empty:
                item = ()  # type: ignore[assignment]  # (): nothing to write, flush check only
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

    Reading goes through `apps.topics.mcap_reader`: one chunk decompressed at a time, record
    and chunk sizes, the decompressed total and every time checked before use (`max_bytes`,
    the verbs' `--max-bytes`, sets the total's cap); a malformed file is one `ConfigError`
    line. Recordings of the first format (frames as JSON with base64 pixels) are still read.

    Attributes:
        path: the file.
        complete: it has its summary and footer (False: cut short, e.g. a killed recorder).
        metadata: the `archery` metadata record.
        message_count: messages in it (complete files only; else None).
        max_bytes: the cap on what its chunks decompress to in all (bytes;
            `apps.topics.read_limits.total_cap`: None, the default; 0, none).
    """

    path: Path
    complete: bool
    metadata: dict[str, str]
    message_count: int | None
    max_bytes: int | None = None

    def _open(self, stream: IO[bytes]) -> McapFile:
        return McapFile(
            stream, self.path.stat().st_size, max_bytes=self.max_bytes, validate_crcs=True
        )

    def attachment(self, name: str) -> bytes | None:
        """The data of the attachment `name` (the first of that name), or None.

        Raises:
            ConfigError: the file's records cannot be read.
        """
        with open(self.path, "rb") as stream:
            try:
                for record in self._open(stream).records(open_chunks=False):
                    if isinstance(record, Attachment) and record.name == name:
                        return bytes(record.data)
            except CutShort:
                return None  # a file cut short: the attachments it holds come first
            except (BadRecording, OSError) as exc:
                raise ConfigError(f"{self.path}: unreadable attachment ({exc})") from None
        return None

    def leading_metadata(self, name: str) -> dict[str, str] | None:
        """The metadata record `name` among those the recorder writes before any message (the
        robot description's: `DESCRIPTION_METADATA`), or None.

        Raises:
            ConfigError: the file's first records cannot be read.
        """
        with open(self.path, "rb") as stream:
            try:
                for record in self._open(stream).records(open_chunks=False):
                    if isinstance(record, Metadata):
                        if record.name == name:
                            return dict(record.metadata)
                    elif not isinstance(record, Header):
                        return None
            except (BadRecording, OSError) as exc:
                raise ConfigError(f"{self.path}: unreadable metadata ({exc})") from None
        return None

    def messages(
        self, *, recover: bool = False, topics: Collection[str] | None = None
    ) -> Iterator[tuple[str, ArcheryMessage, int]]:
        """(key, message, log time ns) in file order (the order they were received), one chunk
        decompressed at a time (`apps.topics.mcap_reader` says within which bounds).

        Args:
            recover: for a file cut short: yield what its complete records hold, then stop.
            topics: only the messages of these keys (the others are not decoded); None: all.

        Raises:
            ConfigError: the file is cut short and `recover` is not set, or a record is
                corrupt or above a cap (one line).
            DecodeError: a message that does not decode as its schema says.
        """
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        with open(self.path, "rb") as stream:
            records = self._open(stream).records()
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    return
                except CutShort as exc:
                    if recover:
                        return
                    raise ConfigError(
                        f"{self.path}: unreadable record (cut short: {exc})"
                    ) from None
                except (BadRecording, OSError) as exc:
                    raise ConfigError(f"{self.path}: unreadable record ({exc})") from None
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, McapMessage):
                    channel = channels.get(record.channel_id)
                    if channel is None:
                        raise ConfigError(
                            f"{self.path}: a message on channel {record.channel_id}, which no "
                            f"channel record before it declares"
                        )
                    if topics is not None and channel.topic not in topics:
                        continue
                    schema = schemas.get(channel.schema_id)
                    if schema is None:
                        raise ConfigError(
                            f"{self.path}: channel {printable(channel.topic)} has no schema"
                        )
                    if schema.name in DERIVED_SCHEMAS:
                        continue  # derived by the recorder (3D records): no mesh message
                    message = from_record(schema.name, record.data, schema.encoding)
                    yield channel.topic, message, record.log_time


def open_recording(path: str | Path, *, max_bytes: int | None = None) -> Recording:
    """Check that `path` is an MCAP recording of this schema version.

    Args:
        max_bytes: the cap on what its chunks decompress to in all, when read (bytes; None:
            `apps.topics.read_limits.total_cap`'s default; 0: none).

    Raises:
        ConfigError: no such file, not MCAP, not an archery recording, another schema
            version, or a header or summary that does not read; one line saying which.
    """
    path = Path(path)
    try:
        with open(path, "rb") as stream:
            head = stream.read(len(MAGIC))
            if head != MAGIC:
                raise ConfigError(f"{str(path)!r} is not an MCAP file (no MCAP magic at its start)")
            reader = McapFile(stream, path.stat().st_size)
            metadata, profile = _head_metadata(reader, path)
            complete, count = _summary(reader, path)
    except OSError as exc:
        raise ConfigError(f"{str(path)!r}: {exc.strerror}") from None
    if profile != PROFILE or metadata is None:
        raise ConfigError(
            f"{str(path)!r} is an MCAP file but not an archery recording "
            f"(profile {printable(profile)!r})"
        )
    version = metadata.get("schema_version", "?")
    if version != str(SCHEMA_VERSION):
        raise ConfigError(
            f"{str(path)!r} was recorded with message schema version {printable(version)}; this "
            f"version of archery replays version {SCHEMA_VERSION} only"
        )
    return Recording(path, complete, metadata, count, max_bytes)


def _head_metadata(reader: McapFile, path: Path) -> tuple[dict[str, str] | None, str]:
    """The `archery` metadata record and the header's profile, read from the file's start (the
    recorder writes them before any message)."""
    profile = ""
    try:
        for record in reader.records(open_chunks=False):
            if isinstance(record, Header):
                profile = record.profile
            elif isinstance(record, Metadata):
                if record.name == PROFILE:
                    return dict(record.metadata), profile
            else:
                break
    except BadRecording as exc:
        raise ConfigError(f"{str(path)!r}: a corrupt MCAP header ({exc})") from None
    return None, profile


def _summary(reader: McapFile, path: Path) -> tuple[bool, int | None]:
    """(has a readable summary and footer, its message count).

    Raises:
        ConfigError: a summary that is there but does not read.
    """
    try:
        summary = reader.summary()
    except BadRecording as exc:
        raise ConfigError(f"{str(path)!r}: a corrupt MCAP summary ({exc})") from None
    if summary is None or summary.statistics is None:
        return False, None
    return True, summary.statistics.message_count
