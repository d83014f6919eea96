"""`archery info FILE.mcap`: what a recording holds, like `ros2 bag info`.

It prints the file's size, profile and library, its duration, start and end, the message count,
then one line per channel (topic, schema and its encoding, message count, mean rate over the
recording) and the attachments and metadata records. A file cut short (a killed recorder: no
summary) is read record by record within the bounds of `apps.topics.mcap_reader`
(`--max-bytes` sets the cap on the decompressed total), as far as it goes; what was read is
printed, then one line on stderr says where it stops (or what is malformed), and the exit
status is 2, as for a file that is no MCAP at all. Any MCAP file is described, not only archery
recordings; text from the file is printed with its control characters escaped.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import (
    Attachment,
    Channel,
    Header,
    Message,
    Metadata,
    Schema,
)

from archery.apps.topics.mcap_reader import MAGIC, BadRecording, CutShort, McapFile
from archery.apps.topics.read_limits import add_max_bytes_arg, printable
from archery.mesh.cliargs import ArgumentParser
from archery.protocol.exit_status import BAD_INPUT, OK

__all__ = ["RecordingInfo", "main", "read_info"]


@dataclass
class RecordingInfo:
    """What `read_info` found in an MCAP file (times in ns since the epoch, sizes in bytes).

    Attributes:
        complete: the file has its summary (else `stopped` says where reading ended).
    """

    path: Path
    size: int
    profile: str = ""
    library: str = ""
    complete: bool = False
    start_ns: int | None = None
    end_ns: int | None = None
    schemas: dict[int, tuple[str, str]] = field(default_factory=dict)  # id: (name, encoding)
    channels: dict[int, Channel] = field(default_factory=dict)
    counts: dict[int, int] = field(default_factory=dict)  # channel id: messages
    attachments: list[tuple[str, str, int]] = field(default_factory=list)  # name, media, size
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    stopped: str | None = None

    @property
    def messages(self) -> int:
        """Messages in the file (as far as it was read)."""
        return sum(self.counts.values())

    @property
    def duration_s(self) -> float:
        """First to last message (s); 0 without messages."""
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9

    def _seen(self, log_time: int) -> None:
        self.start_ns = log_time if self.start_ns is None else min(self.start_ns, log_time)
        self.end_ns = log_time if self.end_ns is None else max(self.end_ns, log_time)


def _from_summary(info: RecordingInfo, reader: McapFile) -> bool:
    """Fill `info` from the file's summary; False when it has none (a file cut short) or it
    does not read (the records are scanned then, and say where they stop)."""
    try:
        header = reader.header()
        summary = reader.summary()
        if summary is None or summary.statistics is None:
            return False
        metadata = {}
        for index in summary.metadata_indexes:
            record = reader.record_at(index.offset)
            if isinstance(record, Metadata):
                metadata[record.name] = dict(record.metadata)
    except (BadRecording, OSError):
        return False
    stats = summary.statistics
    info.profile, info.library = header.profile, header.library
    info.schemas = {i: (s.name, s.encoding) for i, s in summary.schemas.items()}
    info.channels = dict(summary.channels)
    info.counts = {i: stats.channel_message_counts.get(i, 0) for i in summary.channels}
    if stats.message_count:
        info.start_ns, info.end_ns = stats.message_start_time, stats.message_end_time
    info.attachments = [(a.name, a.media_type, a.data_size) for a in summary.attachment_indexes]
    info.metadata = metadata
    info.complete = True
    return True


def _scan(info: RecordingInfo, reader: McapFile) -> None:
    """Fill `info` record by record, chunk by chunk, as far as the file reads; `stopped` says
    why it ends."""
    try:
        for record in reader.records():
            if isinstance(record, Header):
                info.profile, info.library = record.profile, record.library
            elif isinstance(record, Schema):
                info.schemas[record.id] = (record.name, record.encoding)
            elif isinstance(record, Channel):
                info.channels[record.id] = record
                info.counts.setdefault(record.id, 0)
            elif isinstance(record, Message):
                info.counts[record.channel_id] = info.counts.get(record.channel_id, 0) + 1
                info._seen(record.log_time)
            elif isinstance(record, Attachment):
                info.attachments.append((record.name, record.media_type, len(record.data)))
            elif isinstance(record, Metadata):
                info.metadata[record.name] = dict(record.metadata)
    except CutShort as exc:
        info.stopped = f"cut short: {exc}"
        return
    except BadRecording as exc:
        info.stopped = f"unreadable: {exc}"
        return
    except OSError as exc:
        info.stopped = f"unreadable: {exc.strerror}"
        return
    info.stopped = "cut short: it has no summary (a recorder that did not finish)"


def read_info(path: Path, *, max_bytes: int | None = None) -> RecordingInfo:
    """What the MCAP file at `path` holds (`max_bytes`: the cap on what its chunks decompress
    to in all, `apps.topics.read_limits.total_cap`).

    A complete file is read from its summary (its end) alone, so even a large recording answers
    at once; a file cut short is read record by record, one chunk decompressed at a time, as
    far as it goes (`stopped` says where and why it stops).

    Raises:
        ValueError: no such file, or not an MCAP file (one line saying which).
    """
    try:
        size = path.stat().st_size
        with open(path, "rb") as stream:
            if stream.read(len(MAGIC)) != MAGIC:
                raise ValueError(f"{str(path)!r} is not an MCAP file (no MCAP magic at its start)")
            info = RecordingInfo(path, size)
            if not _from_summary(info, McapFile(stream, size, max_bytes=max_bytes)):
                info = RecordingInfo(path, size)
                _scan(info, McapFile(stream, size, max_bytes=max_bytes))
    except IsADirectoryError:
        raise ValueError(f"{str(path)!r} is a folder, not an MCAP file") from None
    except OSError as exc:
        raise ValueError(f"{str(path)!r}: {exc.strerror}") from None
    return info


def _size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} GiB"


def _when(ns: int | None) -> str:
    if ns is None:
        return "–"
    seconds, ms = ns // 1_000_000_000, (ns // 1_000_000) % 1000
    stamp = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(seconds))
    return f"{stamp}.{ms:03d} UTC ({seconds}.{ms:03d})"


def render(info: RecordingInfo) -> str:
    """The report `archery info` prints."""
    duration = info.duration_s
    lines = [
        f"File:          {info.path}",
        f"Size:          {_size(info.size)} ({info.size} bytes)"
        + ("" if info.complete else ", cut short"),
        f"Storage:       mcap, profile {printable(info.profile) or '–'}, "
        f"library {printable(info.library) or '–'}",
        f"Duration:      {duration:.3f} s",
        f"Start:         {_when(info.start_ns)}",
        f"End:           {_when(info.end_ns)}",
        f"Messages:      {info.messages}",
        f"Channels:      {len(info.channels)}",
    ]
    topics = {cid: printable(c.topic) for cid, c in info.channels.items()}
    width = max((len(topic) for topic in topics.values()), default=0)
    for cid, channel in sorted(info.channels.items(), key=lambda kv: kv[1].topic):
        name, encoding = info.schemas.get(channel.schema_id, ("(no schema)", ""))
        count = info.counts.get(cid, 0)
        rate = f"{count / duration:9.2f} Hz" if duration > 0 else "        – Hz"
        encodings = printable(channel.message_encoding) + (
            ", " + printable(encoding) if encoding else ""
        )
        lines.append(
            f"  {topics[cid].ljust(width)}  {count:8d} msgs {rate}  {printable(name)} ({encodings})"
        )
    lines.append(f"Attachments:   {len(info.attachments)}")
    for name, media, size in info.attachments:
        lines.append(f"  {printable(name)}  {printable(media)}  {_size(size)}")
    lines.append(f"Metadata:      {len(info.metadata)}")
    for name, values in info.metadata.items():
        shown = ", ".join(f"{k}={v}" for k, v in values.items())
        lines.append(f"  {printable(name)}: {printable(shown[:200])}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Describe one MCAP file; exit status 2 for a non-MCAP or truncated file."""
    parser = ArgumentParser(prog="archery info", description=__doc__)
    parser.add_argument("file", type=Path, help="an MCAP file (.mcap)")
    add_max_bytes_arg(parser)
    args = parser.parse_args(argv)
    try:
        info = read_info(args.file, max_bytes=args.max_bytes)
    except ValueError as exc:
        print(f"archery info: {exc}", file=sys.stderr)
        return BAD_INPUT
    print(render(info), flush=True)
    if info.stopped is not None:
        print(f"archery info: {info.path} is {info.stopped}", file=sys.stderr)
        return BAD_INPUT
    return OK


if __name__ == "__main__":
    sys.exit(main())
