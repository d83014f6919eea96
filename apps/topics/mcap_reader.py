"""MCAP files read with bounds: the reader of recordings behind `archery info`, `archery
replay` and `archery film --recording`.

A file is read one record at a time and a chunk is decompressed only when its turn comes, so
what a reader holds is one record and one chunk's records, never the file; every length and
time the file claims is checked before it is used (`McapFile` lists the bounds). The limits
(module constants) and `printable`, how text read from a file is shown, live in
`apps.topics.read_limits`.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from io import BytesIO
from typing import IO, Any

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
)
from mcap.summary import Summary

from archery.apps.topics.read_limits import (
    MAX_RECORD_BYTES,
    MAX_TIME_NS,
    printable,
    size_text,
    total_cap,
)
from archery.protocol.errors import ConfigError

__all__ = ["MAGIC", "BadRecording", "CutShort", "McapFile", "Skipped"]

MAGIC = b"\x89MCAP0\r\n"
_HEAD = struct.Struct("<BQ")  # a record's opcode and length
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK = struct.Struct("<QQQII")  # start, end, uncompressed size and crc, compression length
_FOOTER_BYTES = _HEAD.size + 20  # a footer record: summary start, summary offset start, crc
_PARSED: dict[int, Any] = {
    Opcode.HEADER: Header,
    Opcode.FOOTER: Footer,
    Opcode.SCHEMA: Schema,
    Opcode.CHANNEL: Channel,
    Opcode.ATTACHMENT: Attachment,
    Opcode.ATTACHMENT_INDEX: AttachmentIndex,
    Opcode.METADATA: Metadata,
    Opcode.METADATA_INDEX: MetadataIndex,
    Opcode.STATISTICS: Statistics,
    Opcode.DATA_END: DataEnd,
}


class BadRecording(ConfigError):
    """A record that cannot be read as it is (malformed, or above a cap): one line, without
    the file's name."""


class CutShort(BadRecording):
    """The file ends inside a record, or before its footer (a recorder that did not finish)."""


@dataclass(frozen=True)
class Skipped:
    """A record read past without being parsed (a chunk left closed, an index): its opcode,
    where it starts and its length (bytes)."""

    opcode: int
    offset: int
    length: int


def _check_time(ns: int, what: str, offset: int) -> None:
    if ns > MAX_TIME_NS:
        raise BadRecording(
            f"the {what} of the record at byte {offset} is {ns} ns, past 2262 (an int64 of ns)"
        )


