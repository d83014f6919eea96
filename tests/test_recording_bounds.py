"""Reading an MCAP file is bounded and checked: a chunk that decompresses to far more than the
file, or claims to, a record or attachment whose lengths do not fit, a time past 2262 and
names holding terminal escapes end in one line on stderr and exit status 2 (`archery info`,
`replay`, `film --recording`), with the reader's memory independent of the chunk's claim."""

from __future__ import annotations

import struct
from pathlib import Path

import lz4.frame
import pytest
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.records import (
    Attachment,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Metadata,
    Statistics,
)
from mcap.writer import Writer

from archery.apps.film.recorded import RecordedShot
from archery.apps.topics.info import read_info, render
from archery.apps.topics.mcap_reader import MAGIC, BadRecording, McapFile
from archery.apps.topics.read_limits import (
    MAX_RECORD_BYTES,
    MAX_TOTAL_BYTES,
    byte_size,
    printable,
    total_cap,
)
from archery.apps.topics.recording import open_recording, to_record
from archery.mesh.netflags import NetConfig
from archery.protocol.errors import ConfigError
from archery.protocol.journal_records import DoneRecord
from archery.protocol.messages import SCHEMA_VERSION, WorldEvent
from tests.peak_rss import run_with_peak

BOMB_BYTES = 600 << 20  # what the bombs decompress to
RSS_LIMIT_MIB = 300  # a reader's own peak RSS must stay below (the bombs took 1.27 GB)
ESC = "\x1b"


def _records(*records: McapRecord) -> bytes:
    builder = RecordBuilder()
    for record in records:
        record.write(builder)
    return bytes(builder.end())


def _chunk(compression: str, data: bytes, claim: int) -> bytes:
    """A chunk record by hand: any claim, any data."""
    name = compression.encode()
    body = struct.pack("<QQQII", 0, 0, claim, 0, len(name)) + name
    body += struct.pack("<Q", len(data)) + data
    return struct.pack("<BQ", 0x06, len(body)) + body


def _recording(path: Path, *middle: bytes, summary: bool = True) -> Path:
    """An archery recording by hand: header, its metadata, `middle` (raw records), and a
    summary (statistics) or none."""
    metadata = {"schema_version": str(SCHEMA_VERSION), "robot": "icubSim"}
    data = MAGIC + _records(Header("archery", "test"), Metadata("archery", metadata))
    data += b"".join(middle) + _records(DataEnd(0))
    if summary:
        stats = Statistics(0, 0, {}, 1, 0, 0, 0, 1, 0)
        data += _records(stats, Footer(len(data), 0, 0))
    else:
        data += _records(Footer(0, 0, 0))
    path.write_bytes(data + MAGIC)
    return path


def _zeros(compressor: object, first: bytes, n: int) -> bytes:
    """`first` then zeros, `n` bytes in all, through a streaming compressor (never held)."""
    out = [compressor.compress(first)]  # type: ignore[attr-defined]
    block = bytes(1 << 20)
    left = n - len(first)
    while left:
        k = min(left, len(block))
        out.append(compressor.compress(block if k == len(block) else block[:k]))  # type: ignore[attr-defined]
        left -= k
    out.append(compressor.flush())  # type: ignore[attr-defined]
    return b"".join(out)


@pytest.fixture(scope="module")
def bombs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    """Chunk records of a few kB that decompress to 600 MiB (one unknown record and zeros):
    claiming it (zstd, 19 kB), claiming 1 KiB (lz4), or claiming 2^40 bytes."""
    inner = struct.pack("<BQ", 0x80, BOMB_BYTES - 9)
    zstd = _zeros(zstandard.ZstdCompressor(level=1).compressobj(), inner, BOMB_BYTES)
    lz4_compressor = lz4.frame.LZ4FrameCompressor()
    lz4_data = lz4_compressor.begin() + _zeros(lz4_compressor, inner, BOMB_BYTES)
    return {
        "zstd": _chunk("zstd", zstd, BOMB_BYTES),
        "lying": _chunk("lz4", lz4_data, 1024),
        "huge": _chunk("zstd", zstd, 1 << 40),
    }


def _run(*args: str) -> tuple[int, str, str, float]:
    """`archery ARGS` in a child: (exit status, stdout, stderr, its own peak RSS in MiB)."""
    done = run_with_peak(*args)
    return done.status, done.stdout, done.stderr, done.peak_mib


def _one_line(stderr: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    return lines[0]


def _net_flags(net: NetConfig) -> list[str]:
    return ["--connect", net.connect[0], "--robot", net.robot]


@pytest.mark.parametrize("kind", ["zstd", "lying", "huge"])
def test_info_refuses_a_chunk_bomb_in_bounded_memory(
    bombs: dict[str, bytes], kind: str, tmp_path: Path
) -> None:
    # without a summary, info reads the chunks: this one is refused before it is decompressed
    path = _recording(tmp_path / f"{kind}.mcap", bombs[kind], summary=False)
    assert path.stat().st_size < 3 << 20
    status, stdout, stderr, rss = _run("info", str(path))
    line = _one_line(stderr)
    assert status == 2 and line.startswith(f"archery info: {path} is unreadable"), line
    assert "Messages:" in stdout
    assert rss < RSS_LIMIT_MIB, f"archery info peaked at {rss:.0f} MiB"


def _strip_summary(data: bytes) -> bytes:
    """The file with a footer that points to no summary (as a writer without one leaves it)."""
    footer_at = len(data) - len(MAGIC) - 29
    start = struct.unpack_from("<Q", data, footer_at + 9)[0]
    return data[:start] + _records(Footer(0, 0, 0)) + MAGIC


@pytest.mark.parametrize("kind", ["zstd", "lying", "huge"])
def test_replay_refuses_a_chunk_bomb_in_bounded_memory(
    bombs: dict[str, bytes], kind: str, net: NetConfig, tmp_path: Path
) -> None:
    path = _recording(tmp_path / f"{kind}.mcap", bombs[kind])
    status, _, stderr, rss = _run("replay", str(path), "--rate", "1000", *_net_flags(net))
    line = _one_line(stderr)
    assert status == 2 and "unreadable record" in line, line
    assert ("256 MiB" in line) == (kind != "lying") and ("holds more" in line) == (kind == "lying")
    assert rss < RSS_LIMIT_MIB, f"archery replay peaked at {rss:.0f} MiB"


def test_film_refuses_a_chunk_claiming_a_terabyte(bombs: dict[str, bytes], tmp_path: Path) -> None:
    path = _recording(tmp_path / "huge.mcap", bombs["huge"])
    done = DoneRecord(
        session="s",
        index=1,
        rollout=1,
        theta=[0.0, 0.0, 0.0],
        r_m=[0.0, 0.0],
        distance_m=0.0,
        hit=False,
    )
    with pytest.raises(ConfigError, match="claims 1 TiB uncompressed, above the 256 MiB"):
        RecordedShot(path, "s", done)


def test_the_decompressed_total_is_capped_and_max_bytes_sets_the_cap(tmp_path: Path) -> None:
    inner = struct.pack("<BQ", 0x80, (1 << 20) - 9) + bytes((1 << 20) - 9)  # one unknown record
    chunk = _chunk("zstd", zstandard.ZstdCompressor().compress(inner), 1 << 20)
    path = _recording(tmp_path / "many.mcap", *[chunk] * 3)
    size = path.stat().st_size
    assert total_cap(size) == MAX_TOTAL_BYTES and total_cap(size, 0) is None
    assert total_cap(1 << 30) == 64 << 30 and total_cap(size, 5) == 5
    with open(path, "rb") as stream:
        reader = McapFile(stream, size, max_bytes=(2 << 20) + 5)
        with pytest.raises(BadRecording, match=r"more than 2 MiB .*--max-bytes"):
            for _ in reader.records():
                pass
        assert reader.decompressed == 2 << 20
    scan = tmp_path / "many-scan.mcap"
    scan.write_bytes(_strip_summary(path.read_bytes()))
    status, _, stderr, _ = _run("info", str(scan), "--max-bytes", "2M")
    assert status == 2 and "--max-bytes sets that cap" in _one_line(stderr)
    status, _, stderr, _ = _run("info", str(scan), "--max-bytes", "3M")
    assert status == 2 and "no summary" in _one_line(stderr)
    assert byte_size("4G") == 4 << 30 and byte_size("512MiB") == 512 << 20 and byte_size("7") == 7
    assert MAX_RECORD_BYTES == 256 << 20


def _writer_file(path: Path, log_times: list[int], **names: str) -> Path:
    """A recording written by the mcap library's writer: events at `log_times`; `names` may
    replace the topic, schema, metadata and attachment names."""
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start(profile="archery", library="test")
        metadata = {"schema_version": str(SCHEMA_VERSION), "robot": "icubSim"}
        writer.add_metadata("archery", metadata)
        if "metadata" in names:
            writer.add_metadata(names["metadata"], {names["metadata"]: names["metadata"]})
        if "attachment" in names:
            writer.add_attachment(1, 1, names["attachment"], names["attachment"], b"abc")
        schema_name, data = to_record(WorldEvent(kind="reset", seq=1))
        schema = writer.register_schema(names.get("schema", schema_name), "jsonschema", b"{}")
        topic = names.get("topic", "icubSim/world/events:o")
        channel = writer.register_channel(topic, "json", schema)
        for i, log_time in enumerate(log_times):
            writer.add_message(channel, log_time=log_time, data=data, publish_time=1, sequence=i)
        writer.finish()
    return path


def test_a_time_past_2262_is_one_line_and_exit_2(tmp_path: Path, net: NetConfig) -> None:
    start = 1_800_000_000_000_000_000
    path = _writer_file(tmp_path / "late.mcap", [start, 2**64 - 1])
    # info: the summary's end time is refused, the records say which one is wrong
    status, stdout, stderr, _ = _run("info", str(path))
    line = _one_line(stderr)
    assert status == 2 and "past 2262" in line and "Messages:" in stdout, line
    with pytest.raises(ConfigError, match=r"corrupt MCAP summary .*past 2262"):
        open_recording(path)
    # replay: refused with its summary; read without one (--recover), refused at the chunk
    status, stdout, stderr, _ = _run("replay", str(path), *_net_flags(net))
    line = _one_line(stderr)
    assert status == 2 and "past 2262" in line, line
    cut = tmp_path / "late-cut.mcap"
    cut.write_bytes(_strip_summary(path.read_bytes()))
    status, stdout, stderr, _ = _run("replay", str(cut), "--recover", *_net_flags(net))
    line = _one_line(stderr)
    assert status == 2 and "unreadable record" in line and "past 2262" in line, line
    # the last int64 ns is a time, and is shown
    fine = _writer_file(tmp_path / "fine.mcap", [start, 2**63 - 1])
    status, stdout, stderr, _ = _run("info", str(fine))
    assert status == 0 and "2262-04-11 23:47:16" in stdout, stderr


def test_an_attachment_longer_than_its_record_or_the_file_is_one_line(tmp_path: Path) -> None:
    name, media = "camera-calibration", "application/msgpack"
    record = _records(Attachment(1, 1, name, media, b"x" * 64))
    head = 9 + 8 + 8 + 4 + len(name) + 4 + len(media)  # where its data length is
    lying = record[:head] + struct.pack("<Q", 1 << 20) + record[head + 8 :]  # 1 MiB claimed
    path = _recording(tmp_path / "attachment.mcap", lying)
    with pytest.raises(ConfigError, match=r"unreadable attachment .*the attachment record"):
        open_recording(path).attachment(name)
    scan = _recording(tmp_path / "attachment-scan.mcap", lying, summary=False)
    status, _, stderr, _ = _run("info", str(scan))
    line = _one_line(stderr)
    assert status == 2 and "the attachment record at byte" in line, line
    # a file cut inside the attachment's data length
    whole = _recording(tmp_path / "whole.mcap", record, summary=False).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole[: whole.index(record) + head + 3])
    status, stdout, stderr, _ = _run("info", str(cut))
    line = _one_line(stderr)
    assert status == 2 and line.startswith(f"archery info: {cut} is cut short"), line
    assert "Metadata:      1" in stdout