class McapFile:
    """The records of one MCAP file, read with the module's bounds.

    - A record's length against the bytes left in the file (or in its chunk): a file that ends
      inside a record is `CutShort` (a killed recorder), anything else that does not parse is
      a `BadRecording`.
    - One record as stored (a chunk's compressed bytes, an attachment) and one chunk's
      uncompressed bytes: at most `MAX_RECORD_BYTES` (256 MiB; the recorder closes a chunk at
      4 MiB, and a 3840 x 2160 rgb8 frame is 24 MiB). A chunk's claimed uncompressed size is
      checked before it is decompressed; decompression stops one byte past the claim, and what
      comes out must be exactly the claim, so a chunk that lies cannot make more.
    - The whole decompressed total: at most `total_cap(file size, max_bytes)` bytes, by default
      the greater of `MAX_TOTAL_BYTES` (1 GiB) and `MAX_EXPANSION` (64) times the file's size
      (a recording compresses a few times; 19 kB of zeros that claim gigabytes do not pass);
      the verbs' `--max-bytes` sets it.
    - Times (a message's log and publish time, a chunk's, an attachment's, the statistics'):
      ns since the epoch as an int64, at most `MAX_TIME_NS` (2262-04-11).

    Args:
        stream: the file, open for reading in binary (seekable).
        size: its size (bytes).
        max_bytes: the whole decompressed total's cap (`total_cap`: None, the default; 0, none).
        validate_crcs: check the CRCs the file holds (chunks, attachments, the data section).
    """

    def __init__(
        self,
        stream: IO[bytes],
        size: int,
        *,
        max_bytes: int | None = None,
        validate_crcs: bool = False,
    ) -> None:
        self._stream = stream
        self.size = size
        self.cap = total_cap(size, max_bytes)
        self.decompressed = 0  # bytes decompressed so far
        self._validate = validate_crcs

    def records(
        self, start: int = 0, *, open_chunks: bool = True
    ) -> Iterator[McapRecord | Skipped]:
        """The records from byte `start` (0: the magic first) to the footer, in file order: a
        chunk's schemas, channels and messages in its place (`open_chunks`), else `Skipped`;
        message and chunk indexes, summary offsets and unknown records as `Skipped`.

        Raises:
            CutShort: the file ends inside a record or before its footer.
            BadRecording: a record that does not parse, or above a cap.
        """
        stream = self._stream
        stream.seek(start)
        pos = start
        crc: int | None = None
        if start == 0:
            magic = stream.read(len(MAGIC))
            if magic != MAGIC:
                raise BadRecording("no MCAP magic at its start")
            pos = len(MAGIC)
            crc = zlib.crc32(magic) if self._validate else None
        while True:
            head = stream.read(_HEAD.size)
            if len(head) < _HEAD.size:
                raise CutShort(f"it ends at byte {pos + len(head)} without a footer")
            opcode, length = _HEAD.unpack(head)
            left = self.size - pos - _HEAD.size
            if length > left:
                raise CutShort(
                    f"the record at byte {pos} claims {length} bytes; {max(left, 0)} are left"
                )
            parse = opcode in _PARSED or (open_chunks and opcode in (Opcode.CHUNK, Opcode.MESSAGE))
            if length > MAX_RECORD_BYTES and (parse or crc is not None):  # to be read: capped
                raise BadRecording(
                    f"the record at byte {pos} holds {size_text(length)}, above the "
                    f"{size_text(MAX_RECORD_BYTES)} one record may"
                )
            if not parse and crc is None:
                stream.seek(length, 1)
                yield Skipped(opcode, pos, length)
            else:
                body = stream.read(length)
                if len(body) < length:
                    raise CutShort(f"the record at byte {pos} is cut short")
                if opcode == Opcode.DATA_END and crc is not None:
                    self._check_data_crc(body, crc, pos)
                    crc = None
                elif crc is not None:
                    crc = zlib.crc32(body, zlib.crc32(head, crc))
                if not parse:
                    yield Skipped(opcode, pos, length)
                elif opcode == Opcode.CHUNK:
                    yield from self._chunk(memoryview(body), pos)
                elif opcode == Opcode.MESSAGE:
                    yield _message(memoryview(body), pos)
                else:
                    record = self._parse(opcode, body, pos)
                    yield record
                    if opcode == Opcode.FOOTER:
                        return
            pos += _HEAD.size + length

    def header(self) -> Header:
        """The header record (the file's first).

        Raises:
            BadRecording: the file does not start with MCAP magic and a header.
        """
        for record in self.records(open_chunks=False):
            if isinstance(record, Header):
                return record
            break
        raise BadRecording("no header record at its start")

    def summary(self) -> Summary | None:
        """The summary section (schemas, channels, statistics, attachment and metadata
        indexes), or None for a file without one (cut short, or written without).

        Raises:
            BadRecording: a summary that does not read, or a footer pointing outside the file.
        """
        tail = len(MAGIC) + _FOOTER_BYTES
        if self.size < len(MAGIC) + tail:
            return None
        self._stream.seek(self.size - tail)
        end = self._stream.read(tail)
        opcode, length = _HEAD.unpack_from(end)
        if end[-len(MAGIC) :] != MAGIC or opcode != Opcode.FOOTER or length != 20:
            return None
        summary_start = struct.unpack_from("<Q", end, _HEAD.size)[0]
        if summary_start == 0:
            return None
        if not len(MAGIC) <= summary_start <= self.size - tail:
            raise BadRecording(f"its footer points to byte {summary_start}, outside the file")
        summary = Summary()
        for record in self.records(summary_start, open_chunks=False):
            if isinstance(record, Schema):
                summary.schemas[record.id] = record
            elif isinstance(record, Channel):
                summary.channels[record.id] = record
            elif isinstance(record, Statistics):
                summary.statistics = record
            elif isinstance(record, AttachmentIndex):
                summary.attachment_indexes.append(record)
            elif isinstance(record, MetadataIndex):
                summary.metadata_indexes.append(record)
        return summary

    def record_at(self, offset: int) -> McapRecord | Skipped:
        """The one record at byte `offset` (e.g. a metadata index's).

        Raises:
            BadRecording: an offset outside the file, or a record that does not read there.
        """
        if not len(MAGIC) <= offset < self.size:
            raise BadRecording(f"an index points to byte {offset}, outside the file")
        return next(self.records(offset, open_chunks=False))

    def _check_data_crc(self, body: bytes, crc: int, pos: int) -> None:
        claimed = struct.unpack_from("<I", body)[0] if len(body) >= 4 else 0
        if claimed and claimed != crc:
            raise BadRecording(f"the data section's CRC does not match (data end at byte {pos})")

    def _parse(self, opcode: int, body: bytes, pos: int) -> McapRecord:
        """A record of `_PARSED` from its body (bytes), its times and offsets checked."""
        kind = _PARSED[opcode]
        stream = ReadDataStream(BytesIO(body))
        try:
            record = kind.read(stream)
        except (McapError, struct.error, UnicodeDecodeError, ValueError) as exc:
            raise BadRecording(
                f"the {kind.__name__.lower()} record at byte {pos} does not parse "
                f"({type(exc).__name__})"
            ) from None
        if isinstance(record, Attachment):
            _check_time(record.log_time, "log time", pos)
            _check_time(record.create_time, "create time", pos)
            if self._validate:
                end = stream.count - 4
                if end < 0 or len(body) < end + 4:
                    raise BadRecording(f"the attachment record at byte {pos} is cut short")
                claimed = struct.unpack_from("<I", body, end)[0]
                if claimed and claimed != zlib.crc32(body[:end]):
                    raise BadRecording(
                        f"the attachment record at byte {pos}: its CRC does not match"
                    )
        elif isinstance(record, Statistics):
            _check_time(record.message_start_time, "message start time", pos)
            _check_time(record.message_end_time, "message end time", pos)
        elif isinstance(record, AttachmentIndex | MetadataIndex):
            if record.offset + record.length > self.size:
                raise BadRecording(f"the index at byte {pos} points past the file's end")
            if isinstance(record, AttachmentIndex) and record.data_size > record.length:
                raise BadRecording(
                    f"the attachment index at byte {pos} claims more than its record"
                )
        return record  # one of the record classes of _PARSED

    def _chunk(self, body: memoryview, pos: int) -> Iterator[McapRecord | Skipped]:
        """The schemas, channels and messages of the chunk record at `pos` (its body)."""
        if len(body) < _CHUNK.size:
            raise BadRecording(f"the chunk record at byte {pos} does not parse")
        start, end, claim, claimed_crc, name_length = _CHUNK.unpack_from(body)
        _check_time(start, "message start time", pos)
        _check_time(end, "message end time", pos)
        at = _CHUNK.size + name_length
        if at + 8 > len(body):
            raise BadRecording(f"the chunk record at byte {pos} does not parse")
        try:
            compression = str(body[_CHUNK.size : at], "utf-8")
        except UnicodeDecodeError:
            raise BadRecording(f"the chunk record at byte {pos} does not parse") from None
        data_length = struct.unpack_from("<Q", body, at)[0]
        if data_length > len(body) - at - 8:
            raise BadRecording(
                f"the chunk at byte {pos} claims {data_length} compressed bytes; its record "
                f"holds {len(body) - at - 8}"
            )
        if claim > MAX_RECORD_BYTES:
            raise BadRecording(
                f"the chunk at byte {pos} claims {size_text(claim)} uncompressed, above the "
                f"{size_text(MAX_RECORD_BYTES)} one chunk may hold"
            )
        if self.cap is not None and self.decompressed + claim > self.cap:
            raise BadRecording(
                f"its chunks decompress to more than {size_text(self.cap)} (at the chunk at "
                f"byte {pos}); --max-bytes sets that cap (0: none)"
            )
        self.decompressed += claim
        data = _decompress(compression, body[at + 8 : at + 8 + data_length], claim, pos)
        del body
        if self._validate and claimed_crc and zlib.crc32(data) != claimed_crc:
            raise BadRecording(f"the chunk at byte {pos}: its CRC does not match")
        view = memoryview(data)
        inner = 0
        while inner < len(view):
            if inner + _HEAD.size > len(view):
                raise BadRecording(f"the chunk at byte {pos} ends inside a record")
            opcode, length = _HEAD.unpack_from(view, inner)
            body_at = inner + _HEAD.size
            if length > len(view) - body_at:
                raise BadRecording(
                    f"a record in the chunk at byte {pos} claims {length} bytes, past the "
                    f"chunk's end"
                )
            record_view = view[body_at : body_at + length]
            if opcode == Opcode.MESSAGE:
                yield _message(record_view, pos)
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                yield self._parse(opcode, bytes(record_view), pos)
            else:
                yield Skipped(opcode, pos, length)
            inner = body_at + length