def test_names_from_the_file_are_printed_with_their_escapes_shown(tmp_path: Path) -> None:
    evil = {
        "topic": f"icubSim/{ESC}[31mred:o",
        "schema": f"archery.{ESC}]0;title\x07",
        "metadata": f"m{ESC}[2J",
        "attachment": f"a{ESC}[1m\u202e",
    }
    path = _writer_file(tmp_path / "evil.mcap", [1, 2], **evil)
    status, stdout, stderr, _ = _run("info", str(path))
    assert status == 0, stderr
    assert ESC not in stdout and "\x07" not in stdout and "\u202e" not in stdout
    assert "icubSim/\\x1b[31mred:o" in stdout and "archery.\\x1b]0;title\\x07" in stdout
    assert "m\\x1b[2J" in stdout and "a\\x1b[1m\\u202e" in stdout
    text = render(read_info(path))
    assert ESC not in text
    assert printable("plain/key:o") == "plain/key:o" and printable("a\tb\n") == "a\\x09b\\x0a"


def test_a_record_above_the_cap_is_refused_unread(tmp_path: Path) -> None:
    path = _recording(tmp_path / "big.mcap", summary=False)
    head = path.read_bytes()[: -len(MAGIC) - 29 - 13]  # up to its data end record
    big = MAX_RECORD_BYTES + (1 << 20)
    with open(path, "wb") as stream:  # a sparse file: the record's zeros take no disk
        stream.write(head + struct.pack("<BQ", 0x09, big))
        stream.truncate(len(head) + 9 + big)
    status, stdout, stderr, rss = _run("info", str(path))
    line = _one_line(stderr)
    assert status == 2 and "holds 257 MiB, above the 256 MiB one record may" in line, line
    assert "Metadata:      1" in stdout and rss < RSS_LIMIT_MIB