def _message(body: memoryview, pos: int) -> Message:
    """A message record from its body, its times checked (`pos`: where it or its chunk is)."""
    if len(body) < _MESSAGE.size:
        raise BadRecording(f"a message record at byte {pos} is shorter than its fields")
    channel_id, sequence, log_time, publish_time = _MESSAGE.unpack_from(body)
    _check_time(log_time, "log time", pos)
    _check_time(publish_time, "publish time", pos)
    return Message(
        channel_id=channel_id,
        sequence=sequence,
        log_time=log_time,
        publish_time=publish_time,
        data=bytes(body[_MESSAGE.size :]),
    )


def _decompress(compression: str, data: memoryview, claim: int, pos: int) -> bytes:
    """A chunk's `data` decompressed: exactly `claim` bytes, or BadRecording (at most
    `claim` + 1 bytes are ever made)."""
    try:
        if compression == "":
            out = bytes(data)
        elif compression == "zstd":
            with zstandard.ZstdDecompressor().stream_reader(data, read_across_frames=True) as src:
                out = src.read(claim + 1)
        elif compression == "lz4":
            out = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=claim + 1)
        else:
            raise BadRecording(
                f"the chunk at byte {pos} is compressed with {printable(compression)!r}, which "
                f"this reader does not know (zstd, lz4 or none)"
            )
    except (zstandard.ZstdError, RuntimeError, ValueError, OSError) as exc:
        if isinstance(exc, BadRecording):
            raise
        raise BadRecording(f"the chunk at byte {pos} does not decompress ({exc})") from None
    if len(out) != claim:
        more = "more" if len(out) > claim else f"{len(out)} bytes"
        raise BadRecording(
            f"the chunk at byte {pos} claims {claim} bytes uncompressed but holds {more}"
        )
    return out
